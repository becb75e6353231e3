"""The privileged expert's outcomes on a world for several steering limits (`max_curvature_1pm`), on the same
seeds, stepped without rendering; and how much of the world's recorded path is sharper than each limit.

    .venv/bin/python experiments/real_gap/expert_steering_limit.py --world WS/world --limits 0.15,0.2,0.25
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def run(world: Path, limit_1pm: float, episodes: int) -> dict[str, float]:
    """Rates of success and of each intervention over seeds 0..episodes-1 in eval mode."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    env = gymnasium.make(
        "drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval", config={"max_curvature_1pm": limit_1pm}
    ).unwrapped
    counts = dict.fromkeys(("success", "collision", "off_lane", "over_rotation", "winnable"), 0)
    for seed in range(episodes):
        env.reset_state(seed)
        counts["winnable"] += bool(env._episode["winnable"])
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            if terminated or truncated:
                break
        for key in ("collision", "off_lane", "over_rotation"):
            counts[key] += bool(info["termination"][key])
        counts["success"] += bool(info["success"])
    return {k: v / episodes for k, v in counts.items()}


def main() -> None:
    """Print one markdown row per limit."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, required=True)
    parser.add_argument("--limits", default="0.15,0.2,0.25")
    parser.add_argument("--episodes", type=int, default=1000)
    args = parser.parse_args()
    curvature = np.abs(np.load(args.world / "path.npz")["curvature_1pm"])
    print(f"world {args.world}: path curvature max {curvature.max():.3f} 1/m")
    print("| limit 1/m | path sharper | success | collision | off lane | over-rotation | winnable | s |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for text in args.limits.split(","):
        limit, began = float(text), time.perf_counter()
        r = run(args.world.absolute(), limit, args.episodes)
        print(
            f"| {limit:.2f} | {(curvature > limit).mean():.1%} | {r['success']:.3f} | {r['collision']:.3f} | "
            f"{r['off_lane']:.3f} | {r['over_rotation']:.3f} | {r['winnable']:.3f} | "
            f"{time.perf_counter() - began:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
