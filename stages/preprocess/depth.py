"""Per-frame metric depth for `drivesim preprocess`: the table of methods (`DEPTH_METHODS`) and `estimate_depth`.

The settings (DepthConfig) are in `stages/preprocess/config.py`.

Methods (DESIGN §3):
    plane  ground plane from camera height and pitch (VISTA's only mode; the baseline), see depth_plane.py
    mvs    plane-sweep multi-view stereo over neighbouring frames with known poses, fused with the plane prior,
           see depth_mvs.py
    stereo semi-global matching on a rectified second camera (OpenCV SGBM), see depth_stereo.py
    lidar  a recorded point cloud projected into each frame and densified, see depth_lidar.py
    auto   the best the recording supports: lidar > stereo > mvs (`choose_method`)

Output convention for every method: optical-axis depth (z in the camera optical frame) in metres, float32, one
(H, W) map per frame at the trace's working resolution; pixels with no estimate (sky, above the horizon) hold
`max_depth_m`, never inf or NaN, so a view synthesis treats them as far scenery.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.stages.preprocess.config import DepthConfig


def _check_inputs(frames: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, out: np.ndarray) -> None:
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise InputError(f"frames must be uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}")
    n, h, w = frames.shape[:3]
    if np.shape(K) != (3, 3):
        raise InputError(f"K must be 3x3, got shape {np.shape(K)}")
    if np.shape(T_world_camera) != (n, 4, 4):
        raise InputError(f"T_world_camera must be ({n}, 4, 4) to match the frames, got {np.shape(T_world_camera)}")
    if out.shape != (n, h, w) or out.dtype != np.float32:
        raise InputError(f"out must be float32 ({n}, {h}, {w}), got {out.dtype} {out.shape}")


@dataclass(frozen=True)
class DepthInputs:
    """What a depth method may read (each method uses what it needs; see `estimate_depth` for the meaning)."""

    frames: np.ndarray
    K: np.ndarray
    T_world_camera: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float | None
    points_vehicle: Sequence[np.ndarray] | None
    right_frames: np.ndarray | None = None
    baseline_m: float | None = None


class DepthMethod(Protocol):
    """One depth method: fills `out` (N, H, W) frame by frame, calls `progress(k)` per k frames, returns figures."""

    def __call__(
        self, inputs: DepthInputs, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None
    ) -> dict[str, Any]: ...


def _plane(inputs: DepthInputs, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None) -> dict:
    from drivesim.stages.preprocess.depth_plane import plane_depth

    frames = inputs.frames
    depth_m = plane_depth(
        inputs.K, frames.shape[2], frames.shape[1], inputs.T_vehicle_camera, inputs.camera_height_m, cfg.max_depth_m
    )
    for i in range(frames.shape[0]):
        out[i] = depth_m
        if progress is not None:
            progress(1)
    return {}


def _mvs(inputs: DepthInputs, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None) -> dict:
    from drivesim.stages.preprocess.depth_mvs import mvs_depth  # torch

    return mvs_depth(
        inputs.frames, inputs.K, inputs.T_world_camera, inputs.T_vehicle_camera, inputs.camera_height_m, cfg, out,
        progress,
    )  # fmt: skip


def _lidar(inputs: DepthInputs, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None) -> dict:
    from drivesim.stages.preprocess.depth_lidar import lidar_depth

    return lidar_depth(
        inputs.frames.shape, inputs.K, inputs.T_vehicle_camera, inputs.camera_height_m, inputs.points_vehicle, cfg,
        out, progress,
    )  # fmt: skip


def _stereo(inputs: DepthInputs, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None) -> dict:
    from drivesim.stages.preprocess.depth_plane import plane_depth
    from drivesim.stages.preprocess.depth_stereo import stereo_depth

    if inputs.right_frames is None or inputs.baseline_m is None:
        raise InputError("depth.method=stereo but the recording has no second (right) camera; use auto, mvs or plane")
    frames = inputs.frames
    plane_m = plane_depth(
        inputs.K, frames.shape[2], frames.shape[1], inputs.T_vehicle_camera, inputs.camera_height_m, cfg.max_depth_m
    )
    return stereo_depth(
        frames, inputs.right_frames, inputs.K, inputs.baseline_m, plane_m, cfg.max_depth_m, cfg.stereo, out, progress
    )


def choose_method(requested: str, has_lidar: bool, has_stereo: bool) -> tuple[str, str]:
    """The depth method to run and why: `requested` itself, or for auto the best the recording supports
    (lidar > stereo > mvs, the camera-only method)."""
    if requested != "auto":
        return requested, "asked for"
    if has_lidar:
        return "lidar", "auto: the recording has a point cloud"
    if has_stereo:
        return "stereo", "auto: the recording has a rectified second camera"
    return "mvs", "auto: camera only (no point cloud, no second camera)"


# depth.method -> the function that estimates it (the one place that dispatches on the method's name).
DEPTH_METHODS: dict[str, DepthMethod] = {"plane": _plane, "mvs": _mvs, "stereo": _stereo, "lidar": _lidar}


def estimate_depth(
    frames: np.ndarray,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    T_vehicle_camera: np.ndarray,
    camera_height_m: float | None,
    cfg: DepthConfig,
    out: np.ndarray,
    progress: Callable[[int], None] | None = None,
    points_vehicle: Sequence[np.ndarray] | None = None,
    right_frames: np.ndarray | None = None,
    baseline_m: float | None = None,
    run_method: DepthMethod | None = None,
) -> dict[str, Any]:
    """Fill `out` (N, H, W) with per-frame depth (m) of `frames` (N, H, W, 3) by `cfg.method`; returns summary figures.

    :param frames: RGB frames, uint8; may be a read-only memmap (read a few frames at a time).
    :param K: pinhole intrinsics of the frames (pixels).
    :param T_world_camera: per-frame camera poses (optical frame -> world), used by `mvs`.
    :param T_vehicle_camera: camera optical frame -> vehicle frame (carries the camera's height and pitch).
    :param camera_height_m: camera height above the ground; None takes it from T_vehicle_camera.
    :param out: writable float32 array or memmap; written one frame at a time.
    :param progress: called with the number of frames just finished.
    :param points_vehicle: for `lidar`, per-frame (M, 3) points in the vehicle frame at the frame's time (m).
    :param right_frames: for `stereo`, the rectified right camera's frames (N, H, W, 3), same K as `frames`.
    :param baseline_m: for `stereo`, how far the right camera sits along the left one's +x axis (m).
    :param run_method: runs the method instead of `DEPTH_METHODS`' function (`depth_ray`: the same depth on Ray).
    `cfg.method` auto runs `choose_method` on what is given (points, right frames).
    """
    _check_inputs(frames, K, T_world_camera, out)
    if cfg.method == "auto":
        method, _ = choose_method(
            "auto", points_vehicle is not None, right_frames is not None and baseline_m is not None
        )
        cfg = cfg.model_copy(update={"method": method})
    if right_frames is not None and np.shape(right_frames) != frames.shape:
        raise InputError(f"right_frames must match the frames' shape {frames.shape}, got {np.shape(right_frames)}")
    if cfg.method == "mvs" and cfg.mvs.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise ConfigError("depth.mvs.device=cuda but torch sees no CUDA device; use cpu or auto")
    start = time.perf_counter()
    inputs = DepthInputs(
        frames, K, T_world_camera, T_vehicle_camera, camera_height_m, points_vehicle, right_frames, baseline_m
    )
    extra = (run_method or DEPTH_METHODS[cfg.method])(inputs, cfg, out, progress)
    seconds = time.perf_counter() - start
    n = frames.shape[0]
    far_fraction = float(np.mean([np.mean(out[i] >= cfg.max_depth_m) for i in range(0, n, max(1, n // 20))]))
    return {
        "method": cfg.method,
        "frames": int(n),
        "seconds": round(seconds, 3),
        "seconds_per_frame": round(seconds / max(n, 1), 4),
        "far_fraction": round(far_fraction, 4),
        **extra,
    }
