"""Measurements of the simulator (fidelity against ground truth, speed), installed as `drivesim.bench`.

Like the CLI, a bench may import `stages`, `sim` and `pipeline`; no stage imports a bench.
"""
