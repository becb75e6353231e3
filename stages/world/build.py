"""The `drivesim build-world` stage: the simulatable world from the trace and the preprocessed artifact.

The world's schema is in `sim/world.py` (the simulator's loader). Frames and depth are resized to the simulation
resolution chunk by chunk and written frame by frame into image stacks (`sim/image_stack.py`: frames as JPEG or
PNG, depth as float16 (`WORLD_DEPTH_DTYPE`) in lossless PNG), the pages of memory-mapped inputs released after each
chunk, so memory stays flat whatever the drive's length.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.npy_files import release_pages
from drivesim.pipeline.progress import progress_bar
from drivesim.pipeline.stage import BuildContext
from drivesim.sim.geometry import scale_intrinsics
from drivesim.sim.image_stack import ImageStack, ImageStackWriter, stack_path
from drivesim.sim.world import WORLD_DEPTH_DTYPE, WORLD_FORMAT_VERSION
from drivesim.stages.ingest.trace import TraceView, open_trace
from drivesim.stages.preprocess.artifact import POSE_ARRAYS, Preprocessed, load_preprocessed
from drivesim.stages.world.birdseye import write_birdseye
from drivesim.stages.world.config import WorldConfig
from drivesim.stages.world.pointcloud import fuse_pointcloud
from drivesim.stages.world.summary import WorldSummary

PREPROCESS_HINT = "drivesim preprocess"
_CHUNK_FRAMES = 16


def sim_resolution(width_px: int, height_px: int, sim_width_px: int) -> tuple[int, int]:
    """(width, height) of the simulated image: `sim_width_px` wide, keeping the recording's aspect ratio."""
    return int(sim_width_px), max(1, round(height_px * sim_width_px / width_px))


def resize_depth(depth_m: np.ndarray, width_px: int, height_px: int, mode: str) -> np.ndarray:
    """Resize (..., H, W) depth to (..., height_px, width_px) by block minimum ("min") or nearest pixel ("nearest").

    Block minimum is hand-written with `np.minimum.reduceat` because OpenCV has no min-pooling resize for
    non-integer factors; each output pixel takes the nearest surface among the source pixels it covers.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    src_h, src_w = depth.shape[-2:]
    if mode == "nearest":
        rows = np.minimum(((np.arange(height_px) + 0.5) * src_h / height_px).astype(int), src_h - 1)
        cols = np.minimum(((np.arange(width_px) + 0.5) * src_w / width_px).astype(int), src_w - 1)
        return depth[..., rows[:, None], cols[None, :]]
    rows = np.minimum((np.arange(height_px) * src_h // height_px), src_h - 1)
    cols = np.minimum((np.arange(width_px) * src_w // width_px), src_w - 1)
    clean = np.where(np.isnan(depth), np.inf, depth)
    pooled = np.minimum.reduceat(clean, rows, axis=-2)
    return np.minimum.reduceat(pooled, cols, axis=-1).astype(np.float32)


def resize_frames(frames: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Resize (B, H, W, 3) uint8 frames with cv2.INTER_AREA (the anti-aliased choice for shrinking)."""
    return np.stack([cv2.resize(np.asarray(f), (width_px, height_px), interpolation=cv2.INTER_AREA) for f in frames])


def build_world(ctx: BuildContext) -> WorldSummary:
    """Write the world's files into `ctx.dir` from the trace and the preprocessed poses and depth."""
    cfg: WorldConfig = ctx.config  # type: ignore[assignment]
    trace_dir, pre_dir = ctx.inputs["trace"], ctx.inputs["preprocessed"]
    started = time.perf_counter()
    trace = open_trace(trace_dir)
    pre = load_preprocessed(pre_dir)
    frame_index = pre.poses["frame_index"]
    n = pre.frame_count
    src_h, src_w = trace.frames.shape[1:3]
    _check_preprocessed(trace, pre, pre_dir)
    w, h = sim_resolution(src_w, src_h, cfg.sim_width_px)
    K_sim = scale_intrinsics(trace.K, w / src_w, h / src_h)
    far_depth_m = float(pre.origin.get("max_depth_m") or np.inf)
    _write_sim_frames(ctx.dir, trace, pre, (w, h), cfg)

    camera = {
        "width_px": w,
        "height_px": h,
        "K": K_sim.tolist(),
        "T_vehicle_camera": trace.T_vehicle_camera.tolist(),
        "camera_height_m": trace.calibration.get("camera_height_m"),
        "source_width_px": int(src_w),
        "source_height_px": int(src_h),
    }
    (ctx.dir / "camera.json").write_text(json.dumps(camera, indent=2) + "\n")
    path = {key: pre.poses[key] for key in POSE_ARRAYS}
    np.savez(ctx.dir / "path.npz", **path)
    curvature = path["curvature_1pm"]
    path_length_m = float(path["arc_length_m"][-1] - path["arc_length_m"][0])
    info = {
        "format": WORLD_FORMAT_VERSION,
        "frame_count": int(n),
        "road_width_m": cfg.road_width_m,
        "lane_width_m": cfg.lane_width_m,
        "path_length_m": round(path_length_m, 3),
        "curvature_min_1pm": round(float(curvature.min()), 6),
        "curvature_max_1pm": round(float(curvature.max()), 6),
        "pose_source": pre.origin.get("pose_source"),
        "origin_lat_deg": pre.origin.get("origin_lat_deg"),
        "origin_lon_deg": pre.origin.get("origin_lon_deg"),
        "origin_alt_m": pre.origin.get("origin_alt_m"),
        "depth_method": pre.origin.get("depth_method"),
        "far_depth_m": pre.origin.get("max_depth_m"),
    }
    (ctx.dir / "world.json").write_text(json.dumps(info, indent=2) + "\n")

    point_count = 0
    if cfg.pointcloud.enabled:
        point_count = fuse_pointcloud(
            _FrameLookup(trace.frames, frame_index),
            pre.depth_m,
            trace.K,
            pre.poses["T_world_camera"],
            far_depth_m,
            cfg.pointcloud,
            ctx.dir / "pointcloud.ply",
        )
    write_birdseye(
        ctx.dir / "birdseye.png",
        path["x_m"],
        path["y_m"],
        path["yaw_rad"],
        curvature,
        cfg.lane_width_m,
        title=f"reference path: {n} frames, {path_length_m:.1f} m ({info['pose_source']})",
    )
    return WorldSummary(
        frame_count=int(n),
        path_length_m=info["path_length_m"],
        curvature_min_1pm=info["curvature_min_1pm"],
        curvature_max_1pm=info["curvature_max_1pm"],
        sim_width_px=w,
        sim_height_px=h,
        pointcloud_points=point_count,
        pose_source=info["pose_source"],
        depth_method=info["depth_method"],
        seconds=round(time.perf_counter() - started, 3),
    )


