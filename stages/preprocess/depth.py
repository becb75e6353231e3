"""Per-frame metric depth for `drivesim preprocess`: config and dispatch to one method.

Methods (DESIGN §3):
    plane  ground plane from camera height and pitch (VISTA's only mode; the baseline), see depth_plane.py
    mvs    plane-sweep multi-view stereo over neighbouring frames with known poses, fused with the plane prior,
           see depth_mvs.py
    lidar  a recorded point cloud projected into each frame and densified, see depth_lidar.py

Output convention for every method: optical-axis depth (z in the camera optical frame) in metres, float32, one
(H, W) map per frame at the trace's working resolution; pixels with no estimate (sky, above the horizon) hold
`max_depth_m`, never inf or NaN, so a view synthesis treats them as far scenery.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from drivesim.pipeline.config import StageConfig
from drivesim.pipeline.errors import ConfigError, InputError


class MvsConfig(StageConfig):
    """Plane-sweep stereo settings (method `mvs`)."""

    neighbour_offsets: list[int] = Field(default_factory=lambda: [-3, -1, 1, 3])
    """Frames matched against each frame, as index offsets (0 not allowed); at the ends of the drive an offset past
    the end takes the last frame on that side."""
    num_hypotheses: int = Field(32, ge=4, le=512)
    """Fronto-parallel depth planes swept, spaced evenly in inverse depth between min_depth_m and max_depth_m."""
    min_depth_m: float = Field(2.0, gt=0.0)
    """Nearest depth swept (m)."""
    patch_size_px: int = Field(13, ge=3, le=31)
    """Side of the square window of the ZNCC matching cost, in matching-resolution pixels (odd)."""
    matching_width_px: int = Field(320, ge=32)
    """Width of the images the sweep runs on (matching resolution); frames wider than this are downscaled."""
    best_k: int = Field(2, ge=1)
    """The cost of a hypothesis is the mean of the best k neighbours' costs (robust to occlusion at the borders)."""
    min_zncc: float = Field(0.7, ge=-1.0, le=1.0)
    """Stereo is trusted only where the best aggregated ZNCC score is at least this."""
    min_distinctness: float = Field(0.02, ge=0.0)
    """Stereo is trusted only where the second-best cost minimum (away from the best) is this much worse."""
    min_parallax_px: float = Field(0.5, ge=0.0)
    """Stereo is trusted only where a 25 % depth change moves the pixel at least this far (matching pixels) in the
    widest-baseline neighbour: near the focus of expansion of a forward drive there is no parallax to measure."""
    plane_margin: float = Field(0.03, ge=0.0)
    """The ground plane is kept wherever its ZNCC cost is within this margin of the best swept plane."""
    fill_sigma_px: float = Field(3.0, ge=0.0)
    """Pixels with neither trusted stereo nor an agreeing plane take the inverse depth of trusted pixels around them,
    Gaussian-weighted with this sigma (matching pixels), where those surround them densely enough; 0 disables."""
    sky_max_std: float = Field(0.012, ge=0.0)
    """Sky: textureless pixels (grey window deviation below this, grey in [0, 1]) above the horizon connected to the
    image top; they get max_depth_m."""
    upsample: Literal["joint_bilateral", "bilinear"] = "joint_bilateral"
    """How the matching-resolution depth returns to the working resolution: joint_bilateral follows colour edges."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Torch device of the sweep; auto uses CUDA when available."""

    @model_validator(mode="after")
    def _check(self) -> MvsConfig:
        if not self.neighbour_offsets or 0 in self.neighbour_offsets:
            raise ValueError("neighbour_offsets must be a non-empty list of non-zero frame offsets")
        if self.patch_size_px % 2 == 0:
            raise ValueError("patch_size_px must be odd")
        return self


class LidarConfig(StageConfig):
    """Point-cloud projection settings (method `lidar`)."""

    fill_radius_px: int = Field(4, ge=0, le=64)
    """Holes between projected points are filled from the nearest point up to this many pixels away."""
    fallback: Literal["plane", "far"] = "plane"
    """What pixels with no point nearby get: the ground-plane depth, or max_depth_m."""


class DepthConfig(StageConfig):
    """Per-frame depth estimation."""

    method: Literal["plane", "mvs", "lidar"] = "plane"
    """plane: flat ground from camera height and pitch (fast baseline); mvs: multi-view stereo over neighbouring
    frames fused with the plane; lidar: projected point cloud (needs one in the trace)."""
    max_depth_m: float = Field(80.0, gt=0.0)
    """Farthest depth (m): sky, rays above the horizon and anything without an estimate get this value."""
    mvs: MvsConfig = Field(default_factory=MvsConfig)
    """Multi-view stereo settings."""
    lidar: LidarConfig = Field(default_factory=LidarConfig)
    """Point-cloud settings."""

    @model_validator(mode="after")
    def _check(self) -> DepthConfig:
        if self.mvs.min_depth_m >= self.max_depth_m:
            raise ValueError("mvs.min_depth_m must be below max_depth_m")
        return self


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
    """
    _check_inputs(frames, K, T_world_camera, out)
    if cfg.method == "mvs" and cfg.mvs.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise ConfigError("depth.mvs.device=cuda but torch sees no CUDA device; use cpu or auto")
    start = time.perf_counter()
    if cfg.method == "plane":
        from drivesim.stages.preprocess.depth_plane import plane_depth

        depth_m = plane_depth(K, frames.shape[2], frames.shape[1], T_vehicle_camera, camera_height_m, cfg.max_depth_m)
        for i in range(frames.shape[0]):
            out[i] = depth_m
            if progress is not None:
                progress(1)
        extra: dict[str, Any] = {}
    elif cfg.method == "mvs":
        from drivesim.stages.preprocess.depth_mvs import mvs_depth

        extra = mvs_depth(frames, K, T_world_camera, T_vehicle_camera, camera_height_m, cfg, out, progress)
    else:
        from drivesim.stages.preprocess.depth_lidar import lidar_depth

        extra = lidar_depth(frames.shape, K, T_vehicle_camera, camera_height_m, points_vehicle, cfg, out, progress)
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
