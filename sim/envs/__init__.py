"""The driving tasks as gymnasium environments: drivesim/Lane-v0, drivesim/Follow-v0, drivesim/Overtake-v0."""
