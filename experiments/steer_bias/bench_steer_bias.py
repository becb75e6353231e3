"""Why lane policies fail on a real drive they never saw (issue 19): how they steer at and around the recorded poses.

A lane policy that keeps its lane steers back when it is turned or shifted off the recorded path. For each run and
world this script places the ego at the recorded pose of N episode starts (the eval starts of seeds 0 .. N-1, no
augmentation, the view the run trained with), shows the policy that view for 8 steps (the LSTM's state from zero) and
reads its steering action (-1 .. 1, + = left), at five poses: on the path, turned +-ROTATION_RAD, shifted
+-LATERAL_M. Per world it reports
- bias: the mean (± standard deviation over the starts) on the path, where the road's curvature asks for about 0;
- rotation response: steering turned right minus steering turned left (> 0: it steers back);
- lateral response: steering shifted right minus steering shifted left (> 0: it steers back).
A policy whose responses are <= 0 on a world drives away from the path there, whatever its bias.
With --blank REGION (top-left, top-right: quarters of the policy's image; top, bottom: halves) that part of every view
is set to the view's mean colour before the policy sees it: which part of a world's picture makes the response.

    .venv/bin/python experiments/steer_bias/bench_steer_bias.py --run LABEL=RUN ... --world NAME=WORLD ... \
        [--starts 12] [--blank R]

Writes experiments/steer_bias/results/steer_bias.md (--output to change).
"""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.bench.machine import machine_line

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmarks/_lib: the report writer
from _lib.report import write_markdown  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "steer_bias.md"
SETTLE_STEPS = 8
"""Steps the same view is shown before the action is read (the LSTM's state from zero settles in a few)."""
ROTATION_RAD = 0.2
LATERAL_M = 1.0
POSES = ((0.0, 0.0), (0.0, ROTATION_RAD), (0.0, -ROTATION_RAD), (LATERAL_M, 0.0), (-LATERAL_M, 0.0))
"""(lateral m, heading offset rad) from the recorded pose, + = left."""


def views_at(world: str, env_config: dict[str, Any], starts: int) -> dict[tuple[float, float], np.ndarray]:
    """For each of POSES, (starts, C, H, W) uint8: the lane task's eval views of seeds 0 .. starts-1 with the ego
    moved from the recorded pose by that offset, rendered with `env_config` (a run's) without augmentation."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)
    from drivesim.sim.dynamics import BicycleState

    keys = ("roi_fov_deg", "roi_horizon_fraction", "observation_width_px", "observation_height_px")  # not roi_px: a
    config = {k: env_config[k] for k in keys if env_config.get(k) is not None}  # pixel region of its own worlds
    config.update(initial_lateral_m=0.0, initial_yaw_rad=0.0, min_path_length_m=40.0, augment=False)
    env = gymnasium.make("drivesim/Lane-v0", world=world, meshes=None, mode="eval", config=config)
    base = env.unwrapped
    out: dict[tuple[float, float], list[np.ndarray]] = {pose: [] for pose in POSES}
    for seed in range(starts):
        env.reset(seed=seed)
        ego, reference = base.sim.agents[0], base.sim.reference
        for lateral_m, heading_rad in POSES:
            x, y, yaw = reference.pose(ego.arc_m, lateral_m)
            ego.state = BicycleState(x, y, yaw + heading_rad, 0.0, ego.state.speed_mps)
            ego.lateral_m = lateral_m
            out[(lateral_m, heading_rad)].append(np.asarray(base.observation_from(base.sim.views([0])[0])))
    env.close()
    return {pose: np.stack(images) for pose, images in out.items()}


BLANK_REGIONS = {"top-left": (0.0, 0.5, 0.0, 0.5), "top-right": (0.0, 0.5, 0.5, 1.0), "top": (0.0, 0.5, 0.0, 1.0),
                 "bottom": (0.5, 1.0, 0.0, 1.0)}  # fmt: skip
"""(top, bottom, left, right) of each region, fractions of the image's height and width."""


