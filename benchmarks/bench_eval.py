"""Benchmark of `drivesim eval`: episodes per minute with 1 and 2 workers, and the expert's metrics on the demo world
next to the paper's Table I.

    .venv/bin/python benchmarks/bench_eval.py                      # 1000 episodes per worker count (the issue's target)
    .venv/bin/python benchmarks/bench_eval.py --episodes 100       # smaller
    .venv/bin/python benchmarks/bench_eval.py --world PATH         # an existing world instead of building the demo

Without --world it builds the demo world (`drivesim synth --seed 0 --duration-s 8`, ingest, preprocess,
build-world) in a temporary workspace first. Every worker count evaluates the same seeds, so the metrics must be
identical (checked). Writes benchmarks/results/eval.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from drivesim.bench.machine import machine_line
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.report import PAPER_TABLE_I, TABLE_ROWS
from drivesim.stages.evaluate.stage import run_eval

RESULTS = Path(__file__).resolve().parent / "results" / "eval.md"


def build_demo_world(ws: Path) -> Path:
    """The demo world, built as `make demo` builds it."""
    recording = ws / "recordings" / "demo.mcap"
    steps = [
        ["synth", "--seed", "0", "--duration-s", "8", "--output", str(recording)],
        ["ingest", str(recording)],
        ["preprocess"],
        ["build-world"],
    ]
    for args in steps:
        subprocess.run([sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args], check=True)
    return ws / "world"


def bench(world: Path, episodes: int, workers: int, task: str) -> dict:
    """One evaluation in a fresh workspace: wall time end to end and the metrics."""
    import json

    with tempfile.TemporaryDirectory(prefix="bench-eval-") as tmp:
        cfg = EvalConfig(task=task, episodes=episodes, world=str(world), workers=workers)
        tic = time.perf_counter()
        result = run_eval(Workspace(tmp), cfg)
        wall_s = time.perf_counter() - tic
        metrics = json.loads((result.path / "metrics.json").read_text())
    return {"workers": workers, "wall_s": wall_s, "summary": result.summary, "metrics": metrics}


def _estimate(e: dict, pattern: str = "{:.3f}") -> str:
    if e["value"] is None:
        return "n/a"
    return f"{pattern.format(e['value'])} [{pattern.format(e['ci_low'])}, {pattern.format(e['ci_high'])}]"


def main() -> None:
    """Run the benchmark and write its markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000, help="episodes per worker count")
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    parser.add_argument("--world", type=Path, default=None, help="world folder (default: build the demo world)")
    parser.add_argument("--task", default="overtake")
    args = parser.parse_args()
    counts = [int(v) for v in args.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-eval-world-") as tmp:
        world = args.world.absolute() if args.world else build_demo_world(Path(tmp))
        load_start = os.getloadavg()[0]
        runs = [bench(world, args.episodes, k, args.task) for k in counts]
        load_end = os.getloadavg()[0]
    same = all(r["metrics"]["aggregate"] == runs[0]["metrics"]["aggregate"] for r in runs)
    cmd = f"python benchmarks/bench_eval.py --episodes {args.episodes} --workers {args.workers}"
    if args.world:
        cmd += f" --world {args.world}"
    lines = [
        f"# eval: closed-loop evaluation ({args.task}, expert policy)",
        "",
        f"Machine: {machine_line()} (load average {load_start:.1f} at start, {load_end:.1f} at the end). "
        f"Date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}. World: {world}. Reproduce: `{cmd}`.",
        "",
        "| workers | episodes | wall, end to end | episodes / min (episode loop) | episodes / min (end to end) | "
        "1000 episodes would take |",
        "|---|---|---|---|---|---|",
    ]
    for r in runs:
        per_min = 60 * args.episodes / r["wall_s"]
        loop = r["summary"].episodes_per_min
        lines.append(
            f"| {r['workers']} | {args.episodes} | {r['wall_s']:.1f} s | {loop:.1f} | {per_min:.1f} | "
            f"{1000 / per_min:.1f} min |"
        )
    lines += [
        "",
        "End to end includes starting the worker processes (each imports torch and loads the world once), the "
        "figures and the report. Target (issue 10): 1000 overtake episodes on the demo world in at most 10 minutes.",
        "",
        f"Same seeds with every worker count gave {'identical' if same else 'DIFFERENT'} metrics.",
        "",
        f"## The expert's metrics on this world ({args.episodes} episodes, 95 % CI) beside the paper's Table I",
        "",
        "| metric | expert, this world | paper, garage | paper, outdoor |",
        "|---|---|---|---|",
    ]
    agg = runs[0]["metrics"]["aggregate"]
    for key, label, pattern in TABLE_ROWS:
        garage, outdoor = PAPER_TABLE_I[key]
        paper = f"{pattern.format(garage)} | {pattern.format(outdoor)}"
        lines.append(f"| {label} | {_estimate(agg[key], pattern)} | {paper} |")
    causes = runs[0]["metrics"]["intervention_causes"]
    lines += [
        f"| success rate | {_estimate(agg['success'])} | — | — |",
        "",
        f"Intervention causes (episodes): collision {causes['collision']}, off lane {causes['off_lane']}, "
        f"over-rotation {causes['over_rotation']}; ended at the end of the data: {causes['end_of_data']}.",
        "The paper's numbers are for its trained end-to-end policy on real drives; the expert here is the "
        "privileged controller that sees the true state, so it is a reference for the env, not for learning.",
        "",
    ]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
