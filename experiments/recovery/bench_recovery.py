"""Issue 19: does a policy see where it is in the lane? Start it displaced, with no car in view, and watch it return.

Each episode starts up to --offset-m to either side of the recorded path (uniform; heading within 0.05 rad of the
road's), with the other car of an overtake policy's env moved 30 m to the side (out of view at every step), and the
policy drives --steps steps (4 s by default). Per policy and world:
  intervention   the share of episodes that left the lane, over-rotated or collided within those steps
  start / end    the mean |lateral offset| at the start and after the steps, of the episodes without intervention
  slope          the least-squares slope of the offset after the steps against the start offset, all episodes
                 (0: back on the path whatever the start; 1: keeps its offset, i.e. drives parallel to the path)
A policy that passes a lane task from small starts can still have a slope near 1 on a world: it keeps its heading but
does not see its lateral position there, and an overtake (which moves the ego 1.5-2.5 m aside) cannot come back.
The 'straight' baseline (no steering) shows what the road's own curvature does to an offset.

    python experiments/recovery/bench_recovery.py --policy RUN --policy straight --world W1 --world W2 --episodes 50 \
        --name NAME --notes "..."

writes results/recovery_<NAME>.json beside this script and (from every recovery_*.json) results/recovery.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers (study.py)
from study import add_result_arguments, save_result  # noqa: E402

RESULTS = Path(__file__).parent / "results"
OUT_OF_VIEW_LATERAL_M = (30.0, 31.0)
INTERVENTIONS = ("off_lane", "over_rotation", "collision")
SURE_ROAD_M = 45.0


def make_env(task: str, world: str, env_config: dict[str, Any], offset_m: float) -> Any:
    """The task's env in eval mode on `world`, starting up to `offset_m` aside, any other car out of view."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    config = {**env_config, "initial_lateral_m": offset_m, "initial_yaw_rad": 0.05}
    # a drive of 4 s needs ~40 m of road: the 60-m KITTI odometry street is admitted whatever the policy trained with
    config["min_path_length_m"] = min(float(config.get("min_path_length_m", SURE_ROAD_M)), SURE_ROAD_M)
    if task != "lane":
        config["front_lateral_m"] = OUT_OF_VIEW_LATERAL_M
    name = f"drivesim/{task.capitalize()}-v0"
    return gymnasium.make(name, world=world, meshes=None, mode="eval", config=config).unwrapped


def load(policy: str) -> tuple[Any, str, dict[str, Any]]:
    """(policy, task, env config): a run folder, or 'straight' (no steering; lane's default env)."""
    from drivesim.policy.run_folder import load_policy
    from drivesim.stages.evaluate.rollout import StraightPolicy

    if policy == "straight":
        return StraightPolicy(), "lane", {}
    loaded = load_policy(Path(policy))
    return loaded, loaded.task, dict(loaded.env_config)


def drive(env: Any, policy: Any, seed: int, steps: int) -> tuple[float, float, bool]:
    """(start offset, offset after `steps` or at the intervention, intervened) of one episode. The env's end at a
    success (an overtake 'passes' the far-aside car) is ignored: the drive goes on to `steps`."""
    obs, _ = env.reset(seed=seed)
    start_m = float(env.lane_position()[0])
    state, episode_start = policy.initial_state(1), np.ones(1, dtype=bool)
    for _ in range(steps):
        action, state = policy.predict(obs[None], state, episode_start, deterministic=True)
        episode_start = np.zeros(1, dtype=bool)
        obs, _, _, _, info = env.step(np.asarray(action, dtype=np.float32).reshape(-1))
        ended = {k for k, v in info["termination"].items() if v}
        if ended & set(INTERVENTIONS):
            return start_m, float(env.lane_position()[0]), True
        if "end_of_data" in ended:
            break
    return start_m, float(env.lane_position()[0]), False


