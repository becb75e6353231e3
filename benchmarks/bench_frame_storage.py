"""What storing frames as JPEG image stacks (the trace's and the world's default, `sim/image_stack.py`) changes,
against frames stored losslessly. Depth is stored losslessly either way (its float16 bits in PNG), so only the
frames' JPEG rounding can change a figure.

1. View fidelity against ground truth (the figures of `drivesim bench fidelity`): a synthetic drive (seed 0,
   N_FRAMES frames) rendered at the trace's working size (640x400), its depth estimated (plane, mvs; and the ground
   truth) from the frames as stored (raw, or JPEG at quality 95), then, as build-world does, frames shrunk by area
   and depth by block minimum to the simulator's size (320x200), the world's frames stored raw or as JPEG again;
   novel views at the bench's offsets warped from them and scored against the world rendered there. Reported: PSNR
   (dB) of each storage and the difference.
2. The simulator's observations: a world built from a lossless chain (`ingest --set image.codec=png`, `build-world
   --set frame_codec=png`, `--reference`) and the default one (`--world`), from the same recording; the same expert
   episodes (same seeds) of each task stepped on both; reported: PSNR between the two observations, the share of
   pixels that differ, the largest difference.

Usage: python benchmarks/bench_frame_storage.py --reference W_PNG --world W_JPEG [--steps 200]
Writes benchmarks/results/frame_storage.md and .json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _lib.observations import observation_difference
from _lib.report import measured_now, write_markdown

from drivesim.bench.fidelity import DEFAULT_OFFSETS, image_metrics, render_drive
from drivesim.sim.geometry import invert, pose_2d, scale_intrinsics
from drivesim.sim.image_stack import DEFAULT_JPEG_QUALITY, decode_frame, encode_frame
from drivesim.sim.warp import forward_warp
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth
from drivesim.stages.world.build import resize_depth, resize_frames

RESULTS = Path(__file__).resolve().parent / "results" / "frame_storage.md"
N_FRAMES, TRACE_W, TRACE_H, SIM_W, SIM_H, VIEW_FRAMES = 24, 640, 400, 320, 200, 4


def jpeg_round_trip(frames: np.ndarray, quality: int = DEFAULT_JPEG_QUALITY) -> np.ndarray:
    """(N, H, W, 3) uint8 frames as an image stack gives them back: JPEG at `quality`, decoded."""
    return np.stack([decode_frame(encode_frame(f, "jpeg", quality), f.shape, np.dtype(np.uint8)) for f in frames])


def _world_inputs(frames: np.ndarray, depth_m: np.ndarray, quality: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The world's frames (JPEG at `quality`, or raw for None) and depth (float16, as stored) from trace frames and
    depth, as build-world makes them."""
    small = resize_frames(frames, SIM_W, SIM_H)
    small = jpeg_round_trip(small, quality) if quality is not None else small
    depth = resize_depth(depth_m, SIM_W, SIM_H, "min")
    limit = float(np.finfo(np.float16).max)
    depth = np.where(np.isfinite(depth), np.minimum(depth, limit), depth).astype(np.float16).astype(np.float32)
    return small, depth


def view_fidelity(quality: int, sources: list[str]) -> list[dict[str, Any]]:
    """Per depth source and offset: mean PSNR of the views warped from raw and from JPEG-stored frames."""
    drive = render_drive(0, N_FRAMES, TRACE_W, TRACE_H)
    stored = {"raw": drive.rgb, "jpeg": jpeg_round_trip(drive.rgb, quality)}
    K_sim = scale_intrinsics(drive.K, SIM_W / TRACE_W, SIM_H / TRACE_H)
    frames = np.linspace(2, N_FRAMES - 3, VIEW_FRAMES).round().astype(int)
    truths = {}
    for i in frames:
        for offset in DEFAULT_OFFSETS:
            T_vehicle = drive.T_world_vehicle[i] @ pose_2d(0.0, offset.lateral_m, np.deg2rad(offset.yaw_deg))
            T_world_target = T_vehicle @ drive.T_vehicle_camera
            truths[(i, offset.name)] = (T_world_target, drive.world.render(T_world_target, K_sim, SIM_W, SIM_H)[0])
    rows = []
    for source in sources:
        psnr: dict[tuple[str, str], list[float]] = {}
        for kind, trace_frames in stored.items():
            if source == "ground_truth":
                depth = drive.depth_m
            else:
                depth = np.empty(drive.depth_m.shape, np.float32)
                estimate_depth(trace_frames, drive.K, drive.T_world_camera, drive.T_vehicle_camera, None,
                               DepthConfig(method=source), depth)  # fmt: skip
            world_frames, world_depth = _world_inputs(trace_frames, depth, quality if kind == "jpeg" else None)
            for (i, offset), (T_world_target, truth) in truths.items():
                warped = forward_warp(
                    torch.from_numpy(world_frames[i]), torch.from_numpy(np.ascontiguousarray(world_depth[i])), K_sim,
                    invert(T_world_target) @ drive.T_world_camera[i], K_sim, SIM_W, SIM_H,
                )  # fmt: skip
                metrics = image_metrics(warped.rgb.numpy(), truth, warped.valid.numpy())
                psnr.setdefault((kind, offset), []).append(metrics["psnr_db"])
        for offset in DEFAULT_OFFSETS:
            raw_db, jpeg_db = float(np.mean(psnr[("raw", offset.name)])), float(np.mean(psnr[("jpeg", offset.name)]))
            rows.append({"source": source, "offset": offset.name, "psnr_raw_db": raw_db, "psnr_jpeg_db": jpeg_db})
            print(f"{source} {offset.name}: raw {raw_db:.3f} / jpeg {jpeg_db:.3f} dB", flush=True)
    return rows


