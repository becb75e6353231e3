"""ONNX export of a trained run (issue 10): torch vs onnxruntime over a 200-step rollout with a reset in the middle,
and the ONNX policy's latency per step on one thread (the car runs it at 30 Hz).

    .venv/bin/python benchmarks/bench_export.py --workspace drivesim-work     # its newest finished run

Exports into a temporary workspace (the run is read, never changed) with `run_export`, the code behind
`drivesim export onnx`, and writes benchmarks/results/export.md from the stage's summary.
"""

from __future__ import annotations

import argparse
import tempfile
from datetime import UTC, datetime
from pathlib import Path

from _lib.report import write_markdown

from drivesim.bench.machine import machine_line
from drivesim.pipeline.workspace import Workspace
from drivesim.policy.run_folder import latest_run
from drivesim.stages.export.config import ExportConfig
from drivesim.stages.export.stage import run_export

RESULTS = Path(__file__).resolve().parent / "results" / "export.md"
BUDGET_MS = 1000 / 30


def main() -> None:
    """Export the run, then write the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True, help="workspace holding runs/")
    parser.add_argument("--run", type=Path, default=None, help="run folder (default: the newest finished run)")
    args = parser.parse_args()
    run = args.run or latest_run(Workspace(args.workspace))
    if run is None:
        raise SystemExit(f"{args.workspace}: no finished run; run `drivesim train` first")
    with tempfile.TemporaryDirectory(prefix="bench-export-") as tmp:
        s = run_export(Workspace(tmp), ExportConfig(run=str(Path(run).absolute()))).summary
    lines = [
        "# Export: the policy as one ONNX graph",
        "",
        f"Machine: {machine_line()}. Date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC. Run: `{run}` ({s.task}). "
        f"Command: `python benchmarks/bench_export.py --workspace {args.workspace}`.",
        "",
        "| measure | value |",
        "|---|---:|",
        f"| largest abs. steering difference, torch vs onnxruntime, 200 steps with a reset | {s.max_abs_diff:.1e} |",
        f"| largest LSTM-state difference relative to its magnitude | {s.max_rel_diff_state:.1e} |",
        f"| latency per step, one thread, median | {s.latency_median_ms:.2f} ms |",
        f"| latency per step, one thread, p99 | {s.latency_p99_ms:.2f} ms |",
        f"| 30 Hz budget | {BUDGET_MS:.1f} ms |",
        f"| model size | {s.size_bytes / 1e6:.2f} MB |",
        f"| export and checks | {s.export_s:.1f} s |",
        "",
    ]
    raw = {"run": str(run), "task": s.task, "budget_ms": BUDGET_MS} | {
        k: getattr(s, k)
        for k in ("max_abs_diff", "max_rel_diff_state", "latency_median_ms", "latency_p99_ms", "size_bytes", "export_s")
    }
    write_markdown(RESULTS, lines, raw)


if __name__ == "__main__":
    main()
