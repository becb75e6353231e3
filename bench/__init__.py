"""The measurements behind `drivesim bench`: the simulator against ground truth (`fidelity.py`, `car_fidelity.py`),
its speed (`sim_speed.py`, `sim_steps.py`), real stereo pairs (`stereo.py`), and the machine line of every report
(`machine.py`). The benchmark scripts (`benchmarks/`, not installed) reuse them.

Like the CLI, a measurement may import `chain`, `stages`, `policy`, `sim` and `pipeline`; none of those imports it.
"""
