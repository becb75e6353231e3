"""`drivesim train`: PPO with a CNN and an LSTM in the simulator (tasks lane, follow, overtake)."""
