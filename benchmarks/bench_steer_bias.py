"""Why lane policies fail on a real drive they never saw (issue 19): their steering at the recorded poses.

At the recorded pose (the ego centred on the recorded path and aligned with it) a lane policy should steer about as
much as the road curves (KITTI raw 0001's path: |curvature| <= 0.003 1/m, a steering action near 0). For each run and
world this script shows the policy the view at the recorded pose of N episode starts (the eval starts of seeds
0 .. N-1, no lateral or heading offset, no augmentation) for 8 steps (the LSTM's state from zero) and reports the mean
and spread of the steering action (-1 .. 1, + = left) over the starts. A policy whose mean is far from 0 with a small
spread steers the same way wherever it is on that drive: it drifts off the lane at a steady heading, whatever the
scene, which is how the lane policies fail on KITTI raw 0001 (`transfer.md`).

    .venv/bin/python benchmarks/bench_steer_bias.py --run LABEL=RUN ... --world NAME=WORLD ... [--starts 12]
        [--top-from NAME]

With --top-from NAME, each other world gets a second column: the same views with their top TOP_FRACTION of rows (sky,
trees, buildings: what lies above the road) taken from world NAME's views, start by start; a bias that goes away
there comes from above the road.

Writes benchmarks/results/steer_bias.md (--output to change).
"""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivesim.diagnostics.machine import machine_line
from drivesim.diagnostics.report import write_markdown

RESULTS = Path(__file__).resolve().parent / "results" / "steer_bias.md"
SETTLE_STEPS = 8
"""Steps the same view is shown before the action is read (the LSTM's state from zero settles in a few)."""
TOP_FRACTION = 3 / 8
"""Share of the view's rows (from the top) swapped with --top-from: 24 of the policy's 64."""


def recorded_pose_views(world: str, starts: int) -> np.ndarray:
    """(starts, C, H, W) uint8: the lane task's eval views at the recorded pose of the starts of seeds 0 .. starts-1
    (no lateral or heading offset, no augmentation; starts >= 40 m from the path's end)."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    config = {"initial_lateral_m": 0.0, "initial_yaw_rad": 0.0, "min_path_length_m": 40.0, "augment": False}
    env = gymnasium.make("drivesim/Lane-v0", world=world, meshes=None, mode="eval", config=config)
    views = np.stack([np.asarray(env.reset(seed=seed)[0]) for seed in range(starts)])
    env.close()
    return views


def steering(run: str, views: np.ndarray) -> np.ndarray:
    """The run's deterministic steering action for each view, shown SETTLE_STEPS times from a zero LSTM state."""
    import torch

    from drivesim.stages.policy.run_folder import load_policy

    net = load_policy(run).net
    images = torch.from_numpy(views)
    state = net.initial_state(len(views))
    with torch.no_grad():
        for k in range(SETTLE_STEPS):
            action, _, state = net.step(images, state, torch.full((len(views),), float(k == 0)))
    return action[:, 0].clamp(-1.0, 1.0).numpy()


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
    parser.add_argument("--top-from", default=None, help="a --world NAME whose views' tops replace the others'")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    runs, worlds = _pairs(args.run, "run"), _pairs(args.world, "world")
    views = {name: recorded_pose_views(path, args.starts) for name, path in worlds}
    if args.top_from is not None:
        if args.top_from not in views:
            sys.exit(f"error: --top-from {args.top_from!r} is not one of the --world names")
        top = views[args.top_from]
        rows = round(top.shape[2] * TOP_FRACTION)
        for name, _ in list(worlds):
            if name != args.top_from:
                mixed = views[name].copy()
                mixed[:, :, :rows] = top[:, :, :rows]
                views[f"{name}, top from {args.top_from}"] = mixed
    lines = [
        "# Lane policies' steering at the recorded poses of each world (issue 19)",
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `python benchmarks/bench_steer_bias.py {' '.join(f'--run {r}' for r in args.run)} "
        f"{' '.join(f'--world {w}' for w in args.world)} --starts {args.starts}"
        + (f" --top-from {args.top_from}`" if args.top_from else "`"),
        f"- the steering action (-1 .. 1, + = left) at the recorded pose of {args.starts} starts per world, after "
        f"{SETTLE_STEPS} steps of the same view: mean ± standard deviation over the starts"
        + (
            f"; 'top from {args.top_from}': the top {TOP_FRACTION:.1%} of each view's rows replaced by those of "
            f"{args.top_from}'s view of the same start number"
            if args.top_from
            else ""
        ),
        "",
        "| run | " + " | ".join(views) + " |",
        "|---|" + "---:|" * len(views),
    ]
    for label, run in runs:
        cells = []
        for name in views:
            action = steering(run, views[name])
            cells.append(f"{action.mean():+.2f} ± {action.std():.2f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    write_markdown(args.output, lines + [""])


if __name__ == "__main__":
    main()
