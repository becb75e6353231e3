"""What storing depth as float16 (the preprocessed artifact's and the world's default) changes, against float32.

1. View fidelity against ground truth (the figures of `drivesim bench fidelity`): a synthetic drive (seed 0, 24
   frames at 320x200) with its depth from plane, mvs and the ground truth; novel views at the bench's offsets
   (0.5 / 1.0 / 1.5 m lateral, -5 / +5 deg yaw) warped with each depth as float32 and as float16 and scored against
   the world rendered there. Reported: PSNR (dB) of each, and the difference.
2. The simulator's observations: a world built with float32 depth (`--world`) and the same world with its depth
   rounded to float16 (what build-world now writes), the same expert episodes (same seeds) of each task stepped on
   both; reported: PSNR between the two observations, the share of pixels that differ, the largest difference.
   Frames (uint8 at the simulator's size) are stored as before, so only depth can change an observation.

Usage: python benchmarks/bench_storage_fidelity.py --world W [--steps 200]   (W: a world with float32 depth)
Writes benchmarks/results/storage_fidelity.md and .json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _lib.observations import observation_difference
from _lib.report import measured_now, write_markdown

from drivesim.bench.fidelity import DEFAULT_OFFSETS, image_metrics, render_drive
from drivesim.sim.geometry import invert, pose_2d
from drivesim.sim.warp import forward_warp
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth

RESULTS = Path(__file__).resolve().parent / "results" / "storage_fidelity.md"
N_FRAMES, WIDTH_PX, HEIGHT_PX, VIEW_FRAMES = 24, 320, 200, 4


def as_stored(depth_m: np.ndarray) -> np.ndarray:
    """Depth as build-world stores it (float16, finite values clipped to its range), read back as float32."""
    limit = float(np.finfo(np.float16).max)
    return np.where(np.isfinite(depth_m), np.minimum(depth_m, limit), depth_m).astype(np.float16).astype(np.float32)


def view_fidelity() -> list[dict[str, Any]]:
    """Per depth source and offset: mean PSNR of the views warped with float32 and with float16 depth."""
    drive = render_drive(0, N_FRAMES, WIDTH_PX, HEIGHT_PX)
    estimates = {"ground_truth": drive.depth_m}
    for method in ("plane", "mvs"):
        out = np.empty(drive.depth_m.shape, np.float32)
        cfg = DepthConfig(method=method)
        estimate_depth(drive.rgb, drive.K, drive.T_world_camera, drive.T_vehicle_camera, None, cfg, out)
        estimates[method] = out
    frames = np.linspace(2, N_FRAMES - 3, VIEW_FRAMES).round().astype(int)
    rows = []
    for source, depth in estimates.items():
        for offset in DEFAULT_OFFSETS:
            psnr = {"float32": [], "float16": []}
            for i in frames:
                T_vehicle = drive.T_world_vehicle[i] @ pose_2d(0.0, offset.lateral_m, np.deg2rad(offset.yaw_deg))
                T_world_target = T_vehicle @ drive.T_vehicle_camera
                truth, _ = drive.world.render(T_world_target, drive.K, WIDTH_PX, HEIGHT_PX)
                T_dst_src = invert(T_world_target) @ drive.T_world_camera[i]
                for kind, d in (("float32", depth[i]), ("float16", as_stored(depth[i]))):
                    warped = forward_warp(
                        torch.from_numpy(drive.rgb[i]), torch.from_numpy(np.ascontiguousarray(d)), drive.K,
                        T_dst_src, drive.K, WIDTH_PX, HEIGHT_PX,
                    )  # fmt: skip
                    psnr[kind].append(image_metrics(warped.rgb.numpy(), truth, warped.valid.numpy())["psnr_db"])
            p32, p16 = float(np.mean(psnr["float32"])), float(np.mean(psnr["float16"]))
            rows.append({"source": source, "offset": offset.name, "psnr32_db": p32, "psnr16_db": p16})
            print(f"{source} {offset.name}: {p32:.3f} / {p16:.3f} dB", flush=True)
    return rows


def float16_copy(world: Path, folder: Path) -> Path:
    """`world` with its depth rounded to float16 (every other file linked), in `folder`."""
    copy = folder / "world_float16"
    copy.mkdir()
    for path in world.iterdir():
        if path.name != "depth_m.npy":
            (copy / path.name).symlink_to(path.resolve())
    depth = np.load(world / "depth_m.npy", mmap_mode="r")
    out = np.lib.format.open_memmap(copy / "depth_m.npy", "w+", np.float16, depth.shape)
    for start in range(0, depth.shape[0], 64):
        out[start : start + 64] = as_stored(np.asarray(depth[start : start + 64], np.float32))
    out.flush()
    return copy


def observation_change(world: Path, tasks: list[str], steps: int) -> list[dict[str, Any]]:
    """Per task: how the observations of the same expert steps differ between float32 and float16 depth."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="drivesim-storage-") as tmp:
        copy = float16_copy(world, Path(tmp))
        for task in tasks:
            rows.append(observation_difference(world, copy, task, steps))
            print(rows[-1], flush=True)
        shutil.rmtree(copy, ignore_errors=True)
    return rows


