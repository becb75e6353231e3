"""How the privileged expert's pass clearance shapes its own Table I figures on a world: success, interventions by
kind, and how far it swerves, for several clearances on the same seeds.

    .venv/bin/python experiments/real_gap/expert_clearance.py --world WS/world --clearances 0.2,0.5,1.0

The expert keeps `EXPERT_CLEARANCE_M` between the footprints when it swerves (sim/envs/expert.py); a policy cloned
from it passes as wide. Episodes are stepped without rendering (the expert sees the true state). Prints a markdown
table.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def run(world: Path, clearance_m: float, episodes: int) -> dict[str, float]:
    """The expert with `clearance_m` on seeds 0..episodes-1 in eval mode: rates and its largest swerve."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)
    from drivesim.sim.envs import overtake

    overtake.EXPERT_CLEARANCE_M = clearance_m
    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval").unwrapped
    counts = {"success": 0, "collision": 0, "off_lane": 0, "over_rotation": 0, "winnable_success": 0, "winnable": 0}
    deviations = []
    for seed in range(episodes):
        env.reset_state(seed)
        winnable = bool(env._episode["winnable"])
        deviation = 0.0
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            deviation = max(deviation, abs(env.sim.agents[0].lateral_m))
            if terminated or truncated:
                break
        flags = info["termination"]
        for key in ("collision", "off_lane", "over_rotation"):
            counts[key] += bool(flags[key])
        counts["success"] += bool(info["success"])
        counts["winnable"] += winnable
        counts["winnable_success"] += winnable and bool(info["success"])
        deviations.append(deviation)
    return {
        **{k: counts[k] / episodes for k in ("success", "collision", "off_lane", "over_rotation")},
        "winnable_success": counts["winnable_success"] / max(1, counts["winnable"]),
        "mean_max_deviation_m": sum(deviations) / len(deviations),
        "max_deviation_m": max(deviations),
    }


def main() -> None:
    """Run each clearance and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, required=True)
    parser.add_argument("--clearances", default="0.2,0.35,0.5,0.75,1.0")
    parser.add_argument("--episodes", type=int, default=1000)
    args = parser.parse_args()
    print(f"world {args.world}, {args.episodes} episodes per clearance, load {os.getloadavg()[0]:.1f}")
    print("| clearance m | success | of winnable | collision | off lane | over-rotation | mean / max deviation m | s |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for text in args.clearances.split(","):
        began = time.perf_counter()
        r = run(args.world.absolute(), float(text), args.episodes)
        print(
            f"| {float(text):.2f} | {r['success']:.3f} | {r['winnable_success']:.3f} | {r['collision']:.3f} | "
            f"{r['off_lane']:.3f} | {r['over_rotation']:.3f} | {r['mean_max_deviation_m']:.2f} / "
            f"{r['max_deviation_m']:.2f} | {time.perf_counter() - began:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
