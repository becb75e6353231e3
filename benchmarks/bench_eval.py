"""Benchmark of `drivesim eval`: episodes per minute with 1 and 2 workers, and the metrics of the expert and of
trained policies on the demo world next to the paper's Table I.

    .venv/bin/python benchmarks/bench_eval.py --world WS/world                 # expert, 1000 episodes per worker count
    .venv/bin/python benchmarks/bench_eval.py --world WS/world --policy WS/runs/overtake-... --one-worker-episodes 200

The speed is measured on the first policy (every worker count evaluates the same seeds, so the metrics must be
identical: checked); each further policy is evaluated once with the most workers. Without --world it builds the
demo world as `make demo` does (a 60-s synthetic drive, depth by multi-view stereo) in a temporary workspace first.
Writes benchmarks/results/eval.md.
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
from typing import Any

from _lib.report import write_markdown

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
        ["synth", "--seed", "0", "--duration-s", "60", "--output", str(recording)],
        ["ingest", str(recording)],
        ["preprocess", "--set", "depth.method=mvs"],
        ["build-world"],
    ]
    for args in steps:
        subprocess.run([sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args], check=True)
    return ws / "world"


def bench(world: Path, episodes: int, workers: int, task: str, policy: str = "expert") -> dict:
    """One evaluation in a fresh workspace: wall time end to end and the metrics."""
    import json

    with tempfile.TemporaryDirectory(prefix="bench-eval-") as tmp:
        cfg = EvalConfig(task=task, episodes=episodes, world=str(world), workers=workers, policy=policy)
        tic = time.perf_counter()
        result = run_eval(Workspace(tmp), cfg)
        wall_s = time.perf_counter() - tic
        metrics = json.loads((result.path / "metrics.json").read_text())
    return {
        "workers": workers,
        "episodes": episodes,
        "policy": policy,
        "wall_s": wall_s,
        "summary": result.summary,
        "metrics": metrics,
    }


def _estimate(e: dict, pattern: str = "{:.3f}") -> str:
    if e["value"] is None:
        return "n/a"
    return f"{pattern.format(e['value'])} [{pattern.format(e['ci_low'])}, {pattern.format(e['ci_high'])}]"


def _policy_name(policy: str) -> str:
    return policy if policy == "expert" else f"trained ({Path(policy).name})"


def main() -> None:
    """Run the benchmark and write its markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000, help="episodes per evaluation")
    parser.add_argument(
        "--one-worker-episodes", type=int, default=None, help="episodes of the 1-worker speed run (default --episodes)"
    )
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    parser.add_argument("--world", type=Path, default=None, help="world folder (default: build the demo world)")
    parser.add_argument("--policy", action="append", default=None, help="a run folder (repeatable); expert first")
    parser.add_argument("--task", default="overtake")
    args = parser.parse_args()
    counts = [int(v) for v in args.workers.split(",")]
    policies = ["expert", *[str(Path(p).absolute()) for p in args.policy or []]]
    with tempfile.TemporaryDirectory(prefix="bench-eval-world-") as tmp:
        world = args.world.absolute() if args.world else build_demo_world(Path(tmp))
        load_start = os.getloadavg()[0]
        runs = []
        for k in counts:
            n = args.one_worker_episodes if (k == 1 and args.one_worker_episodes) else args.episodes
            runs.append(bench(world, n, k, args.task))
            print(f"expert, {k} worker(s): {n} episodes in {runs[-1]['wall_s']:.0f} s", flush=True)
        others = [bench(world, args.episodes, max(counts), args.task, p) for p in policies[1:]]
        load_end = os.getloadavg()[0]
    comparable = [r for r in runs if r["episodes"] == runs[-1]["episodes"]]
    same = all(r["metrics"]["aggregate"] == comparable[0]["metrics"]["aggregate"] for r in comparable)
    cmd = f"python benchmarks/bench_eval.py --episodes {args.episodes} --workers {args.workers}"
    if args.one_worker_episodes:
        cmd += f" --one-worker-episodes {args.one_worker_episodes}"
    if args.world:
        cmd += f" --world {args.world}"
    cmd += "".join(f" --policy {p}" for p in args.policy or [])
    lines = [
        f"# eval: closed-loop evaluation ({args.task})",
        "",
        f"Machine: {machine_line()} (load average {load_start:.1f} at start, {load_end:.1f} at the end). "
        f"Date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}. World: {world}. Reproduce: `{cmd}`.",
        "",
        "| policy | workers | episodes | wall, end to end | episodes / min (episode loop) | "
        "episodes / min (end to end) | "
        "1000 episodes would take |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in runs + others:
        per_min = 60 * r["episodes"] / r["wall_s"]
        loop = r["summary"].episodes_per_min
        lines.append(
            f"| {_policy_name(r['policy'])} | {r['workers']} | {r['episodes']} | {r['wall_s']:.1f} s | {loop:.1f} | "
            f"{per_min:.1f} | {1000 / per_min:.1f} min |"
        )
    lines += [
        "",
        "End to end includes starting the worker processes (each imports torch and loads the world once), the "
        "figures and the report. Target (issue 10): 1000 overtake episodes on the demo world in at most 10 minutes.",
        "",
    ]
    if len(comparable) > 1:
        lines += [f"Same seeds with every worker count gave {'identical' if same else 'DIFFERENT'} metrics.", ""]
    lines += _metrics_lines([runs[-1], *others], args.episodes)
    raw = _raw_record(
        cmd, world, args.task, (load_start, load_end), same if len(comparable) > 1 else None, runs + others
    )
    write_markdown(RESULTS, lines, raw)


def _metrics_lines(table: list[dict[str, Any]], episodes: int) -> list[str]:
    """The Table I metrics of each run in `table` beside the paper's, and their interventions by cause."""
    lines: list[str] = []
    lines += [
        f"## Metrics on this world ({episodes} episodes each, 95 % CI) beside the paper's Table I",
        "",
        "| metric | " + " | ".join(_policy_name(r["policy"]) for r in table) + " | paper, garage | paper, outdoor |",
        "|---|" + "---|" * (len(table) + 2),
    ]
    for key, label, pattern in TABLE_ROWS:
        garage, outdoor = PAPER_TABLE_I[key]
        cells = " | ".join(_estimate(r["metrics"]["aggregate"][key], pattern) for r in table)
        lines.append(f"| {label} | {cells} | {pattern.format(garage)} | {pattern.format(outdoor)} |")
    cells = " | ".join(_estimate(r["metrics"]["aggregate"]["success"]) for r in table)
    lines += [f"| success rate | {cells} | — | — |", ""]
    for r in table:
        c = r["metrics"]["intervention_causes"]
        lines.append(
            f"- {_policy_name(r['policy'])}: interventions by cause (episodes): collision {c['collision']}, off lane "
            f"{c['off_lane']}, over-rotation {c['over_rotation']}; ended at the end of the data: {c['end_of_data']}."
        )
    lines += [
        "",
        "The paper's numbers are for its trained end-to-end policy on real drives (a garage and rural roads); the "
        "expert here is the privileged controller that sees the true state, a reference for the env.",
        "",
    ]
    return lines


def _raw_record(
    cmd: str, world: Path, task: str, loads: tuple[float, float], same: bool | None, runs: list[dict[str, Any]]
) -> dict[str, Any]:
    """The benchmark's JSON record: the command, the world, the loads and every run's figures."""
    return {
        "command": cmd,
        "world": str(world),
        "task": task,
        "load_average_start_end": list(loads),
        "same_metrics_every_worker_count": same,
        "runs": [
            {
                "policy": _policy_name(r["policy"]),
                "workers": r["workers"],
                "episodes": r["episodes"],
                "wall_s": r["wall_s"],
                "episodes_per_min_loop": r["summary"].episodes_per_min,
                "episodes_per_min_end_to_end": 60 * r["episodes"] / r["wall_s"],
                "aggregate": r["metrics"]["aggregate"],
                "intervention_causes": r["metrics"]["intervention_causes"],
            }
            for r in runs
        ],
        "paper_table_i": PAPER_TABLE_I,
    }


if __name__ == "__main__":
    main()
