"""The `drivesim preprocess` stage: read the trace, fuse poses, estimate depth, write the preprocessed artifact.

The artifact's schema is in `stages/preprocess/artifact.py`. Depth is streamed frame by frame into a float32 .npy
memmap inside the artifact's temporary folder, the pages of the frames and depth read or written released every
RELEASE_FRAMES frames, so memory stays flat whatever the drive's length; it is then stored frame by frame as float16
in a lossless image stack (depth.imgs, `sim/image_stack.py`) and the float32 file removed.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.npy_files import open_reserved_memmap, release_pages
from drivesim.pipeline.progress import console, progress_bar
from drivesim.pipeline.stage import BuildContext
from drivesim.sim.geometry import invert
from drivesim.sim.image_stack import ImageStack, ImageStackWriter, stack_path
from drivesim.stages.ingest.trace import TraceInfo, open_trace
from drivesim.stages.preprocess import depth as depth_mod
from drivesim.stages.preprocess import poses as poses_mod
from drivesim.stages.preprocess import series as series_mod
from drivesim.stages.preprocess.artifact import DEPTH_DTYPE, POSE_ARRAYS_FLOAT
from drivesim.stages.preprocess.config import PreprocessConfig
from drivesim.stages.preprocess.summary import PreprocessSummary


class LidarPerFrame(Sequence[np.ndarray]):
    """One point cloud per frame, in the vehicle frame at the frame's time, read lazily from the trace's scans.

    Each frame takes the scan nearest in time (none when it is more than `max_gap_s` away: the depth method then
    falls back for that frame). The scan was taken while the vehicle moved, so its points are carried from the
    vehicle pose at the scan's time to the pose at the frame's time (poses interpolated between frames: linear
    position, slerp rotation); at 10 m/s a 50 ms offset would otherwise put everything 0.5 m too near or far.
    """

    def __init__(
        self, info: TraceInfo, frame_times_ns: np.ndarray, T_world_vehicle: np.ndarray, max_gap_s: float = 0.1
    ) -> None:
        scans = info.load_series("lidar_scans")
        points = info.lidar_points()
        if scans is None or points is None or len(scans["t_ns"]) == 0:
            raise InputError("depth.method=lidar but the trace has no lidar scans", info.path)
        self.points = points  # (P, 4) float32, memory-mapped
        self._start = scans["start"]
        self._count = scans["count"]
        scan_t = scans["t_ns"]
        frame_t = np.asarray(frame_times_ns, dtype=np.int64)
        after = np.clip(np.searchsorted(scan_t, frame_t), 0, len(scan_t) - 1)
        before = np.clip(after - 1, 0, len(scan_t) - 1)
        take_before = np.abs(frame_t - scan_t[before]) <= np.abs(scan_t[after] - frame_t)
        self._scan = np.where(take_before, before, after)
        self._usable = np.abs(scan_t[self._scan] - frame_t) <= max_gap_s * 1e9
        self._T_frame_scan = _relative_to_frames(frame_t, T_world_vehicle, scan_t[self._scan])

    def __len__(self) -> int:
        return len(self._scan)

    def __getitem__(self, i: int) -> np.ndarray:
        """(M, 3) float64 points of frame i in the vehicle frame at the frame's time (empty when no scan is near)."""
        if not self._usable[i]:
            return np.empty((0, 3))
        s = self._scan[i]
        xyz = np.asarray(self.points[self._start[s] : self._start[s] + self._count[s], :3], dtype=np.float64)
        T = self._T_frame_scan[i]
        return xyz @ T[:3, :3].T + T[:3, 3]


