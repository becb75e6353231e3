"""Table I rows split by today's winnable label: each row's success on the starts labelled winnable and unwinnable,
from a `bench_table1.py` workspace's own evaluations (the same 1000 seeds as its table1-* folders).

    .venv/bin/python experiments/winnable/bench_rows_by_label.py --workspace WS [--workspace WS2 ...]

The label is recomputed with the current code for every seed (`OvertakeEnv.reset_state`, no rendering), so rows
evaluated before a change of the label are split by today's. Writes experiments/winnable/results/rows_by_label.md.
"""

from __future__ import annotations

import argparse
import csv
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivesim.bench.machine import machine_line

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmarks/_lib: the report writer
from _lib.report import write_markdown  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "rows_by_label.md"
ROWS = ("expert", "warm-start", "final-policy")


def labels(world: Path, seeds: list[int]) -> np.ndarray:
    """(len(seeds),) bool: whether each seed's overtake start is labelled winnable on `world`."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval").unwrapped
    out = []
    for seed in seeds:
        env.reset_state(seed)
        out.append(bool(env._episode["winnable"]))
    return np.array(out)


def rows_for(workspace: Path) -> list[str]:
    """Markdown rows of one workspace: per Table I row, success overall, on winnable and on unwinnable starts."""
    lines, winnable = [], None
    for row in ROWS:
        path = workspace / "eval" / f"table1-{row}" / "episodes.csv"
        episodes = sorted(csv.DictReader(path.open()), key=lambda r: int(r["seed"]))
        if winnable is None:
            winnable = labels(workspace / "world", [int(r["seed"]) for r in episodes])
        success = np.array([r["success"] == "True" for r in episodes])
        lines.append(
            f"| {workspace.name} | {row} | {len(success)} | {1 - winnable.mean():.3f} | {success.mean():.3f} | "
            f"{success[winnable].mean():.3f} | {success[~winnable].mean():.3f} |"
        )
    return lines


def main() -> None:
    """Split each workspace's Table I rows and write the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, action="append", required=True)
    args = parser.parse_args()
    rows = [line for ws in args.workspace for line in rows_for(ws.absolute())]
    write_markdown(
        RESULTS,
        [
            "## Table I rows on winnable and unwinnable starts",
            "",
            f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine_line()}. "
            f"`{' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}`.",
            "",
            "Each row's episodes are its `drivesim eval` of `bench_table1.py` (the same seeds in every row); the label "
            "is today's (`sim/envs/winnable.py`).",
            "",
            "| drive | row | episodes | unwinnable share | success | on winnable | on unwinnable |",
            "|---|---|---:|---:|---:|---:|---:|",
            *rows,
            "",
        ],
    )


if __name__ == "__main__":
    main()
