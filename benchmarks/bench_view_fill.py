"""No black in the policy's view (issue 20): where the view's pixels come from, and what filling costs per step.

(a) Coverage on a real drive: agents at lateral offsets and heading rotations up to the task's largest (max_lateral_m
    2.5 m, max_rotation_rad 0.5 rad), at every 2nd frame of the drive; the fraction of the policy's view from recorded
    data (the view's own frame, its margins filled from the neighbouring frames, the per-view neighbour frames of
    an option), inpainted, and left unfilled, for the warp alone, with margins, with the per-view neighbour frames,
    and with inpainting. The margins' share is the margin variant's recorded share less the warp alone's at the same
    poses (the margins only add pixels where the frame alone leaves holes: the frame's own pixels are the same).
(b) Speed: expert steps of the lane and follow tasks, one env in one process per variant (a subprocess each, in
    turn, `--rounds` times); warp ms per step (which includes the filling) and total ms per step with filling off
    (the warp alone), inpainting alone, margins and inpainting (the default) and the per-view neighbour frames; with
    `--issue-day-code F` also the code of the day issue 20 was filed (a folder holding its `drivesim` package tree,
    `F/drivesim/{sim,...}`, e.g. `git archive 0bc1b72`), whose warp filled nothing, in the same rounds.

    .venv/bin/python benchmarks/bench_view_fill.py --coverage-world W --skip speed
    .venv/bin/python benchmarks/bench_view_fill.py --speed-world W --skip coverage --output .../view_fill_speed.md

Writes benchmarks/results/view_fill.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "view_fill.md"
POSES = ((0.0, 0.0), (1.0, 0.0), (2.5, 0.0), (0.0, 0.5), (2.5, 0.5), (-2.5, -0.5))
OPTION = (-1, 1, -2)  # ViewConfig.fill_frames to try: the frame behind, the one ahead, the second behind
VARIANTS = {
    "warp only, no margins": {"fill_frames": (), "inpaint": False, "source_margin": 0.0},
    "warp with margins": {"fill_frames": (), "inpaint": False},
    "+ neighbour frames -1, +1, -2 per view (an option)": {"fill_frames": OPTION, "inpaint": False},
    "+ inpainting (the option's whole fill)": {"fill_frames": OPTION},
    "inpainting alone, no margins (the default until 2026-11-26)": {"fill_frames": (), "source_margin": 0.0},
    "margins + inpainting (the default)": {},
}
NO_MARGIN_BASE = "warp only, no margins"  # the own frame's share each margin variant is compared with

SPEED_VARIANTS = {
    "off (the warp alone, no margins)": {"fill_frames": (), "inpaint": False, "source_margin": 0.0},
    "inpainting alone, no margins (the default until 2026-11-26)": {"fill_frames": (), "source_margin": 0.0},
    "margins + inpainting (the default)": {},
    "margins + frames -1, +1, -2 per view + inpainting (an option)": {"fill_frames": OPTION},
}
ISSUE_DAY = "the warp alone, code of the day issue 20 was filed"

_CHILD = """
import json, sys, time
import gymnasium, torch
import drivesim.sim.envs
from drivesim.sim.view import ViewSynthesizer
world, task, steps, flags = sys.argv[1], sys.argv[2], int(sys.argv[3]), json.loads(sys.argv[4])
torch.set_num_threads(1)
env = gymnasium.make(f"drivesim/{task.capitalize()}-v0", world=world, meshes=None)
base = env.unwrapped
env.reset(seed=0)
vs = None
if flags is not None:
    vs = ViewSynthesizer(base.worlds[0], base.sim.renderer.config.model_copy(update=flags))
    base._renderers[0] = base.sim.renderer = vs  # the same view, filling switched as named
for _ in range(5):
    env.step(base.expert_action())
env.reset(seed=0)
if vs is not None:
    base.sim.renderer = vs
    vs.fill_stats.__init__()
base.reset_timings()
episode, start = 0, time.perf_counter()
for _ in range(steps):
    _, _, terminated, truncated, _ = env.step(base.expert_action())
    if terminated or truncated:
        episode += 1
        env.reset(seed=episode)
        if vs is not None:
            base.sim.renderer = vs
seconds = time.perf_counter() - start
n = max(int(base.step_count), 1)
fractions = vs.fill_stats.fractions() if vs is not None else None
print(json.dumps({"warp_ms": base.timings_ms["warp"] / n, "total_ms": 1e3 * seconds / steps, "fractions": fractions}))
"""


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
    own = {(r["lateral_m"], r["rotation_rad"]): r["frame"] for r in rows if r["variant"] == NO_MARGIN_BASE}
    for r in rows:
        with_margins = VARIANTS[r["variant"]].get("source_margin") != 0.0
        r["margins"] = r["frame"] - own[(r["lateral_m"], r["rotation_rad"])] if with_margins else 0.0
        r["frame"] -= r["margins"]
    return rows


def _measure(code: Path | None, world: str, task: str, steps: int, flags: dict | None) -> dict:
    """One subprocess's figures with the `drivesim` package of folder `code` (None: this checkout)."""
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = f"{code}{os.pathsep}{env.get('PYTHONPATH', '')}"
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, world, task, str(steps), json.dumps(flags)],
        capture_output=True, text=True, env=env, check=True,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def speed_rows(world_path: str, tasks: tuple[str, ...], steps: int, rounds: int, issue_day: Path | None) -> list[dict]:
    """(b): ms per expert step (warp and total) with filling off and on, each variant in a subprocess, in turn."""
    variants: dict[str, tuple[Path | None, dict | None]] = {}
    if issue_day is not None:
        variants[ISSUE_DAY] = (issue_day, None)
    variants.update({name: (None, flags) for name, flags in SPEED_VARIANTS.items()})
    rows = []
    for task in tasks:
        runs: dict[str, list[dict]] = {name: [] for name in variants}
        for _ in range(rounds):
            for name, (code, flags) in variants.items():
                runs[name].append(_measure(code, world_path, task, steps, flags))
        for name, results in runs.items():
            fractions = results[-1]["fractions"]
            rows.append({
                "task": task, "filling": name,
                "warp_ms": float(np.mean([r["warp_ms"] for r in results])),
                "total_ms": float(np.mean([r["total_ms"] for r in results])),
                "frame": None if fractions is None else fractions["frame"],
                "filled_other": None if fractions is None else fractions["neighbour"] + fractions["inpainted"],
            })  # fmt: skip
    return rows