def _relative_to_frames(frame_t: np.ndarray, T_world_vehicle: np.ndarray, scan_t: np.ndarray) -> np.ndarray:
    """T_vehicle(frame i)_vehicle(scan time i): the vehicle's motion between each frame and its scan, (N, 4, 4)."""
    t_s = (frame_t - frame_t[0]) * 1e-9
    query_s = np.clip((scan_t - frame_t[0]) * 1e-9, t_s[0], t_s[-1])
    rotation = Slerp(t_s, Rotation.from_matrix(T_world_vehicle[:, :3, :3]))(query_s).as_matrix()
    T_world_scan = np.tile(np.eye(4), (len(frame_t), 1, 1))
    T_world_scan[:, :3, :3] = rotation
    for axis in range(3):
        T_world_scan[:, axis, 3] = np.interp(query_s, t_s, T_world_vehicle[:, axis, 3])
    return invert(T_world_vehicle) @ T_world_scan


def select_frames(n_frames: int, cfg: PreprocessConfig) -> slice:
    """The trace frames to preprocess as a slice (a slice keeps memmap views lazy; fancy indexing would copy)."""
    stop = n_frames if cfg.frames.stop is None else min(cfg.frames.stop, n_frames)
    selected = slice(cfg.frames.start, stop, cfg.frames.step)
    count = len(range(*selected.indices(n_frames)))
    if count < 2:
        raise InputError(
            f"frames {cfg.frames.start}:{cfg.frames.stop}:{cfg.frames.step} select {count} of the trace's "
            f"{n_frames} frames; a drive needs at least 2"
        )
    return selected


# The depth methods write float32; it is kept here, inside the artifact's temporary folder, until stored compactly.
DEPTH_WORK_FILE = "depth_float32.npy"
# Frames between releases of the memory-mapped frames' and depth's pages, and frames per chunk of `store_depth`.
RELEASE_FRAMES = 32


def releasing_pages(progress: Callable[[int], None], *arrays: np.ndarray) -> Callable[[int], None]:
    """`progress` that also releases the pages of the memory-mapped `arrays` every RELEASE_FRAMES frames, so that a
    pass over the drive keeps memory flat in its length (`release_pages`)."""
    since = [0]

    def advance(done: int) -> None:
        progress(done)
        since[0] += done
        if since[0] >= RELEASE_FRAMES:
            since[0] = 0
            for array in arrays:
                release_pages(array)

    return advance


def store_depth(depth_m: np.ndarray, path: Path) -> ImageStack:
    """`depth_m` (N, H, W) written to the image stack `path` as DEPTH_DTYPE (finite values beyond its range clipped
    to it; lossless PNG per frame), a chunk of frames at a time; the stored array, read one frame at a time."""
    out = ImageStackWriter(path, depth_m.shape[1:], DEPTH_DTYPE, "png")
    limit = float(np.finfo(DEPTH_DTYPE).max)
    try:
        for start in range(0, depth_m.shape[0], RELEASE_FRAMES):
            chunk = np.asarray(depth_m[start : start + RELEASE_FRAMES])
            out.write_rows(np.where(np.isfinite(chunk), np.minimum(chunk, limit), chunk).astype(DEPTH_DTYPE))
            release_pages(depth_m)
    finally:
        out.close()
    return ImageStack(path)