def world_info(world: Path) -> str:
    """A few words on a world: frames, path length, depth method."""
    info = json.loads((world / "world.json").read_text())
    return f"{info['frame_count']} frames, {info['path_length_m']:.0f} m, {info['depth_method']} depth"


def markdown(raw: dict[str, Any]) -> list[str]:
    """The report's lines."""
    m = raw["measured"]
    lines = [
        "## float16 depth against float32",
        "",
        f"Machine: {m['machine']}. Date: {m['date_utc']} UTC. Load average {m['load_average_1_5_15_min']}. "
        f"Reproduce: `{raw['command']}`.",
        "",
        f"Views warped from a synthetic drive (seed 0, {N_FRAMES} frames at {WIDTH_PX}x{HEIGHT_PX}) with float32 "
        "and with float16 depth, PSNR over the filled pixels against the world rendered at the view (the view "
        f"figures of `drivesim bench fidelity`), mean over {VIEW_FRAMES} frames:",
        "",
        "| depth | view | PSNR float32 dB | PSNR float16 dB | change dB |",
        "|---|---|---|---|---|",
    ]
    for r in raw["views"]:
        lines.append(
            f"| {r['source']} | {r['offset']} | {r['psnr32_db']:.3f} | {r['psnr16_db']:.3f} "
            f"| {r['psnr16_db'] - r['psnr32_db']:+.3f} |"
        )
    worst = max(abs(r["psnr16_db"] - r["psnr32_db"]) for r in raw["views"])
    lines += [
        "",
        f"Largest change: {worst:.3f} dB (target: within 0.2 dB).",
        "",
        f"The simulator's observations on a world of {raw['world_info']} with its float32 depth and with the same "
        "depth as float16, the same expert steps:",
        "",
        "| task | steps | PSNR between them dB | pixels differing | largest difference (of 255) | steps identical |",
        "|---|---|---|---|---|---|",
    ]
    for r in raw["observations"]:
        lines.append(
            f"| {r['task']} | {r['steps']} | {r['psnr_db']:.1f} | {100 * r['pixels_differing']:.3f} % "
            f"| {r['max_abs_diff']:.0f} | {r['steps_identical']} |"
        )
    lines.append("")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, required=True, help="a world folder with float32 depth")
    parser.add_argument("--steps", type=int, default=200, help="expert steps per task")
    parser.add_argument("--tasks", default="lane,overtake", help="comma-separated tasks")
    parser.add_argument("--output", type=Path, default=RESULTS, help="markdown report to write")
    args = parser.parse_args()
    if np.load(args.world / "depth_m.npy", mmap_mode="r").dtype != np.float32:
        raise SystemExit(f"{args.world}: its depth is not float32; pass a world built with float32 depth")
    tasks = [t for t in args.tasks.split(",") if t]
    raw = {
        "measured": measured_now(),
        "command": f"python benchmarks/bench_storage_fidelity.py --world W --steps {args.steps} --tasks {args.tasks}",
        "world": str(args.world),
        "world_info": world_info(args.world),
        "observations": observation_change(args.world, tasks, args.steps),
        "views": view_fidelity(),
    }
    write_markdown(args.output, markdown(raw), raw)


if __name__ == "__main__":
    main()