def _check_preprocessed(trace: TraceView, pre: Preprocessed, pre_dir: Path) -> None:
    """Refuse (one line) preprocessed files that do not fit the trace: depth of another size, or frames it lacks."""
    src_h, src_w = trace.frames.shape[1:3]
    frame_index = pre.poses["frame_index"]
    if pre.depth_m.shape[1:] != (src_h, src_w):
        raise InputError(
            f"the depth is {pre.depth_m.shape[2]}x{pre.depth_m.shape[1]} but the trace's frames are {src_w}x{src_h}; "
            f"run `{PREPROCESS_HINT} --force`",
            pre_dir,
        )
    if frame_index[-1] >= trace.frames.shape[0]:
        raise InputError(
            f"refers to trace frame {frame_index[-1]} of {trace.frames.shape[0]}; run `{PREPROCESS_HINT} --force`",
            pre_dir,
        )


def _write_sim_frames(
    folder: Path, trace: TraceView, pre: Preprocessed, size: tuple[int, int], cfg: WorldConfig
) -> None:
    """frames.imgs and depth_m.imgs: the preprocessed frames and their depth at the simulator's (width, height)
    `size`, a chunk of frames at a time."""
    w, h = size
    n = pre.frame_count
    frames_out = ImageStackWriter(stack_path(folder, "frames"), (h, w, 3), np.uint8, cfg.frame_codec, cfg.jpeg_quality)
    depth_out = ImageStackWriter(stack_path(folder, "depth_m"), (h, w), WORLD_DEPTH_DTYPE, "png")
    try:
        with progress_bar(f"world frames at {w}x{h}", total=n) as (progress, task):
            resize_into(
                trace.frames,
                pre.poses["frame_index"],
                pre.depth_m,
                frames_out,
                depth_out,
                cfg.depth_resize,
                lambda done: progress.advance(task, done),
            )
    finally:
        frames_out.close()
        depth_out.close()


def resize_into(
    frames: np.ndarray | ImageStack,
    frame_index: np.ndarray,
    depth_m: np.ndarray | ImageStack,
    frames_out: np.ndarray | ImageStackWriter,
    depth_out: np.ndarray | ImageStackWriter,
    depth_resize: str,
    progress: Callable[[int], None] | None = None,
    chunk_frames: int = _CHUNK_FRAMES,
) -> None:
    """Fill `frames_out` (N, h, w, 3) with frames[frame_index] and `depth_out` (N, h, w) with `depth_m` (N, H, W),
    both resized to (w, h), `chunk_frames` at a time; the outputs are arrays or image stack writers (appended to).

    Memory stays flat in N: after each chunk the pages it touched in memory-mapped inputs and outputs are released
    (`release_pages`). Depth is stored in `depth_out`'s dtype; finite depth beyond float16's range is clipped to it.
    """
    n = len(frame_index)
    h, w = _frame_shape(depth_out)[:2]
    limit = float(np.finfo(depth_out.dtype).max)
    for start in range(0, n, chunk_frames):
        stop = min(n, start + chunk_frames)
        _put(frames_out, start, resize_frames(frames[frame_index[start:stop]], w, h))
        depth = resize_depth(np.asarray(depth_m[start:stop]), w, h, depth_resize)
        _put(depth_out, start, np.where(np.isfinite(depth), np.minimum(depth, limit), depth).astype(depth_out.dtype))
        for array in (frames, depth_m, frames_out, depth_out):
            release_pages(array)
        if progress is not None:
            progress(stop - start)


def _frame_shape(out: np.ndarray | ImageStackWriter) -> tuple[int, ...]:
    return out.frame_shape if isinstance(out, ImageStackWriter) else out.shape[1:]


def _put(out: np.ndarray | ImageStackWriter, start: int, rows: np.ndarray) -> None:
    """Rows start.. of `out`: assigned into an array, appended to a writer (which is written in order)."""
    if isinstance(out, ImageStackWriter):
        if out.rows_written != start:
            raise ValueError(f"rows must be written in order: row {start} after {out.rows_written}")
        out.write_rows(rows)
    else:
        out[start : start + len(rows)] = rows


class _FrameLookup:
    """The trace frames of the preprocessed selection, indexed 0..N-1 without reading the others."""

    def __init__(self, frames: np.ndarray, frame_index: np.ndarray) -> None:
        self._frames = frames
        self._index = frame_index
        self._mmap = getattr(frames, "_mmap", None)  # the trace's mapping, for release_pages

    def __getitem__(self, key: tuple) -> np.ndarray:
        i, *rest = key
        return self._frames[(int(self._index[i]), *rest)]
