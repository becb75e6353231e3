"""Inserted cars on a gray camera (issue 20 item 6): the car-fidelity bench's synthetic part on a gray world.

The synthetic drive of `drivesim bench car-fidelity` (frames with true depth and poses) is turned gray (luma, as a
monochrome camera records it), and so is the true render with the car 10 m ahead. The simulator's view with the
inserted car is compared with that gray truth with the camera taken as colour (today's behaviour: the car drawn and
harmonized in its paint colours) and as monochrome (detected from the gray frames: the car drawn in luma):
PSNR and SSIM over the true car mask, and the colour left on the car (mean and largest max - min channel spread over
the car's pixels; a gray camera shows 0).

    .venv/bin/python benchmarks/bench_car_gray.py   # writes benchmarks/results/car_gray.md
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "car_gray.md"
OFFSETS_M = (0.0, 0.5, 1.0)


def gray(rgb: np.ndarray) -> np.ndarray:
    """Luma of uint8 RGB images (..., 3) as 3 equal channels."""
    flat = rgb.reshape(-1, *rgb.shape[-3:])
    luma = np.stack([cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY) for f in flat])
    return np.repeat(luma[..., None], 3, axis=-1).reshape(rgb.shape)


def run(frames: int, seed: int) -> list[dict]:
    """Rows per offset and camera assumption: means over `frames` frames."""
    import torch

    from drivesim.bench.car_fidelity import _CAR_ID, CAR_AHEAD_M, true_view, world_from_drive
    from drivesim.bench.fidelity import image_metrics, render_drive
    from drivesim.sim.geometry import pose_2d, yaw_of
    from drivesim.sim.vehicle_library import VehicleLibrary
    from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer

    torch.set_num_threads(1)
    drive = render_drive(seed, 4 * frames + 4, 320, 200)
    colour_frames = drive.rgb
    drive = dataclasses.replace(drive, rgb=gray(colour_frames))
    world = world_from_drive(drive, Path("."))
    model = VehicleLibrary.procedural(count=4, seed=seed).models[0]
    views = {
        "colour (today)": ViewSynthesizer(world, ViewConfig(monochrome=False)),
        "monochrome (detected)": ViewSynthesizer(world, ViewConfig()),
    }
    assert views["monochrome (detected)"].monochrome, "the gray frames must be detected as a gray camera"
    any_view = views["colour (today)"]
    size = (any_view.config.out_width_px, any_view.config.out_height_px)
    sums: dict[tuple, list[dict]] = {}
    for k in range(frames):
        i = 4 * k + 1
        T_world_car = drive.T_world_vehicle[i] @ pose_2d(CAR_AHEAD_M, 0.0, 0.0)
        car_meshes = [dataclasses.replace(m.transformed(T_world_car), object_id=_CAR_ID) for m in model.full]
        placement = CarPlacement(model, float(T_world_car[0, 3]), float(T_world_car[1, 3]), float(yaw_of(T_world_car)))
        for offset in OFFSETS_M:
            T_world_agent = drive.T_world_vehicle[i] @ pose_2d(0.0, offset, 0.0)
            truth, car_mask = true_view(
                drive, car_meshes, T_world_agent @ drive.T_vehicle_camera, any_view.K_view, size
            )
            truth = gray(truth)
            agent = (np.array([i]), T_world_agent[0, 3:4], T_world_agent[1, 3:4], np.atleast_1d(yaw_of(T_world_agent)))
            for name, vs in views.items():
                out = vs.render(*agent, [[placement]])
                view = out.rgb[0]
                car = image_metrics(view, truth, car_mask)
                pixels = view[out.car_mask[0]].astype(int)
                spread = pixels.max(axis=-1) - pixels.min(axis=-1) if len(pixels) else np.zeros(1)
                sums.setdefault((offset, name), []).append(
                    {"psnr_car_db": car["psnr_db"], "ssim_car": car["ssim"], "spread_mean": float(spread.mean()),
                     "spread_max": float(spread.max())}
                )  # fmt: skip
    rows = []
    for (offset, name), values in sums.items():
        row = {"offset_m": offset, "camera": name}
        row.update({key: float(np.mean([v[key] for v in values])) for key in values[0]})
        row["spread_max"] = float(max(v["spread_max"] for v in values))
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    before = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows = run(args.frames, args.seed)
    after = os.getloadavg()
    lines = [
        "# Inserted cars on a gray camera (issue 20 item 6)",
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- command: `python benchmarks/bench_car_gray.py --frames {args.frames} --seed {args.seed}`",
        f"- load: before `{before}`; after {after[0]:.2f} / {after[1]:.2f} / {after[2]:.2f}",
        "- data: the car-fidelity bench's synthetic drive and true render (car 10 m ahead), both turned gray (luma)",
        "",
        "PSNR / SSIM over the true car mask against the gray truth; colour spread = max - min of R, G, B over the "
        "inserted car's pixels (grey levels; 0 on a gray camera). Means over the frames (spread max: the largest).",
        "",
        "| offset m | camera taken as | PSNR car dB | SSIM car | colour spread mean | colour spread max |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['offset_m']:.1f} | {r['camera']} | {r['psnr_car_db']:.2f} | {r['ssim_car']:.3f} | "
            f"{r['spread_mean']:.1f} | {r['spread_max']:.0f} |"
        )
    report = "\n".join(lines) + "\n"
    raw = {
        "frames": args.frames,
        "seed": args.seed,
        "load_before": before,
        "load_after_1_5_15_min": after,
        "rows": rows,
    }
    write_markdown(args.output, [report], raw)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
