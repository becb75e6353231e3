"""`drivesim eval`: offline closed-loop evaluation with the paper's metrics, plots and an HTML report."""