def observation_change(reference: Path, world: Path, tasks: list[str], steps: int) -> list[dict[str, Any]]:
    """Per task: how the observations of the same expert steps differ between the lossless and the JPEG world."""
    rows = []
    for task in tasks:
        rows.append(observation_difference(reference, world, task, steps))
        print(rows[-1], flush=True)
    return rows


def decode_ms(world: Path, samples: int = 300) -> dict[str, float]:
    """Median milliseconds to read one random frame of the world's frames and of its depth."""
    from drivesim.sim.world import World

    loaded = World.load(world)
    rng = np.random.default_rng(0)
    out = {}
    for name, array in (("frames", loaded.frames), ("depth_m", loaded.depth_m)):
        times = []
        for i in rng.integers(0, len(array), samples):
            start = time.perf_counter()
            np.asarray(array[int(i)])
            times.append(time.perf_counter() - start)
        out[name] = 1e3 * float(np.median(times))
    return out


def markdown(raw: dict[str, Any]) -> list[str]:
    """The report's lines."""
    m = raw["measured"]
    lines = [
        "## Frames stored as JPEG against lossless",
        "",
        f"Machine: {m['machine']}. Date: {m['date_utc']} UTC. Load average {m['load_average_1_5_15_min']}. "
        f"Reproduce: `{raw['command']}`.",
        "",
        f"Views warped from a synthetic drive (seed 0, {N_FRAMES} frames rendered at {TRACE_W}x{TRACE_H}, the "
        f"trace's size; the world at {SIM_W}x{SIM_H}) whose trace and world frames are stored raw or as JPEG "
        f"(quality {raw['quality']}, 4:4:4; depth estimated from the stored trace frames; depth float16 "
        "either way), PSNR over the filled pixels against the world rendered at the view (the view figures of "
        f"`drivesim bench fidelity`), mean over {VIEW_FRAMES} frames:",
        "",
        "| depth | view | PSNR raw dB | PSNR JPEG dB | change dB |",
        "|---|---|---|---|---|",
    ]
    for r in raw["views"]:
        lines.append(
            f"| {r['source']} | {r['offset']} | {r['psnr_raw_db']:.3f} | {r['psnr_jpeg_db']:.3f} "
            f"| {r['psnr_jpeg_db'] - r['psnr_raw_db']:+.3f} |"
        )
    worst = max(abs(r["psnr_jpeg_db"] - r["psnr_raw_db"]) for r in raw["views"])
    lines += ["", f"Largest change: {worst:.3f} dB (target: within 0.2 dB).", ""]
    if raw["observations"]:
        lines += [
            f"The simulator's observations on a world of {raw['world_info']}, built by a lossless chain (trace and "
            "world frames PNG) and by the default one (JPEG), the same expert steps:",
            "",
            "| task | steps | PSNR between them dB | pixels differing | mean difference (of 255) | largest |",
            "|---|---|---|---|---|---|",
        ]
        for r in raw["observations"]:
            lines.append(
                f"| {r['task']} | {r['steps']} | {r['psnr_db']:.1f} | {100 * r['pixels_differing']:.1f} % "
                f"| {r['mean_abs_diff']:.2f} | {r['max_abs_diff']:.0f} |"
            )
        d = raw["decode_ms"]
        lines += [
            "",
            f"Reading one random frame of that world: frames {d['frames']:.3f} ms, depth {d['depth_m']:.3f} ms "
            "(median of 300).",
        ]
    lines.append("")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, default=None, help="a world built with lossless (png) frames")
    parser.add_argument("--world", type=Path, default=None, help="the same drive's world at the default settings")
    parser.add_argument("--steps", type=int, default=200, help="expert steps per task")
    parser.add_argument("--tasks", default="lane,overtake", help="comma-separated tasks")
    parser.add_argument("--quality", type=int, default=DEFAULT_JPEG_QUALITY, help="JPEG quality of the views part")
    parser.add_argument("--sources", default="ground_truth,plane,mvs", help="depth sources of the views part")
    parser.add_argument("--output", type=Path, default=RESULTS, help="markdown report to write")
    args = parser.parse_args()
    tasks = [t for t in args.tasks.split(",") if t]
    worlds = args.reference is not None and args.world is not None
    info = json.loads((args.world / "world.json").read_text()) if worlds else {}
    raw = {
        "measured": measured_now(),
        "command": "python benchmarks/bench_frame_storage.py --reference W_PNG --world W_JPEG "
        f"--steps {args.steps} --tasks {args.tasks} --quality {args.quality} --sources {args.sources}",
        "quality": args.quality,
        "world_info": f"{info.get('frame_count')} frames, {info.get('path_length_m', 0):.0f} m, "
        f"{info.get('depth_method')} depth",
        "observations": observation_change(args.reference, args.world, tasks, args.steps) if worlds else [],
        "decode_ms": decode_ms(args.world) if worlds else {},
        "views": view_fidelity(args.quality, [s for s in args.sources.split(",") if s]),
    }
    write_markdown(args.output, markdown(raw), raw)


if __name__ == "__main__":
    main()
