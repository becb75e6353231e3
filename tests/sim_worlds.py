"""A small hand-made world for simulator and env tests: a road that runs straight and then turns left, a ground plane
and a textured wall of depth at 30 m, at 80 x 50 pixels (no synth or /tmp needed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from drivesim.sim.geometry import intrinsics_from_hfov

WIDTH_PX, HEIGHT_PX = 80, 50
# The env config for this world: a region of interest inside its 80 x 50 image and a small observation.
SMALL_VIEW = {"roi_px": (0, 18, 80, 32), "observation_width_px": 40, "observation_height_px": 16}


def write_test_world(root: Path, length_m: float = 200.0, spacing_m: float = 1.0, curve_from_m: float = 120.0) -> Path:
    """A world folder: straight for `curve_from_m`, then a left curve of radius 80 m; frames every `spacing_m`."""
    root.mkdir(parents=True, exist_ok=True)
    arc = np.arange(0.0, length_m + 1e-9, spacing_m)
    curvature = np.where(arc > curve_from_m, 1.0 / 80.0, 0.0)
    yaw = np.concatenate([[0.0], np.cumsum(curvature[:-1] * spacing_m)])
    x = np.concatenate([[0.0], np.cumsum(np.cos(yaw[:-1]) * spacing_m)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(yaw[:-1]) * spacing_m)])
    n = len(arc)
    K = intrinsics_from_hfov(WIDTH_PX, HEIGHT_PX, np.radians(90.0))
    camera_height = 1.6
    R_vehicle_camera = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T_vehicle_camera = np.eye(4)
    T_vehicle_camera[:3, :3] = R_vehicle_camera
    T_vehicle_camera[:3, 3] = [1.5, 0.0, camera_height]
    T_world_vehicle = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    T_world_vehicle[:, 0, 0], T_world_vehicle[:, 0, 1], T_world_vehicle[:, 1, 0], T_world_vehicle[:, 1, 1] = c, -s, s, c
    T_world_vehicle[:, 0, 3], T_world_vehicle[:, 1, 3] = x, y
    rng = np.random.default_rng(0)
    # Depth: the ground plane below the horizon, a wall at 30 m above it; texture: noise that moves with the frame.
    v = np.arange(HEIGHT_PX, dtype=float)[:, None] + 0.5
    below = v > K[1, 2] + 0.5
    ground = np.where(below, camera_height * K[1, 1] / np.maximum(v - K[1, 2], 1e-3), 30.0)
    depth = np.broadcast_to(np.minimum(ground, 30.0), (HEIGHT_PX, WIDTH_PX)).astype(np.float32)
    frames = np.empty((n, HEIGHT_PX, WIDTH_PX, 3), np.uint8)
    base = rng.integers(60, 200, size=(HEIGHT_PX, WIDTH_PX + n, 3), dtype=np.uint8)
    for i in range(n):
        frames[i] = base[:, i : i + WIDTH_PX]
    np.save(root / "frames.npy", frames)
    np.save(root / "depth_m.npy", np.broadcast_to(depth, (n, HEIGHT_PX, WIDTH_PX)).copy())
    camera = {
        "width_px": WIDTH_PX,
        "height_px": HEIGHT_PX,
        "K": K.tolist(),
        "T_vehicle_camera": T_vehicle_camera.tolist(),
        "camera_height_m": camera_height,
        "source_width_px": WIDTH_PX,
        "source_height_px": HEIGHT_PX,
    }
    (root / "camera.json").write_text(json.dumps(camera))
    np.savez(
        root / "path.npz",
        frame_index=np.arange(n, dtype=np.int64),
        t_ns=(arc / 8.0 * 1e9).astype(np.int64),
        x_m=x, y_m=y, z_m=np.zeros(n), yaw_rad=yaw, speed_mps=np.full(n, 8.0), curvature_1pm=curvature,
        arc_length_m=arc, T_world_vehicle=T_world_vehicle, T_world_camera=T_world_vehicle @ T_vehicle_camera,
    )  # fmt: skip
    info = {
        "format": 1, "frame_count": n, "road_width_m": 7.0, "lane_width_m": 3.5, "path_length_m": float(arc[-1]),
        "curvature_min_1pm": 0.0, "curvature_max_1pm": float(curvature.max()), "pose_source": "test",
        "origin_lat_deg": 0.0, "origin_lon_deg": 0.0, "origin_alt_m": 0.0, "depth_method": "test",
        "far_depth_m": 30.0,
    }  # fmt: skip
    (root / "world.json").write_text(json.dumps(info))
    return root


def straight_path(x_m: np.ndarray, T_world_vehicle: np.ndarray, T_vehicle_camera: np.ndarray, dt_ns: int) -> dict:
    """A world's path arrays for a straight drive along +x at 10 m/s: frame k at `x_m[k]`, `dt_ns` apart."""
    n = len(x_m)
    return {
        "x_m": x_m, "y_m": np.zeros(n), "z_m": np.zeros(n), "yaw_rad": np.zeros(n), "speed_mps": np.full(n, 10.0),
        "curvature_1pm": np.zeros(n), "arc_length_m": x_m.copy(), "t_ns": np.arange(n) * dt_ns,
        "frame_index": np.arange(n), "T_world_vehicle": T_world_vehicle,
        "T_world_camera": T_world_vehicle @ T_vehicle_camera,
    }  # fmt: skip
