"""Depth from a recorded point cloud: points projected into each frame, z-buffered, and densified.

Each frame's points (vehicle frame, at the frame's time) are moved into the camera optical frame, projected with K;
where several land on one pixel the nearest wins. Empty pixels take the depth of the nearest projected point
(Euclidean distance transform) when one lies within `fill_radius_px`; the rest get the ground-plane depth or
max_depth_m (config `lidar.fallback`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from drivesim.pipeline.errors import InputError
from drivesim.sim.geometry import invert
from drivesim.stages.preprocess.depth_plane import plane_depth

if TYPE_CHECKING:
    from drivesim.stages.preprocess.config import DepthConfig


def project_points(
    points_vehicle: np.ndarray, K: np.ndarray, T_vehicle_camera: np.ndarray, width_px: int, height_px: int
) -> np.ndarray:
    """Sparse depth (m) of points (M, 3) in the vehicle frame seen by the camera: (H, W) float32, inf where none."""
    pts = np.asarray(points_vehicle, dtype=np.float64).reshape(-1, 3)
    T = invert(np.asarray(T_vehicle_camera, dtype=np.float64))
    cam = pts @ T[:3, :3].T + T[:3, 3]
    cam = cam[cam[:, 2] > 0.1]
    uv = cam @ np.asarray(K, dtype=np.float64).T
    u = np.floor(uv[:, 0] / uv[:, 2] + 0.5).astype(np.int64)
    v = np.floor(uv[:, 1] / uv[:, 2] + 0.5).astype(np.int64)
    keep = (u >= 0) & (u < width_px) & (v >= 0) & (v < height_px)
    depth = np.full((height_px, width_px), np.inf, dtype=np.float32)
    np.minimum.at(depth, (v[keep], u[keep]), cam[keep, 2].astype(np.float32))
    return depth


def densify(sparse_depth_m: np.ndarray, fill_radius_px: int) -> np.ndarray:
    """Fill empty (inf) pixels from the nearest measured pixel within `fill_radius_px`; the rest stay inf."""
    empty = ~np.isfinite(sparse_depth_m)
    if empty.all() or not empty.any() or fill_radius_px == 0:
        return sparse_depth_m.copy()
    distance_px, (iy, ix) = ndimage.distance_transform_edt(empty, return_indices=True)
    filled = sparse_depth_m[iy, ix]
    return np.where(distance_px <= fill_radius_px, filled, np.inf).astype(np.float32)


def lidar_depth(
    frames_shape: tuple[int, ...],
    K: np.ndarray,
    T_vehicle_camera: np.ndarray,
    camera_height_m: float | None,
    points_vehicle: Sequence[np.ndarray] | None,
    cfg: DepthConfig,
    out: np.ndarray,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Fill `out` with densified projected point-cloud depth; returns the fraction of pixels measured or filled."""
    n, H, W = frames_shape[:3]
    if points_vehicle is None:
        raise InputError("depth.method=lidar but the trace has no point cloud (no PointCloud2 topic); use plane or mvs")
    if len(points_vehicle) != n:
        raise InputError(f"depth.method=lidar needs one point cloud per frame: {len(points_vehicle)} for {n} frames")
    fallback = (
        plane_depth(K, W, H, T_vehicle_camera, camera_height_m, cfg.max_depth_m)
        if cfg.lidar.fallback == "plane"
        else np.full((H, W), cfg.max_depth_m, np.float32)
    )
    covered = 0
    for i in range(n):
        dense = densify(project_points(points_vehicle[i], K, T_vehicle_camera, W, H), cfg.lidar.fill_radius_px)
        has = np.isfinite(dense)
        covered += int(has.sum())
        out[i] = np.where(has, np.minimum(dense, cfg.max_depth_m), fallback)
        if progress is not None:
            progress(1)
    return {"lidar_coverage_fraction": round(covered / max(1, n * H * W), 4)}
