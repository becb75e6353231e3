"""The installed diagnostics behind `drivesim bench`: measurements of the simulator (fidelity against ground truth,
speed, real lateral views), and fixture recordings shared with the tests. Not the benchmark scripts: those are in
`benchmarks/` (not installed) and write `benchmarks/RESULTS.md`.

Like the CLI, a diagnostic may import `stages`, `sim` and `pipeline`; no stage imports one.
"""
