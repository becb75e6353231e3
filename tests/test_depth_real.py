"""Multi-view stereo on real frames: the KITTI odometry snippet with its ground-truth camera poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from cli_helpers import REAL_DATA

from drivesim.sim.geometry import camera_mount, invert
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth

REAL = REAL_DATA
KITTI = REAL / "kitti_odometry_straight"
CAMERA_HEIGHT_M = 1.65  # KITTI set-up: camera 0 about 1.65 m above the road, looking level


def _kitti(first: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not (KITTI / "poses.txt").is_file():
        pytest.skip(f"real data not found at {KITTI} (shared data sits beside the checkout)")
    tokens = (KITTI / "calib.txt").read_text().splitlines()[0].split()
    K = np.array([t for t in tokens if not t.endswith(":")], float).reshape(3, 4)[:, :3]  # P0, with or without "P0:"
    poses = np.loadtxt(KITTI / "poses.txt").reshape(-1, 3, 4)[first : first + count]
    T_world_camera = np.tile(np.eye(4), (count, 1, 1))
    T_world_camera[:, :3, :] = poses  # KITTI's camera frame is the optical frame (x right, y down, z forward)
    grey = [
        cv2.imread(str(KITTI / "image_l" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(first, first + count)
    ]
    frames = np.stack([np.repeat(g[..., None], 3, axis=-1) for g in grey])
    return frames, K, T_world_camera


def test_mvs_on_kitti_matches_with_true_poses_and_agrees_with_the_road_plane() -> None:
    frames, K, T_world_camera = _kitti(10, 8)
    T_vehicle_camera = camera_mount(0.0, 0.0, CAMERA_HEIGHT_M)
    results = {}
    for name, poses in (("true", T_world_camera), ("inverted", invert(T_world_camera))):
        plane = np.zeros(frames.shape[:3], np.float32)
        mvs = np.zeros(frames.shape[:3], np.float32)
        estimate_depth(frames, K, poses, T_vehicle_camera, CAMERA_HEIGHT_M, DepthConfig(method="plane"), plane)
        summary = estimate_depth(frames, K, poses, T_vehicle_camera, CAMERA_HEIGHT_M, DepthConfig(method="mvs"), mvs)
        road = (slice(3, 5), slice(300, 370), slice(480, 720))  # the lane just ahead, frames with all neighbours
        agree = np.mean(np.abs(mvs[road] - plane[road]) < 0.1 * plane[road])
        results[name] = (summary["stereo_fraction"], summary["plane_fraction"], agree)
    stereo, plane_matched, road_agrees = results["true"]
    assert stereo > 0.25  # real texture triangulates with the recorded motion ...
    assert results["inverted"][0] < 0.5 * stereo  # ... and does not with the wrong motion
    assert plane_matched > 0.1  # the ground plane from the camera height photo-matches across frames
    assert road_agrees > 0.9
