"""Inserted cars drawn in the right depth order on real drives: background pixels shown through a car body, counted
against the car's own depth buffer over expert overtaking steps (issue 44's occlusion target).

For every env step whose view draws the other car (the CPU path the simulator trains with), the cars are rendered a
second time alone, and `sim.raster.through_body_count` counts the pixels where the car's own depth buffer has the car,
the warped world there is not nearer than the car by more than `OCCLUDER_MIN_GAP` of its depth, and yet the view shows
the world. Beside it: the car pixels a nearer world surface covers (correct occlusion, or depth noise in front of the
car) and all car pixels drawn.

    .venv/bin/python benchmarks/bench_occlusion.py --world 0001=WS/world --world 07=WS2/world --seeds 0,3
Writes benchmarks/results/occlusion.{md,json}.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line
from drivesim.bench.sim_steps import make_env
from drivesim.sim.raster import through_body_count

RESULTS = Path(__file__).resolve().parent / "results" / "occlusion.md"
SHORT_PATH_M = 40.0  # the path an episode needs on a drive given with --short-world (the task's default: 60 m)


@contextmanager
def counting_occlusion() -> Iterator[dict[str, int]]:
    """While active, every car drawn by `ViewSynthesizer._draw_cpu` adds to the yielded counts: "through_body",
    "covered" (car pixels a nearer world surface hides), "car_px" (the car's own pixels) and "views"."""
    from drivesim.sim.view import ViewSynthesizer

    original = ViewSynthesizer._draw_cpu
    counts = {"through_body": 0, "covered": 0, "car_px": 0, "views": 0}

    def draw(self: Any, rgb: Any, depth: Any, scenes: Any, poses: Any, lights: Any, viewers: list[int]) -> Any:
        world_depth = depth.numpy()[viewers].copy()  # before the draw: the warped world's own depth
        out_rgb, car_mask = original(self, rgb, depth, scenes, poses, lights, viewers)
        alone = self.rasterizer.render(scenes, poses, self.K_view, lighting=lights).depth_m.numpy()
        shown = car_mask[viewers]
        counts["through_body"] += through_body_count(alone, world_depth, shown)
        counts["covered"] += int(np.count_nonzero(np.isfinite(alone) & ~shown))
        counts["car_px"] += int(np.count_nonzero(np.isfinite(alone)))
        counts["views"] += len(viewers)
        return out_rgb, car_mask

    ViewSynthesizer._draw_cpu = draw
    try:
        yield counts
    finally:
        ViewSynthesizer._draw_cpu = original


def count_drive(world: str, seed: int, steps: int, config: dict | None) -> dict[str, Any]:
    """`steps` expert steps of the overtake task (eval mode) on `world` from episode seed `seed` on; the counts."""
    env = make_env("overtake", world, None, "eval", config)
    unwrapped = env.unwrapped
    episode = 0
    env.reset(seed=seed)
    began = time.perf_counter()
    with counting_occlusion() as counts:
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(unwrapped.expert_action())
            if terminated or truncated:
                episode += 1
                env.reset(seed=seed + 1000 * episode)
    env.close()
    return {**counts, "steps": steps, "episodes": episode + 1, "wall_s": round(time.perf_counter() - began, 1)}


def report_lines(rows: list[dict[str, Any]], short: set[str], steps: int, load_before: float) -> list[str]:
    """occlusion.md's lines."""
    lines = [
        "# Inserted cars in the right depth order on real drives (issue 44)",
        "",
        f"- machine: {machine_line()}",
        f"- load average {load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the end",
        f"- date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        "- command: `.venv/bin/python benchmarks/bench_occlusion.py " + " ".join(sys.argv[1:]) + "`",
        f"- {steps} expert steps of the overtake task (eval mode, default view, the procedural car library) per row;"
        " episode k of a row starts with seed + 1000 k; the car rendered alone a second time at every step that draws"
        " it",
        *[f"- {name}: episodes start where {SHORT_PATH_M:.0f} m of path is left (a short drive)" for name in short],
        "",
        "| drive | first seed | episodes | views with the car | car pixels | covered by a nearer world surface | "
        "background through the body |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['drive']} | {r['seed']} | {r['episodes']} | {r['views']} | {r['car_px']} | {r['covered']} "
            f"({100 * r['covered'] / max(r['car_px'], 1):.2f} %) | **{r['through_body']}** |"
        )
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", action="append", default=[], help="NAME=WORLD_FOLDER (repeatable)")
    parser.add_argument(
        "--short-world",
        action="append",
        default=[],
        help=f"NAME=WORLD_FOLDER of a drive too short for the task: episodes need {SHORT_PATH_M:.0f} m of path",
    )
    parser.add_argument("--seeds", default="0,3", help="comma-separated first episode seeds, one run of --steps each")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    worlds = dict(item.split("=", 1) for item in args.world + args.short_world)
    short = sorted(item.split("=", 1)[0] for item in args.short_world)
    missing = [path for path in worlds.values() if not (Path(path) / "world.json").is_file()]
    if not worlds or missing:
        sys.exit(f"no world.json in {', '.join(missing) or '(none given)'}: give build-world's folders")
    load_before = os.getloadavg()[0]
    rows = []
    for name, world in worlds.items():
        config = {"min_path_length_m": SHORT_PATH_M} if name in short else None
        for seed in (int(s) for s in args.seeds.split(",")):
            rows.append({"drive": name, "world": world, "seed": seed, **count_drive(world, seed, args.steps, config)})
            print(f"{name} seed {seed}: {rows[-1]['through_body']} through the body", flush=True)
            if rows[-1]["views"] == 0:  # a count over no drawn car would read as a pass
                sys.exit(f"{name}: no step drew the car on the compiled CPU path; nothing was counted")
    raw = {"rows": rows, "load_average_start_end": [load_before, os.getloadavg()[0]]}
    write_markdown(args.out, report_lines(rows, short, args.steps, load_before), raw)


if __name__ == "__main__":
    main()
