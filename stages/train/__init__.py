"""`drivesim train`: PPO with a CNN and an LSTM in the simulator (the tasks of sim/envs/registry.py)."""
