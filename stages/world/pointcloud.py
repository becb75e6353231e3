"""The fused coloured point cloud of the drive (open3d), for people to look at."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivesim.stages.world.config import PointCloudConfig

_MERGE_POINTS = 1_000_000


def fuse_pointcloud(
    frames: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    far_depth_m: float,
    cfg: PointCloudConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every `cfg.frame_step`-th frame into the world; returns voxel-merged (points_m, colours_rgb01).

    Pixels at or beyond `far_depth_m` (no estimate) or `cfg.max_depth_m` are left out.
    """
    import open3d as o3d

    n, h, w = depth_m.shape
    v, u = np.mgrid[0 : h : cfg.pixel_step, 0 : w : cfg.pixel_step]
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(np.float64)
    rays = pixels @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    limit = min(cfg.max_depth_m, far_depth_m)
    merged = o3d.geometry.PointCloud()
    pending = o3d.geometry.PointCloud()
    for i in range(0, n, cfg.frame_step):
        depth = np.asarray(depth_m[i, :: cfg.pixel_step, :: cfg.pixel_step], dtype=np.float64).reshape(-1)
        keep = np.isfinite(depth) & (depth > 0.0) & (depth < limit)
        if not np.any(keep):
            continue
        points_camera = rays[keep] * depth[keep, None]
        T = np.asarray(T_world_camera[i], dtype=np.float64)
        points_world = points_camera @ T[:3, :3].T + T[:3, 3]
        colours = np.asarray(frames[i, :: cfg.pixel_step, :: cfg.pixel_step], dtype=np.float64).reshape(-1, 3)[keep]
        cloud = o3d.geometry.PointCloud()
        cloud.points = o3d.utility.Vector3dVector(points_world)
        cloud.colors = o3d.utility.Vector3dVector(colours / 255.0)
        pending += cloud.voxel_down_sample(cfg.voxel_size_m)
        # Merging into the whole cloud only every ~1M points keeps memory bounded without re-voxelising the
        # (growing) merged cloud after every frame, which made long drives quadratic.
        if len(pending.points) > _MERGE_POINTS:
            merged = (merged + pending).voxel_down_sample(cfg.voxel_size_m)
            pending = o3d.geometry.PointCloud()
    if len(pending.points):
        merged = (merged + pending).voxel_down_sample(cfg.voxel_size_m)
    return np.asarray(merged.points), np.asarray(merged.colors)


def write_ply(path: Path, points_m: np.ndarray, colours_rgb01: np.ndarray) -> None:
    """Write a coloured point cloud as binary PLY."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points_m, dtype=np.float64).reshape(-1, 3))
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(colours_rgb01, dtype=np.float64).reshape(-1, 3))
    if not o3d.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise OSError(f"{path}: open3d could not write the point cloud")