def markdown(coverage: list[dict], speed: list[dict], args: argparse.Namespace, load: str) -> str:
    """The report."""
    lines = [
        "# No black in the policy's view: neighbour frames and inpainting (issue 20)",
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `python benchmarks/bench_view_fill.py{_command_arguments(args)}`",
        f"- load: {load}",
        "",
    ]
    if coverage:
        lines += [
            f"## (a) Where the policy's view comes from, real drive `{args.coverage_world}`",
            "",
            "Agents at the pose offsets below from every 2nd recorded frame; fractions of all the view's pixels.",
            "",
            "| variant | lateral m | rotation rad | own frame | its margins (neighbours) | neighbour frames per "
            "view | inpainted | unfilled (black) |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in coverage:
            lines.append(
                f"| {r['variant']} | {r['lateral_m']:+.1f} | {r['rotation_rad']:+.2f} | {r['frame']:.3f} | "
                f"{r['margins']:.3f} | {r['neighbour']:.3f} | {r['inpainted']:.3f} | {r['unfilled']:.4f} |"
            )
        lines.append("")
    if speed:
        lines += [
            f"## (b) Cost per step, world `{args.speed_world}`, {args.steps} expert steps, one env, one process",
            "",
            "| task | filling | warp ms / step (filling included) | total ms / step | recorded data (own frame and "
            "its margins) | neighbour frames per view or inpainting |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for r in speed:
            frame = "" if r["frame"] is None else f"{r['frame']:.4f}"
            other = "" if r["filled_other"] is None else f"{r['filled_other']:.4f}"
            lines.append(
                f"| {r['task']} | {r['filling']} | {r['warp_ms']:.3f} | {r['total_ms']:.3f} | {frame} | {other} |"
            )
        lines += ["", *_ratio_lines(speed), ""]
    return "\n".join(lines)


def _command_arguments(args: argparse.Namespace) -> str:
    """The command line's arguments that the measured parts used."""
    words = "" if "coverage" in args.skip else f" --coverage-world {args.coverage_world}"
    if "speed" not in args.skip:
        words += f" --speed-world {args.speed_world} --tasks {args.tasks} --steps {args.steps} --rounds {args.rounds}"
        words += f" --issue-day-code {args.issue_day_code}" if args.issue_day_code else ""
    words += "".join(f" --skip {part}" for part in args.skip)
    return words + ("" if args.output == RESULTS else f" --output {args.output}")


def _ratio_lines(speed: list[dict]) -> list[str]:
    """Each filling's warp ms per step over the warp alone's (same code) and the issue day's code's, per task."""
    lines = []
    for task in dict.fromkeys(r["task"] for r in speed):
        warp = {r["filling"]: r["warp_ms"] for r in speed if r["task"] == task}
        alone = warp["off (the warp alone, no margins)"]
        for name, ms in warp.items():
            if name in (ISSUE_DAY, "off (the warp alone, no margins)"):
                continue
            against = f"{ms / alone:.2f}x the warp alone"
            if ISSUE_DAY in warp:
                against += f", {ms / warp[ISSUE_DAY]:.2f}x the issue day's warp"
            lines.append(f"- {task}, {name}: {against}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coverage-world", default="/tmp/dh/ws-st/world", help="a world built from a real drive")
    parser.add_argument("--speed-world", default="/tmp/rec/demo/world")
    parser.add_argument("--tasks", default="lane,follow")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--skip", choices=("coverage", "speed"), action="append", default=[])
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--rounds", type=int, default=2, help="subprocess runs per variant, in turn (their mean)")
    parser.add_argument(
        "--issue-day-code", type=Path, default=None, help="a folder with the drivesim package tree of the day issue "
        "20 was filed (F/drivesim/sim, ...): its warp alone is measured in the same rounds"
    )  # fmt: skip
    args = parser.parse_args()
    before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    coverage = [] if "coverage" in args.skip else coverage_rows(args.coverage_world)
    speed = (
        []
        if "speed" in args.skip
        else speed_rows(args.speed_world, tuple(args.tasks.split(",")), args.steps, args.rounds, args.issue_day_code)
    )
    after = os.getloadavg()
    load = f"before `{before}`; 1/5/15-min load average after {after[0]:.2f} / {after[1]:.2f} / {after[2]:.2f}"
    report = markdown(coverage, speed, args, load)
    raw = {"command_arguments": _command_arguments(args), "load": load, "coverage": coverage, "speed": speed}
    write_markdown(args.output, [report], raw)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
