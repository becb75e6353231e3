"""The fused coloured point cloud of the drive (open3d), for people to look at: written to its PLY in parts, so
memory stays flat in the drive's length."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from drivesim.pipeline.npy_files import release_pages
from drivesim.stages.world.config import PointCloudConfig

# Per-frame clouds are merged into the whole every this many points.
_MERGE_POINTS = 500_000
# The merged cloud is written out and started afresh beyond this many points, so memory stays flat in the drive's
# length (a drive moves on: voxels of earlier stretches are not revisited, except where the path passes again, whose
# points are then kept twice near the flush boundaries: about 2 % more points on a 5-minute synthetic drive). The
# peak memory of build-world grows with both sizes (measured: 0.86 GB at 500k points each, 2.1 GB at 1M and 4M).
FLUSH_POINTS = 500_000
# Frames between releases of the memory-mapped inputs' pages (`release_pages`).
_RELEASE_FRAMES = 64
# A PLY vertex: float32 x, y, z (m; 2 mm steps 20 km from the origin, finer than any voxel) and uint8 r, g, b.
PLY_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def fuse_pointcloud(
    frames: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    far_depth_m: float,
    cfg: PointCloudConfig,
    path: Path,
    flush_points: int = FLUSH_POINTS,
) -> int:
    """Back-project every `cfg.frame_step`-th frame into the world, voxel-merge the points and write them as a binary
    PLY at `path`; returns the number of points written.

    Pixels at or beyond `far_depth_m` (no estimate) or `cfg.max_depth_m` are left out. At most about
    `flush_points` merged points are held in memory at a time.
    """
    import open3d as o3d

    n, h, w = depth_m.shape
    v, u = np.mgrid[0 : h : cfg.pixel_step, 0 : w : cfg.pixel_step]
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(np.float64)
    rays = pixels @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    limit = min(cfg.max_depth_m, far_depth_m)
    merged = o3d.geometry.PointCloud()
    pending = o3d.geometry.PointCloud()
    with PlyWriter(path) as ply:
        for i in range(0, n, cfg.frame_step):
            depth = np.asarray(depth_m[i, :: cfg.pixel_step, :: cfg.pixel_step], dtype=np.float64).reshape(-1)
            keep = np.isfinite(depth) & (depth > 0.0) & (depth < limit)
            if i % _RELEASE_FRAMES < cfg.frame_step:
                release_pages(depth_m)
                release_pages(frames)
            if not np.any(keep):
                continue
            points_camera = rays[keep] * depth[keep, None]
            T = np.asarray(T_world_camera[i], dtype=np.float64)
            points_world = points_camera @ T[:3, :3].T + T[:3, 3]
            colours = np.asarray(frames[i, :: cfg.pixel_step, :: cfg.pixel_step], dtype=np.float64)
            cloud = o3d.geometry.PointCloud()
            cloud.points = o3d.utility.Vector3dVector(points_world)
            cloud.colors = o3d.utility.Vector3dVector(colours.reshape(-1, 3)[keep] / 255.0)
            pending += cloud.voxel_down_sample(cfg.voxel_size_m)
            # Merging into the whole cloud only every ~1M points keeps memory bounded without re-voxelising the
            # (growing) merged cloud after every frame, which made long drives quadratic.
            if len(pending.points) > _MERGE_POINTS:
                merged = (merged + pending).voxel_down_sample(cfg.voxel_size_m)
                pending = o3d.geometry.PointCloud()
                if len(merged.points) > flush_points:
                    ply.write(np.asarray(merged.points), np.asarray(merged.colors))
                    merged = o3d.geometry.PointCloud()
        if len(pending.points):
            merged = (merged + pending).voxel_down_sample(cfg.voxel_size_m)
        ply.write(np.asarray(merged.points), np.asarray(merged.colors))
    return ply.count


class PlyWriter:
    """A binary little-endian PLY of coloured points (`PLY_VERTEX`), written in parts: the vertices go to a
    temporary file first, since the header must state their count.

    :param path: the .ply file to write (when the `with` block ends without an error).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.count = 0
        self._body = self.path.with_name(self.path.name + ".vertices")
        self._file = None

    def __enter__(self) -> PlyWriter:
        self._file = open(self._body, "wb")  # noqa: SIM115 (closed in __exit__)
        return self

    def write(self, points_m: np.ndarray, colours_rgb01: np.ndarray) -> None:
        """Append (M, 3) points (m) and their (M, 3) colours in [0, 1]."""
        points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        rows = np.empty(len(points), PLY_VERTEX)
        for axis, name in enumerate(("x", "y", "z")):
            rows[name] = points[:, axis]
        colours = np.clip(np.rint(np.asarray(colours_rgb01, dtype=np.float64).reshape(-1, 3) * 255.0), 0, 255)
        for channel, name in enumerate(("red", "green", "blue")):
            rows[name] = colours[:, channel]
        self._file.write(rows.tobytes())
        self.count += len(rows)

    def __exit__(self, kind, value, traceback) -> None:
        self._file.close()
        try:
            if kind is None:
                self._assemble()
        finally:
            self._body.unlink(missing_ok=True)

    def _assemble(self) -> None:
        properties = "".join(
            f"property {'float' if PLY_VERTEX[name].kind == 'f' else 'uchar'} {name}\n" for name in PLY_VERTEX.names
        )
        header = f"ply\nformat binary_little_endian 1.0\nelement vertex {self.count}\n{properties}end_header\n"
        with open(self.path, "wb") as out, open(self._body, "rb") as body:
            out.write(header.encode("ascii"))
            shutil.copyfileobj(body, out, 1 << 22)
