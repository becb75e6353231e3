"""Helpers the benchmark scripts share (not installed): the markdown report writer (`report.py`) and the folders of
the test fixtures and research probes a script reuses, put on the import path (`paths.py`).

A script run as `python benchmarks/bench_x.py` has `benchmarks/` first on its path and imports these as `_lib.*`.
"""
