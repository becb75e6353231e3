"""A tiny trace artifact and a fake pose estimator shared by the preprocess-stage and world tests (no tests here).

The fake estimator drives a known left-hand arc, so every figure downstream (path length, curvature, the ground
depth of a pixel) has an exact expected value.
"""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np

from drivesim.pipeline.workspace import Workspace
from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, pose_2d

WIDTH_PX, HEIGHT_PX = 96, 60
FRAME_COUNT = 12
FRAME_PERIOD_NS = 100_000_000
RADIUS_M = 50.0
SPEED_MPS = 10.0
CAMERA_HEIGHT_M = 1.6
T_VEHICLE_CAMERA = camera_mount(1.5, 0.0, CAMERA_HEIGHT_M, pitch_down_rad=0.08)
K = intrinsics_from_hfov(WIDTH_PX, HEIGHT_PX, np.deg2rad(90.0))


def make_trace(ws: Workspace, frame_count: int = FRAME_COUNT) -> Path:
    """Write a small trace artifact (random-textured frames, stamps, calibration) into `ws`; returns its folder."""
    rng = np.random.default_rng(0)
    with ws.write_artifact("trace", "ingest", {"fake": True}, {}) as build:
        frames = rng.integers(0, 256, size=(frame_count, HEIGHT_PX, WIDTH_PX, 3), dtype=np.uint8)
        frames[:, :, :, 0] = np.arange(frame_count, dtype=np.uint8)[:, None, None] * 10  # frame id in red
        np.save(build.dir / "frames.npy", frames)
        np.save(build.dir / "frame_times_ns.npy", 1_700_000_000_000_000_000 + np.arange(frame_count) * FRAME_PERIOD_NS)
        calibration = {
            "width_px": WIDTH_PX,
            "height_px": HEIGHT_PX,
            "K": K.tolist(),
            "source_width_px": WIDTH_PX,
            "source_height_px": HEIGHT_PX,
            "distortion_model": "none",
            "T_vehicle_camera": T_VEHICLE_CAMERA.tolist(),
            "camera_height_m": CAMERA_HEIGHT_M,
            "extrinsics_source": "config",
            "time_base": "unix",
        }
        (build.dir / "calibration.json").write_text(json.dumps(calibration))
        (build.dir / "sources.json").write_text(json.dumps({"recording": "fake", "format": "mcap", "sensors": {}}))
        build.summary = {"frame_count": frame_count}
    return ws.artifact_dir("trace")


def arc_pose(t_s: float) -> np.ndarray:
    """T_world_vehicle on the arc `t_s` seconds after the first frame."""
    yaw = SPEED_MPS * t_s / RADIUS_M
    return pose_2d(RADIUS_M * np.sin(yaw), RADIUS_M * (1.0 - np.cos(yaw)), yaw)


def add_lidar_wall(trace_dir: Path, scan_offset_s: float, scan_count: int, wall_x_m: float) -> None:
    """Lidar scans of a wall (the world plane x = wall_x_m) taken `scan_offset_s` after each of the first frames."""
    t0_ns = int(np.load(trace_dir / "frame_times_ns.npy")[0])
    wy, wz = np.meshgrid(np.arange(-10.0, 15.0, 0.05), np.arange(0.0, 4.0, 0.05))
    wall = np.stack([np.full(wy.size, wall_x_m), wy.ravel(), wz.ravel(), np.ones(wy.size)], axis=1)
    scans, times = [], []
    for i in range(scan_count):
        t_s = i * FRAME_PERIOD_NS * 1e-9 + scan_offset_s
        scans.append((np.linalg.inv(arc_pose(t_s)) @ wall.T).T)
        times.append(t0_ns + round(t_s * 1e9))
    points = np.concatenate(scans).astype(np.float32)
    points[:, 3] = np.nan  # no intensity
    np.save(trace_dir / "lidar_points.npy", points)
    counts = np.array([len(scan) for scan in scans], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    np.savez(trace_dir / "lidar_scans.npz", t_ns=np.array(times, dtype=np.int64), start=starts, count=counts)


def arc_poses(frame_times_ns: np.ndarray) -> types.SimpleNamespace:
    """FusedPoses of a car driving a left-hand arc of RADIUS_M at SPEED_MPS, starting at the origin heading east."""
    t_s = (np.asarray(frame_times_ns) - frame_times_ns[0]) * 1e-9
    s = SPEED_MPS * t_s
    yaw = s / RADIUS_M
    x = RADIUS_M * np.sin(yaw)
    y = RADIUS_M * (1.0 - np.cos(yaw))
    n = len(t_s)
    return types.SimpleNamespace(
        t_ns=np.asarray(frame_times_ns),
        x_m=x,
        y_m=y,
        z_m=np.zeros(n),
        yaw_rad=yaw,
        speed_mps=np.full(n, SPEED_MPS),
        curvature_1pm=np.full(n, 1.0 / RADIUS_M),
        arc_length_m=s,
        T_world_vehicle=np.stack([pose_2d(x[i], y[i], yaw[i]) for i in range(n)]),
        source="fake_gps_imu",
        origin_lat_deg=49.0,
        origin_lon_deg=8.4,
        origin_alt_m=116.0,
        residual_m=np.full(n, 0.2),
    )


def install_fake_poses(monkeypatch) -> list[dict]:
    """Replace series loading and pose fusion by the arc above; returns a list recording each call's arguments."""
    from drivesim.stages.preprocess import run as stage

    calls: list[dict] = []

    def fake_estimate(series, frame_times_ns, cfg, frames=None, K=None, T_vehicle_camera=None):
        calls.append(
            {"frame_times_ns": np.array(frame_times_ns), "frames_shape": None if frames is None else frames.shape}
        )
        return arc_poses(frame_times_ns)

    monkeypatch.setattr(stage.series_mod, "load_series", lambda trace_dir: object())
    monkeypatch.setattr(stage.poses_mod, "estimate_poses", fake_estimate)
    return calls
