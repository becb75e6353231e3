"""Why the privileged expert failed winnable overtakes on real drives, and what two fixes of the start state and the
pursuit change: the expert on the same seeds with

- `before`: every car starting with its steering straight (0) and the pursuit computed from the current pose;
- `start steering`: cars start steering with the road's curve (`DrivingEnv._road_steering_rad`), pursuit as before;
- `both` (the product): that start and the pursuit from the pose one env step ahead (`sim/envs/expert.py`).

    .venv/bin/python experiments/expert_delay/bench_expert_delay.py --workspace WS [--workspace WS2 ...] \
        [--episodes 400]

Each workspace needs world/ and meshes/. The expert is stepped without rendering (it sees the true state; the outcome
is the same). Writes experiments/expert_delay/results/expert_delay.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.bench.machine import machine_line

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmarks/_lib: the report writer
from _lib.report import write_markdown  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "expert_delay.md"
VARIANTS = ("before", "start steering", "both")
ENDS = ("collision", "off_lane", "over_rotation", "end_of_data", "time_limit")


def _expert_from_current_pose(env: Any) -> np.ndarray:
    """The expert as it was: pure pursuit from the current pose (no step of prediction)."""
    from drivesim.sim.agents import pure_pursuit_curvature
    from drivesim.sim.envs.expert import EXPERT_LOOKAHEAD_M, EXPERT_LOOKAHEAD_S

    c, ego = env.config, env.sim.agents[0]
    lookahead = max(EXPERT_LOOKAHEAD_M, EXPERT_LOOKAHEAD_S * ego.state.speed_mps)
    tx, ty, _ = env.sim.reference.pose(ego.arc_m + lookahead, env.expert_target_offset())
    curvature = pure_pursuit_curvature(ego.state, tx, ty, gain=1.0, lookahead_m=lookahead)
    return np.array([np.clip(curvature / c.max_curvature_1pm, -1.0, 1.0)], dtype=np.float32)


def run_variant(workspace: Path, variant: str, episodes: int) -> list[dict[str, Any]]:
    """The expert's episodes (seeds 0 .. episodes-1) under `variant`: one row per episode."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    env = gymnasium.make(
        "drivesim/Overtake-v0", world=str(workspace / "world"), meshes=str(workspace / "meshes"), mode="eval"
    ).unwrapped
    rows = []
    for seed in range(episodes):
        env.reset_state(seed)
        if variant == "before":
            for agent in env.sim.agents:
                agent.state.steering_rad = 0.0
        start = dict(env._episode)
        while True:
            action = _expert_from_current_pose(env) if variant != "both" else env.expert_action()
            _, terminated, truncated, info = env.advance(action)
            if terminated or truncated:
                break
        ends = [k for k in ENDS if info["termination"].get(k)]
        rows.append(
            {"success": bool(info["success"]), "winnable": bool(start["winnable"]),
             "pass_left": start["other_lateral_m"] < 0.0, "end": ends[0] if ends else ""}
        )  # fmt: skip
    return rows


def _share(rows: list[dict[str, Any]], key: str = "success") -> str:
    return f"{np.mean([r[key] for r in rows]):.3f}" if rows else "—"


def table_row(name: str, variant: str, rows: list[dict[str, Any]]) -> str:
    """One markdown row: success overall, on winnable starts, by side, and the episodes' ends."""
    ends = Counter(r["end"] for r in rows if not r["success"])
    left = [r for r in rows if r["pass_left"]]
    right = [r for r in rows if not r["pass_left"]]
    winnable = [r for r in rows if r["winnable"]]
    counts = ", ".join(f"{k} {ends[k]}" for k in ENDS if ends[k])
    return (
        f"| {name} | {variant} | {_share(rows)} | {_share(winnable)} | {_share(left)} / {_share(right)} | "
        f"{counts or '-'} |"
    )


def main() -> None:
    """Run the three variants on each workspace and write the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, action="append", required=True)
    parser.add_argument("--episodes", type=int, default=400)
    args = parser.parse_args()
    load_before, began = os.getloadavg()[0], time.perf_counter()
    rows = []
    for workspace in args.workspace:
        for variant in VARIANTS:
            episodes = run_variant(workspace.absolute(), variant, args.episodes)
            rows.append(table_row(workspace.absolute().name, variant, episodes))
            print(rows[-1], flush=True)
    lines = [
        "## The expert's start and its counter-steer",
        "",
        f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine_line()}; load {load_before:.1f} before, "
        f"{os.getloadavg()[0]:.1f} after ({time.perf_counter() - began:.0f} s, one process). "
        f"`{' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}`.",
        "",
        f"The privileged expert on the overtake task's default starts, seeds 0 to {args.episodes - 1}, the same seeds "
        "in every row of a world. Ends: how the failed episodes ended.",
        "",
        "| world | variant | success | on winnable starts | pass-left / pass-right | failed episodes' ends |",
        "|---|---|---:|---:|---:|---|",
        *rows,
        "",
    ]
    write_markdown(RESULTS, lines)


if __name__ == "__main__":
    main()
