"""Overtake starts that can be won (issue 19 item 7): how many of the default starts the env labels unwinnable
(sim/envs/winnable.py), and how the privileged expert does on them and on the others, on the same seeds.

    .venv/bin/python benchmarks/bench_winnable.py --world WS/world [--episodes 500] [--workers 2]

The label is a physical bound (no steering within the ego's limits gets clear of the front car before the bumpers
meet); the expert checks it: it should fail most of the labelled starts and rarely the others. Writes
benchmarks/results/winnable.md.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from drivesim.diagnostics.machine import machine_line
from drivesim.diagnostics.report import write_markdown
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.stage import run_eval

RESULTS = Path(__file__).resolve().parent / "results" / "winnable.md"


def evaluate(world: Path, episodes: int, workers: int) -> tuple[list[dict[str, str]], float]:
    """The expert's episodes.csv rows on `world` (seeds 0 .. episodes-1) and the wall time [s]."""
    with tempfile.TemporaryDirectory(prefix="bench-winnable-") as tmp:
        cfg = EvalConfig(task="overtake", episodes=episodes, world=str(world), workers=workers, record="none")
        began = time.perf_counter()
        result = run_eval(Workspace(tmp), cfg)
        wall_s = time.perf_counter() - began
        with open(result.path / "episodes.csv", newline="") as f:
            return list(csv.DictReader(f)), wall_s


def _rate(rows: list[dict[str, str]], key: str) -> str:
    if not rows:
        return "—"
    k = sum(r[key] == "True" for r in rows)
    return f"{k}/{len(rows)} ({k / len(rows):.1%})"


def main() -> None:
    """Run the expert on the default starts and write the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    rows, wall_s = evaluate(args.world.absolute(), args.episodes, args.workers)
    load_after = os.getloadavg()[0]
    winnable = [r for r in rows if r["winnable"] == "True"]
    unwinnable = [r for r in rows if r["winnable"] == "False"]
    lines = [
        "## Overtake starts that can be won (issue 19, item 7)",
        "",
        f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine_line()}; load {load_before:.1f} before, "
        f"{load_after:.1f} after ({wall_s / 60:.1f} min for {len(rows)} episodes, {args.workers} workers). "
        f"`{' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}`; world `{args.world}`.",
        "",
        "The privileged expert on the overtake task's default starts (seeds 0 to "
        f'{args.episodes - 1}), split by the env\'s label `info["episode"]["winnable"]` (sim/envs/winnable.py: '
        "no steering within the ego's limits gets it clear of the front car before the bumpers meet).",
        "",
        "| starts | episodes | expert fails (intervention) | collision | success |",
        "|---|---|---|---|---|",
    ]
    for name, group in (("labelled unwinnable", unwinnable), ("labelled winnable", winnable), ("all", rows)):
        lines.append(
            f"| {name} | {len(group)} | {_rate(group, 'intervention')} | {_rate(group, 'collision')} | "
            f"{_rate(group, 'success')} |"
        )
    lines += [
        "",
        f"Unwinnable share of the starts: {len(unwinnable)}/{len(rows)}. `--set env.redraw_unwinnable=true` (train "
        "or eval) draws them again; every report has a table of the two groups apart.",
        "",
    ]
    write_markdown(RESULTS, lines)


if __name__ == "__main__":
    main()