def blank(views: np.ndarray, region: str) -> np.ndarray:
    """(N, C, H, W) uint8 views with `region` (a key of BLANK_REGIONS) set to each view's mean colour."""
    top, bottom, left, right = BLANK_REGIONS[region]
    out = views.copy()
    H, W = views.shape[2:]
    mean = np.rint(views.mean(axis=(2, 3), keepdims=True)).astype(np.uint8)
    rows, cols = slice(int(top * H), int(bottom * H)), slice(int(left * W), int(right * W))
    out[:, :, rows, cols] = mean
    return out


def steering(net: Any, views: np.ndarray) -> np.ndarray:
    """The policy's deterministic steering action for each view, shown SETTLE_STEPS times from a zero LSTM state."""
    import torch

    images = torch.from_numpy(views)
    state = net.initial_state(len(views))
    with torch.no_grad():
        for k in range(SETTLE_STEPS):
            action, _, state = net.step(images, state, torch.full((len(views),), float(k == 0)))
    return action[:, 0].clamp(-1.0, 1.0).numpy()


def world_cell(net: Any, views: dict[tuple[float, float], np.ndarray]) -> str:
    """'bias ± spread / rotation response / lateral response' of one run on one world."""
    actions = {pose: steering(net, images) for pose, images in views.items()}
    mean = {pose: float(action.mean()) for pose, action in actions.items()}
    on_path = actions[(0.0, 0.0)]
    rotation = mean[(0.0, -ROTATION_RAD)] - mean[(0.0, ROTATION_RAD)]
    lateral = mean[(-LATERAL_M, 0.0)] - mean[(LATERAL_M, 0.0)]
    return f"{on_path.mean():+.2f} ± {on_path.std():.2f} / {rotation:+.2f} / {lateral:+.2f}"


def _pairs(values: list[str], what: str) -> list[tuple[str, str]]:
    pairs = []
    for value in values:
        label, sep, path = value.partition("=")
        if not sep or not Path(path).is_dir():
            sys.exit(f"error: --{what} wants LABEL=FOLDER with an existing folder, got {value!r}")
        pairs.append((label, path))
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, help="LABEL=RUN_FOLDER of a lane run (repeatable)")
    parser.add_argument("--world", action="append", required=True, help="NAME=WORLD_FOLDER (repeatable)")
    parser.add_argument("--starts", type=int, default=12)
    parser.add_argument("--blank", choices=sorted(BLANK_REGIONS), default=None, help="neutralize this part of views")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    import torch

    from drivesim.policy.run_folder import load_policy

    torch.set_num_threads(1)
    runs, worlds = _pairs(args.run, "run"), _pairs(args.world, "world")
    lines = [
        "# Lane policies' steering at and around the recorded poses of each world (issue 19)"
        + (f": the {args.blank} of every view blanked" if args.blank else ""),
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `python experiments/steer_bias/bench_steer_bias.py {' '.join(f'--run {r}' for r in args.run)} "
        f"{' '.join(f'--world {w}' for w in args.world)} --starts {args.starts}"
        f"{f' --blank {args.blank}' if args.blank else ''}`",
        f"- per world: bias (the steering action, -1 .. 1, + = left, on the recorded path: mean ± standard deviation "
        f"over {args.starts} starts) / rotation response (steering turned {ROTATION_RAD} rad right minus turned left) "
        f"/ lateral response (shifted {LATERAL_M} m right minus shifted left); a response > 0 steers back to the path",
        "",
        "| run | " + " | ".join(name for name, _ in worlds) + " |",
        "|---|" + "---:|" * len(worlds),
    ]
    cache: dict[tuple[str, str], dict] = {}
    for label, run in runs:
        policy = load_policy(run)
        cells = []
        for _, world in worlds:
            key = (world, repr(sorted((k, v) for k, v in policy.env_config.items() if k.startswith(("roi", "obs")))))
            if key not in cache:
                cache[key] = views_at(world, policy.env_config, args.starts)
                if args.blank:
                    cache[key] = {pose: blank(images, args.blank) for pose, images in cache[key].items()}
            cells.append(world_cell(policy.net, cache[key]))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    write_markdown(args.output, lines + [""])


if __name__ == "__main__":
    main()