def build_preprocessed(ctx: BuildContext) -> PreprocessSummary:
    """Fuse poses and estimate per-frame depth for the workspace's trace, writing the files into `ctx.dir`."""
    cfg: PreprocessConfig = ctx.config  # type: ignore[assignment]
    trace_dir = ctx.inputs["trace"]
    started = time.perf_counter()
    trace = open_trace(trace_dir)
    method = _depth_method(cfg, trace)  # before the pose fusion, so that a wrong method is said at once
    depth_cfg = cfg.depth.model_copy(update={"method": method})
    selected = select_frames(trace.frames.shape[0], cfg)
    run_method = _ray_method(cfg, method, trace_dir, selected.indices(trace.frames.shape[0]))
    frame_index = np.arange(trace.frames.shape[0])[selected]
    frames = trace.frames[selected]
    frame_times_ns = trace.frame_times_ns[selected]
    K, T_vehicle_camera = trace.K, trace.T_vehicle_camera

    with console.status("fusing poses"):
        series = series_mod.load_series(trace_dir)
        fused = poses_mod.estimate_poses(
            series, frame_times_ns, cfg.poses, frames=frames, K=K, T_vehicle_camera=T_vehicle_camera
        )
    T_world_vehicle = np.asarray(fused.T_world_vehicle, dtype=float)
    T_world_camera = T_world_vehicle @ T_vehicle_camera
    n, h, w = frames.shape[:3]

    depth_work = open_reserved_memmap(ctx.dir / DEPTH_WORK_FILE, np.float32, (n, h, w))
    right = trace.info.right_frames()[selected] if method == "stereo" else None
    lidar = LidarPerFrame(trace.info, frame_times_ns, T_world_vehicle) if method == "lidar" else None
    inputs = [a for a in (frames, depth_work, right, lidar.points if lidar else None) if a is not None]
    with progress_bar(f"depth ({method}{', on Ray' if run_method else ''})", total=n) as (progress, task):
        depth_summary = depth_mod.estimate_depth(
            frames,
            K,
            T_world_camera,
            T_vehicle_camera,
            trace.calibration.get("camera_height_m"),
            depth_cfg,
            depth_work,
            progress=releasing_pages(lambda done: progress.advance(task, done), *inputs),
            points_vehicle=lidar,
            right_frames=right,
            baseline_m=trace.info.baseline_m if method == "stereo" else None,
            run_method=run_method,
        )
    depth_out = store_depth(depth_work, stack_path(ctx.dir, "depth"))
    del depth_work
    (ctx.dir / DEPTH_WORK_FILE).unlink()
    poses = {
        "frame_index": frame_index.astype(np.int64),
        "t_ns": np.asarray(frame_times_ns, dtype=np.int64),
        **{k: np.asarray(getattr(fused, k), dtype=np.float64) for k in POSE_ARRAYS_FLOAT},
        "T_world_vehicle": T_world_vehicle,
        "T_world_camera": T_world_camera,
    }
    np.savez(ctx.dir / "poses.npz", **poses)
    origin = _write_origin(ctx.dir, fused, method, cfg.depth.max_depth_m, (w, h))
    preview = np.linspace(0, n - 1, min(cfg.preview.frame_count, n)).round().astype(int)
    write_depth_preview(ctx.dir / "depth_preview.png", frames, depth_out, preview, frame_index, cfg.depth.max_depth_m)
    depth_stats = _depth_stats(depth_out, cfg.depth.max_depth_m)
    del depth_out
    return PreprocessSummary(
        pose_source=origin["pose_source"],
        frame_count=int(n),
        path_length_m=round(float(poses["arc_length_m"][-1] - poses["arc_length_m"][0]), 3),
        residual_m=origin["residual_m"],
        depth_method=method,
        width_px=int(w),
        height_px=int(h),
        **depth_stats,
        depth_seconds_per_frame=depth_summary.get("seconds_per_frame"),
        seconds=round(time.perf_counter() - started, 3),
    )


def _depth_method(cfg: PreprocessConfig, trace: Any) -> str:
    """The depth method the config asks for (auto: the best the trace allows), said on the console; a method the
    trace lacks the sensor for is refused with one line."""
    has_lidar = "lidar_scans" in trace.info.series
    has_stereo = trace.info.baseline_m is not None
    if cfg.depth.method == "lidar" and not has_lidar:
        raise InputError("depth.method=lidar but the trace has no point cloud (no PointCloud2 topic); use auto or mvs")
    if cfg.depth.method == "stereo" and not has_stereo:
        raise InputError("depth.method=stereo but the trace has no second camera (frames_right.imgs); use auto or mvs")
    method, why = depth_mod.choose_method(cfg.depth.method, has_lidar, has_stereo)
    console.print(f"depth method: {method} ({why})")
    return method


