"""How the privileged expert's own settings shape its Table I figures on a world: its pass clearance
(`EXPERT_CLEARANCE_M`, sim/envs/expert.py) and the ego's steering limit (`max_curvature_1pm`), on the same seeds,
stepped without rendering (the expert sees the true state).

    .venv/bin/python experiments/real_gap/expert_settings.py --world WS/world --clearances 0.2,0.5,1.0
    .venv/bin/python experiments/real_gap/expert_settings.py --world WS/world --limits 0.15,0.2,0.25

Prints one markdown row per setting: success (of all starts and of the winnable ones), each intervention, and the
mean and largest swerve; with the share of the world's recorded path sharper than the steering limit.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def run(world: Path, clearance_m: float, limit_1pm: float, episodes: int) -> dict[str, float]:
    """The expert on seeds 0..episodes-1 in eval mode: rates and its swerves."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)
    from drivesim.sim.envs import overtake

    overtake.EXPERT_CLEARANCE_M = clearance_m
    config = {"max_curvature_1pm": limit_1pm}
    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval", config=config).unwrapped
    counts = dict.fromkeys(("success", "collision", "off_lane", "over_rotation", "winnable", "winnable_success"), 0)
    deviations = []
    for seed in range(episodes):
        env.reset_state(seed)
        winnable, deviation = bool(env._episode["winnable"]), 0.0
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            deviation = max(deviation, abs(env.sim.agents[0].lateral_m))
            if terminated or truncated:
                break
        for key in ("collision", "off_lane", "over_rotation"):
            counts[key] += bool(info["termination"][key])
        counts["success"] += bool(info["success"])
        counts["winnable"] += winnable
        counts["winnable_success"] += winnable and bool(info["success"])
        deviations.append(deviation)
    rates = {k: counts[k] / episodes for k in ("success", "collision", "off_lane", "over_rotation")}
    rates["winnable_success"] = counts["winnable_success"] / max(1, counts["winnable"])
    return {**rates, "mean_max_deviation_m": float(np.mean(deviations)), "max_deviation_m": float(max(deviations))}


def main() -> None:
    """Run each setting (clearances at the default limit, or limits at the default clearance) and print the table."""
    from drivesim.sim.envs.config import EnvConfig
    from drivesim.sim.envs.expert import EXPERT_CLEARANCE_M

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, required=True)
    parser.add_argument("--clearances", default=str(EXPERT_CLEARANCE_M), help="m, comma-separated")
    parser.add_argument("--limits", default=str(EnvConfig().max_curvature_1pm), help="1/m, comma-separated")
    parser.add_argument("--episodes", type=int, default=1000)
    args = parser.parse_args()
    curvature = np.abs(np.load(args.world / "path.npz")["curvature_1pm"])
    print(f"world {args.world}: {args.episodes} episodes per setting; path curvature max {curvature.max():.3f} 1/m")
    print("| clearance m | limit 1/m | path sharper | success | of winnable | collision | off lane | over-rotation | "
          "mean / max deviation m | s |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for clearance in (float(c) for c in args.clearances.split(",")):
        for limit in (float(k) for k in args.limits.split(",")):
            began = time.perf_counter()
            r = run(args.world.absolute(), clearance, limit, args.episodes)
            print(
                f"| {clearance:.2f} | {limit:.2f} | {(curvature > limit).mean():.1%} | {r['success']:.3f} | "
                f"{r['winnable_success']:.3f} | {r['collision']:.3f} | {r['off_lane']:.3f} | "
                f"{r['over_rotation']:.3f} | {r['mean_max_deviation_m']:.2f} / {r['max_deviation_m']:.2f} | "
                f"{time.perf_counter() - began:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
