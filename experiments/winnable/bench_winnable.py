"""Overtake starts that can be won (issue 19 item 7): how many of the default starts the env labels unwinnable
(sim/envs/winnable.py), and how the privileged expert does on them and on the others, on the same seeds.

    .venv/bin/python experiments/winnable/bench_winnable.py --world WS/world [--world WS2/world ...] [--episodes 500]

The label: the hardest swerve within the ego's steering limits does not get it clear of the front car; the expert
checks it: it should fail most of the labelled starts and rarely the others. Writes
experiments/winnable/results/winnable.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from drivesim.bench.machine import machine_line

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmarks/_lib: the report writer
from _lib.report import write_markdown  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "winnable.md"


def evaluate(world: Path, episodes: int) -> tuple[list[dict[str, str]], float]:
    """The expert's episodes on `world` (seeds 0 .. episodes-1, eval mode: any overlap is a collision), one row each
    with the start's label, and the wall time [s]. The expert sees the true state, not the camera: the episodes are
    stepped without rendering (`advance`), which changes nothing of their outcome."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval").unwrapped
    rows = []
    began = time.perf_counter()
    for seed in range(episodes):
        env.reset_state(seed)
        start = dict(env._episode)
        gap_m, closing_mps = env._gap_m, start["ego_speed_mps"] - start["other_speed_mps"]
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            if terminated or truncated:
                break
        flags = info["termination"]
        intervention = flags["collision"] or flags["off_lane"] or flags["over_rotation"]
        rows.append(
            {
                "winnable": str(start["winnable"]),
                "intervention": str(bool(intervention)),
                "collision": str(bool(flags["collision"])),
                "success": str(bool(info["success"])),
                "bumper_gap_m": gap_m - 0.5 * (start["ego_length_m"] + start["other_length_m"]),
                "closing_mps": closing_mps,
            }
        )
    return rows, time.perf_counter() - began


def _rate(rows: list[dict[str, str]], key: str) -> str:
    if not rows:
        return "—"
    k = sum(r[key] == "True" for r in rows)
    return f"{k}/{len(rows)} ({k / len(rows):.1%})"


def main() -> None:
    """Run the expert on the default starts and write the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, action="append", required=True)
    parser.add_argument("--episodes", type=int, default=500)
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    runs = [(world, *evaluate(world.absolute(), args.episodes)) for world in args.world]
    load_after = os.getloadavg()[0]
    wall_s = sum(run[2] for run in runs)
    lines = [
        "## Overtake starts that can be won",
        "",
        f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine_line()}; load {load_before:.1f} before, "
        f"{load_after:.1f} after ({wall_s:.0f} s for {len(runs)} x {args.episodes} episodes, one process). "
        f"`{' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}`.",
        "",
        "The privileged expert on the overtake task's default starts (seeds 0 to "
        f'{args.episodes - 1}), split by the env\'s label `info["episode"]["winnable"]` (sim/envs/winnable.py: '
        "the hardest swerve within the ego's steering limits, on the bend where the pass happens, does not get it "
        "clear of the front car, or the pass cannot finish in the road and time left). The expert is stepped without "
        "rendering (it sees the true state; the outcome is the same).",
        "",
        "| world | starts | episodes | expert fails (intervention) | collision | success |",
        "|---|---|---|---|---|---|",
    ]
    for world, rows, _ in runs:
        winnable = [r for r in rows if r["winnable"] == "True"]
        unwinnable = [r for r in rows if r["winnable"] == "False"]
        for name, group in (("labelled unwinnable", unwinnable), ("labelled winnable", winnable), ("all", rows)):
            lines.append(
                f"| {world.absolute().parent.name} | {name} | {len(group)} | {_rate(group, 'intervention')} | "
                f"{_rate(group, 'collision')} | {_rate(group, 'success')} |"
            )
    lines += [
        "",
        "`--set env.redraw_unwinnable=true` (train or eval) draws unwinnable starts again; every report has a table "
        "of the two groups apart.",
        "",
    ]
    write_markdown(RESULTS, lines)


if __name__ == "__main__":
    main()