def measure(policy_text: str, world: str, episodes: int, offset_m: float, steps: int) -> dict[str, Any]:
    """The row of one policy in one world."""
    policy, task, env_config = load(policy_text)
    env = make_env(task, world, env_config, offset_m)
    drives = [drive(env, policy, seed, steps) for seed in range(episodes)]
    starts, ends, intervened = (np.array([d[i] for d in drives]) for i in range(3))
    env.close()
    kept = ~intervened.astype(bool)
    return {
        "policy": policy_text,
        "task": task,
        "world": world,
        "episodes": episodes,
        "intervention": float(np.mean(intervened)),
        "start_abs_m": float(np.mean(np.abs(starts[kept]))) if kept.any() else None,
        "end_abs_m": float(np.mean(np.abs(ends[kept]))) if kept.any() else None,
        "slope": float(np.polyfit(starts, ends, 1)[0]),
    }


def label(path: str) -> str:
    """A short name for a world or policy path: the folder above `world`, or the run folder's name after its
    workspace's (WORKSPACE/runs/RUN)."""
    p = Path(path)
    if p.name == "world":
        return p.parent.name
    return f"{p.parent.parent.name}/{p.name}" if p.parent.name == "runs" else p.name


def write_markdown() -> None:
    """experiments/recovery/results/recovery.md from every recovery_*.json."""
    lines = [
        "# Lateral recovery: policies started displaced, no car in view (`experiments/recovery/bench_recovery.py`)",
        "",
        "Intervention: left the lane, over-rotated or collided within the steps. start / end: mean |offset| of the",
        "episodes without intervention. slope: offset after the steps against the start offset (0 = back on the",
        "path, 1 = keeps its offset).",
        "",
    ]
    for path in sorted(RESULTS.glob("recovery_*.json")):
        data = json.loads(path.read_text())
        setup = f"starts up to ±{data['offset_m']:g} m, {data['steps']} steps ({data['steps'] / 10:g} s)"
        lines += [f"## {data['name']}", "", f"{data['machine']}, {data['date']}; {data['episodes']} episodes per row, "]
        lines[-1] += setup + "."
        lines.append("")
        lines += ["| policy | task | world | intervention | start → end (m) | slope |", "|---|---|---|---|---|---|"]
        for r in data["rows"]:
            moved = "-" if r["start_abs_m"] is None else f"{r['start_abs_m']:.2f} → {r['end_abs_m']:.2f}"
            lines.append(
                f"| {label(r['policy'])} | {r['task']} | {label(r['world'])} | {r['intervention']:.0%} | {moved} | "
                f"{r['slope']:.2f} |"
            )
        lines += ["", data.get("notes", ""), ""]
    (RESULTS / "recovery.md").write_text("\n".join(lines))


def main() -> None:
    """Parse the arguments, measure every policy in every world, write the JSON and the markdown."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", action="append", required=True, help="a run folder, or 'straight' (repeatable)")
    parser.add_argument("--world", action="append", required=True, help="a world folder (repeatable)")
    parser.add_argument("--episodes", type=int, default=50, help="episodes per policy and world (seeds 0..N-1)")
    parser.add_argument("--offset-m", type=float, default=2.0, help="largest start offset to either side, m")
    parser.add_argument("--steps", type=int, default=40, help="steps to drive (10 per second)")
    add_result_arguments(parser, "recovery")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", module="gymnasium")  # stepping on after the env's success is intended here
    import torch

    from drivesim.bench.machine import machine_line

    torch.set_num_threads(1)
    rows = []
    for policy in args.policy:
        for world in args.world:
            rows.append(measure(policy, world, args.episodes, args.offset_m, args.steps))
            r = rows[-1]
            print(f"{label(policy)} on {label(world)}: intervention {r['intervention']:.0%}, slope {r['slope']:.2f}")
    result = {
        "name": args.name,
        "machine": machine_line(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        **{k: getattr(args, k) for k in ("episodes", "offset_m", "steps", "notes")},
        "rows": rows,
    }
    save_result(RESULTS, "recovery", result, write_markdown)


if __name__ == "__main__":
    main()
