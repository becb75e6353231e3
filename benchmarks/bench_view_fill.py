"""No black in the policy's view (issue 20): where the view's pixels come from, and what filling costs per step.

(a) Coverage on a real drive: agents at lateral offsets and heading rotations up to the task's largest (max_lateral_m
    2.5 m, max_rotation_rad 0.5 rad), at every 2nd frame of the drive; the fraction of the policy's view from the
    view's own recorded frame, from neighbouring frames, inpainted, and left unfilled, for the warp alone, with the
    neighbour frames (an option), with them and inpainting, and with inpainting alone (the default).
(b) Speed: expert steps of the lane and follow tasks, one env in one process; warp ms per step (which includes the
    filling) and total ms per step with filling off (the warp alone), inpainting alone (the default) and with
    neighbour frames, in the same run.

    .venv/bin/python benchmarks/bench_view_fill.py --coverage-world W --skip speed
    .venv/bin/python benchmarks/bench_view_fill.py --speed-world W --skip coverage --output .../view_fill_speed.md

Writes benchmarks/results/view_fill.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivesim.diagnostics.machine import machine_line

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "view_fill.md"
POSES = ((0.0, 0.0), (1.0, 0.0), (2.5, 0.0), (0.0, 0.5), (2.5, 0.5), (-2.5, -0.5))
OPTION = (-1, 1, -2)  # ViewConfig.fill_frames to try: the frame behind, the one ahead, the second behind
VARIANTS = {
    "warp only": {"fill_frames": (), "inpaint": False},
    "+ neighbour frames -1, +1, -2 (side wedges; an option)": {"fill_frames": OPTION, "inpaint": False},
    "+ inpainting (the option's whole fill)": {"fill_frames": OPTION},
    "inpainting alone (the default)": {},
}

SPEED_VARIANTS = {
    "off (the warp alone)": {"fill_frames": (), "inpaint": False},
    "inpainting alone (the default)": {},
    "frame -1 + inpainting": {"fill_frames": (-1,)},
    "frames -1, +1, -2 + inpainting (an option)": {"fill_frames": OPTION},
}


def coverage_rows(world_path: str, step: int = 2) -> list[dict]:
    """(a): fractions of the view by source, per pose and variant, over every `step`-th frame of the drive."""
    import torch

    from drivesim.sim.envs.config import EnvConfig
    from drivesim.sim.envs.roi import default_roi
    from drivesim.sim.geometry import yaw_of
    from drivesim.sim.view import ViewConfig, ViewSynthesizer, planar_transforms
    from drivesim.sim.world import World

    torch.set_num_threads(1)
    world = World.load(world_path)
    task = EnvConfig()
    roi = default_roi(world.width_px, world.height_px, task)
    size = {"roi_px": roi, "out_width_px": task.observation_width_px, "out_height_px": task.observation_height_px}
    frames = range(2, world.frame_count - 2, step)
    rows = []
    for name, flags in VARIANTS.items():
        vs = ViewSynthesizer(world, ViewConfig(**size, **flags))
        for lat, rot in POSES:
            vs.fill_stats.__init__()
            for f in frames:
                T = world.path["T_world_vehicle"][f] @ planar_transforms(0.0, lat, rot)[0]
                vs.render(np.array([f]), T[0, 3:4], T[1, 3:4], np.atleast_1d(yaw_of(T)), [[]])
            rows.append({"variant": name, "lateral_m": lat, "rotation_rad": rot, **vs.fill_stats.fractions()})
    return rows


def speed_rows(world_path: str, tasks: tuple[str, ...], steps: int) -> list[dict]:
    """(b): ms per expert step (warp and total) with filling off and on, one env in this process."""
    import gymnasium
    import torch

    import drivesim.sim.envs  # noqa: F401  (registers the envs)
    from drivesim.sim.view import ViewSynthesizer

    torch.set_num_threads(1)
    rows = []
    for task in tasks:
        for name, flags in SPEED_VARIANTS.items():
            env = gymnasium.make(f"drivesim/{task.capitalize()}-v0", world=world_path, meshes=None)
            base = env.unwrapped
            env.reset(seed=0)
            old = base.sim.renderer
            vs = ViewSynthesizer(base.worlds[0], old.config.model_copy(update=flags))
            base._renderers[0] = base.sim.renderer = vs  # the same view, filling switched as named
            for _ in range(5):
                env.step(base.expert_action())
            env.reset(seed=0)
            base.sim.renderer = vs
            base.reset_timings()
            vs.fill_stats.__init__()
            episode, start = 0, time.perf_counter()
            for _ in range(steps):
                _, _, terminated, truncated, _ = env.step(base.expert_action())
                if terminated or truncated:
                    episode += 1
                    env.reset(seed=episode)
                    base.sim.renderer = vs
            seconds = time.perf_counter() - start
            n = max(int(base.step_count), 1)
            fractions = vs.fill_stats.fractions()
            rows.append({"task": task, "filling": name, "warp_ms": base.timings_ms["warp"] / n,
                         "total_ms": 1e3 * seconds / steps, "frame": fractions["frame"],
                         "filled_other": fractions["neighbour"] + fractions["inpainted"]})  # fmt: skip
            env.close()
    return rows


def markdown(coverage: list[dict], speed: list[dict], args: argparse.Namespace, load: str) -> str:
    """The report."""
    lines = [
        "# No black in the policy's view: neighbour frames and inpainting (issue 20)",
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `python benchmarks/bench_view_fill.py --coverage-world {args.coverage_world} --speed-world "
        f"{args.speed_world} --steps {args.steps}{''.join(f' --skip {s}' for s in args.skip)}`",
        f"- load: {load}",
        "",
    ]
    if coverage:
        lines += [
            f"## (a) Where the policy's view comes from, real drive `{args.coverage_world}`",
            "",
            "Agents at the pose offsets below from every 2nd recorded frame; fractions of all the view's pixels.",
            "",
            "| variant | lateral m | rotation rad | own frame | neighbour frames | inpainted | unfilled (black) |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for r in coverage:
            lines.append(
                f"| {r['variant']} | {r['lateral_m']:+.1f} | {r['rotation_rad']:+.2f} | {r['frame']:.3f} | "
                f"{r['neighbour']:.3f} | {r['inpainted']:.3f} | {r['unfilled']:.4f} |"
            )
        lines.append("")
    if speed:
        lines += [
            f"## (b) Cost per step, world `{args.speed_world}`, {args.steps} expert steps, one env, one process",
            "",
            "| task | filling | warp ms / step (filling included) | total ms / step | view from own frame | "
            "filled from neighbours or inpainting |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for r in speed:
            lines.append(
                f"| {r['task']} | {r['filling']} | {r['warp_ms']:.3f} | {r['total_ms']:.3f} | {r['frame']:.4f} | "
                f"{r['filled_other']:.4f} |"
            )
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coverage-world", default="/tmp/dh/ws-st/world", help="a world built from a real drive")
    parser.add_argument("--speed-world", default="/tmp/rec/demo/world")
    parser.add_argument("--tasks", default="lane,follow")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--skip", choices=("coverage", "speed"), action="append", default=[])
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    coverage = [] if "coverage" in args.skip else coverage_rows(args.coverage_world)
    speed = [] if "speed" in args.skip else speed_rows(args.speed_world, tuple(args.tasks.split(",")), args.steps)
    after = os.getloadavg()
    load = f"before `{before}`; 1/5/15-min load average after {after[0]:.2f} / {after[1]:.2f} / {after[2]:.2f}"
    report = markdown(coverage, speed, args, load)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report)
    print(report)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
