"""drivesim command line."""