def _ray_method(
    cfg: PreprocessConfig, method: str, trace_dir: Path, selection: tuple[int, int, int]
) -> depth_mod.DepthMethod | None:
    """With backend ray, the depth method that runs mvs on Ray (Ray's import checked now, before the pose fusion);
    None for the local backend and for a method that runs in this process (said on the console)."""
    if cfg.backend != "ray":
        return None
    if method != "mvs":
        console.print(f"depth method {method} runs in this process (the Ray backend spreads mvs, the camera-only one)")
        return None
    from drivesim.pipeline.ray_cluster import import_ray
    from drivesim.stages.preprocess.depth_ray import ray_depth_method

    import_ray()
    return ray_depth_method(trace_dir, selection, cfg.address)


def _write_origin(folder: Path, fused: Any, method: str, max_depth_m: float, size: tuple[int, int]) -> dict[str, Any]:
    """origin.json: the pose source and its geographic origin, the poses' residual, the depth method and range, the
    frames' (width, height) `size` in px; returns what it wrote."""
    origin = {
        "pose_source": str(fused.source),
        "origin_lat_deg": _float_or_none(getattr(fused, "origin_lat_deg", None)),
        "origin_lon_deg": _float_or_none(getattr(fused, "origin_lon_deg", None)),
        "origin_alt_m": _float_or_none(getattr(fused, "origin_alt_m", None)),
        "residual_m": _rms_or_none(getattr(fused, "residual_m", None)),
        "depth_method": method,
        "max_depth_m": max_depth_m,
        "width_px": int(size[0]),
        "height_px": int(size[1]),
    }
    (folder / "origin.json").write_text(json.dumps(origin, indent=2) + "\n")
    return origin


def _float_or_none(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def _rms_or_none(value: Any) -> float | None:
    """One figure for the pose residual, whether the estimator gives a scalar or one residual per fix."""
    if value is None:
        return None
    values = np.asarray(value, dtype=float).ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    return round(float(np.sqrt(np.mean(values**2))), 4)


def _depth_stats(depth_m: np.ndarray, max_depth_m: float) -> dict[str, float | None]:
    """Median and 95th percentile of the estimated (non-far) depth, and the far fraction, over up to 50 frames."""
    n = depth_m.shape[0]
    sample = np.asarray(depth_m[:: max(1, n // 50)])
    near = sample[sample < max_depth_m]
    far_fraction = 1.0 - near.size / max(sample.size, 1)
    if near.size == 0:
        return {"depth_median_m": None, "depth_p95_m": None, "depth_far_fraction": round(far_fraction, 4)}
    median, p95 = np.percentile(near, [50, 95])
    return {
        "depth_median_m": round(float(median), 3),
        "depth_p95_m": round(float(p95), 3),
        "depth_far_fraction": round(far_fraction, 4),
    }


def write_depth_preview(
    path: Path,
    frames: np.ndarray,
    depth_m: np.ndarray,
    indices: np.ndarray,
    trace_index: np.ndarray,
    max_depth_m: float,
) -> None:
    """A PNG of the chosen frames (top row) above their depth on a log colour scale (bottom row), for people."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    count = len(indices)
    h, w = frames.shape[1:3]
    panel_w = 3.2
    fig, axes = plt.subplots(
        2, count, figsize=(panel_w * count + 1.0, 2 * panel_w * h / w + 1.4), squeeze=False, layout="constrained"
    )
    norm = LogNorm(vmin=1.0, vmax=max_depth_m)
    image = None
    for col, i in enumerate(indices):
        axes[0, col].imshow(frames[i])
        axes[0, col].set_title(f"frame {int(trace_index[i])}", fontsize=9)
        depth = np.clip(np.asarray(depth_m[i], dtype=np.float32), 1.0, max_depth_m)
        image = axes[1, col].imshow(depth, cmap="turbo_r", norm=norm, interpolation="nearest")
        for row in (0, 1):
            axes[row, col].set_axis_off()
    bar = fig.colorbar(image, ax=axes[1, :].tolist(), location="bottom", shrink=0.5, aspect=40, pad=0.02)
    ticks = [t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500) if t <= max_depth_m]
    bar.set_ticks(ticks, labels=[f"{t:g}" for t in ticks])
    bar.set_label("depth (m)")
    fig.suptitle("preprocess: frames and estimated depth", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
