"""build-world's passes over a drive keep memory flat in its length: the resize into the world's frames and depth
(memmapped inputs and outputs, released chunk by chunk) and the point cloud (written to its PLY in parts)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from drivesim.pipeline.npy_files import open_reserved_memmap
from drivesim.stages.world import build, pointcloud
from drivesim.stages.world.build import resize_depth, resize_frames, resize_into
from drivesim.stages.world.config import PointCloudConfig
from drivesim.stages.world.pointcloud import fuse_pointcloud

N_FRAMES, H, W = 400, 200, 320  # a 40 s drive at 10 Hz: 77 MB of frames and 102 MB of depth
SIM_W, SIM_H = 160, 100


def _rss_mb() -> float:
    """This process's resident memory now (MB), file-backed pages of its memmaps included."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


@pytest.fixture(scope="module")
def long_drive(tmp_path_factory) -> tuple[np.ndarray, np.ndarray]:
    """Memory-mapped (N, H, W, 3) uint8 frames and (N, H, W) float32 depth written to disk row by row."""
    folder = tmp_path_factory.mktemp("drive")
    rng = np.random.default_rng(0)
    frames = np.lib.format.open_memmap(folder / "frames.npy", "w+", np.uint8, (N_FRAMES, H, W, 3))
    depth = np.lib.format.open_memmap(folder / "depth.npy", "w+", np.float32, (N_FRAMES, H, W))
    row_depth = np.linspace(1.0, 80.0, H, dtype=np.float32)[:, None]
    for i in range(N_FRAMES):
        frames[i] = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        depth[i] = row_depth + 0.01 * i
    frames.flush()
    depth.flush()
    del frames, depth
    return np.load(folder / "frames.npy", mmap_mode="r"), np.load(folder / "depth.npy", mmap_mode="r")


def _resize_peak_growth_mb(drive, out_dir: Path) -> tuple[float, np.ndarray, np.ndarray]:
    frames, depth = drive
    frames_out = open_reserved_memmap(out_dir / "frames.npy", np.uint8, (N_FRAMES, SIM_H, SIM_W, 3))
    depth_out = open_reserved_memmap(out_dir / "depth_m.npy", np.float16, (N_FRAMES, SIM_H, SIM_W))
    start = _rss_mb()
    peak = [start]
    resize_into(frames, np.arange(N_FRAMES), depth, frames_out, depth_out, "min", lambda _: peak.append(_rss_mb()))
    return max(peak) - start, frames_out, depth_out


def test_resize_into_the_world_keeps_memory_flat_and_writes_every_frame(long_drive, tmp_path) -> None:
    growth_mb, frames_out, depth_out = _resize_peak_growth_mb(long_drive, tmp_path)
    # inputs and outputs together are ~200 MB; a chunk of 16 frames is ~10 MB
    assert growth_mb < 40.0, f"resident memory grew {growth_mb:.0f} MB over a {N_FRAMES}-frame pass"
    frames, depth = long_drive
    for i in (0, 137, N_FRAMES - 1):
        assert np.array_equal(frames_out[i], resize_frames(frames[i : i + 1], SIM_W, SIM_H)[0])
        expected = resize_depth(depth[i : i + 1], SIM_W, SIM_H, "min")[0].astype(np.float16)
        assert depth_out.dtype == np.float16 and np.array_equal(depth_out[i], expected)


def test_without_releasing_pages_the_same_pass_grows_with_the_drive(long_drive, tmp_path, monkeypatch) -> None:
    """The control: the measure above sees a whole drive held in memory (memmapped pages kept resident)."""
    monkeypatch.setattr(build, "release_pages", lambda array: None)
    growth_mb, _, _ = _resize_peak_growth_mb(long_drive, tmp_path)
    assert growth_mb > 100.0, f"only {growth_mb:.0f} MB: the measure cannot tell a flat pass from a growing one"


def test_point_cloud_written_in_parts_is_the_whole_cloud(tmp_path, monkeypatch) -> None:
    """With a tiny flush size the cloud goes to its PLY in many parts: every point arrives, readable by open3d."""
    import open3d as o3d

    n, h, w = 40, 60, 80
    frames = np.full((n, h, w, 3), 200, np.uint8)
    depth = np.full((n, h, w), 8.0, np.float32)
    K = np.array([[60.0, 0.0, w / 2], [0.0, 60.0, h / 2], [0.0, 0.0, 1.0]])
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * 5.0  # 5 m apart: the frames' points do not overlap
    cfg = PointCloudConfig(frame_step=1, pixel_step=2, voxel_size_m=0.05)
    whole = fuse_pointcloud(frames, depth, K, T, 100.0, cfg, tmp_path / "whole.ply")
    monkeypatch.setattr(pointcloud, "_MERGE_POINTS", 500)
    split = fuse_pointcloud(frames, depth, K, T, 100.0, cfg, tmp_path / "split.ply", flush_points=1000)
    assert split == whole == n * (h // 2) * (w // 2)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "split.ply"))
    assert len(cloud.points) == split
    assert np.allclose(np.asarray(cloud.points)[:, 2], 8.0, atol=1e-4)
    assert np.allclose(np.asarray(cloud.colors), 200 / 255, atol=1e-6)
    assert not list(tmp_path.glob("*.vertices"))
