"""Ground-plane depth: every pixel's ray met with the flat ground below the vehicle (VISTA's method, our baseline).

The ground is the plane z = 0 of the vehicle frame (the trace's vehicle origin is on the ground). A pixel's ray
leaves the camera centre (height from the calibration) along K^-1 [u, v, 1] rotated into the vehicle frame by
T_vehicle_camera, so the camera's pitch and roll are taken into account. Rays that never reach the ground within
`far_depth_m` (above the horizon, or nearly parallel to the road) get `far_depth_m`: the scene there is treated as
far away, which makes it move only with the camera's rotation when a view is synthesized.
"""

from __future__ import annotations

import numpy as np


def pixel_rays(K: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Ray direction of every pixel centre in the camera optical frame, scaled to unit z; shape (H, W, 3)."""
    u, v = np.meshgrid(np.arange(width_px, dtype=np.float64), np.arange(height_px, dtype=np.float64))
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    return pixels @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T


def plane_depth(
    K: np.ndarray,
    width_px: int,
    height_px: int,
    T_vehicle_camera: np.ndarray,
    camera_height_m: float | None,
    far_depth_m: float,
) -> np.ndarray:
    """Optical-axis depth (m) of the ground plane at every pixel, `far_depth_m` where the ray misses it; (H, W) float32.

    `camera_height_m` overrides the height in T_vehicle_camera when given (the calibration's measured height).
    """
    T = np.asarray(T_vehicle_camera, dtype=np.float64)
    height_m = float(T[2, 3]) if camera_height_m is None else float(camera_height_m)
    rays_vehicle = pixel_rays(K, width_px, height_px) @ T[:3, :3].T
    down = -rays_vehicle[..., 2]  # metres dropped per metre of optical depth
    with np.errstate(divide="ignore", invalid="ignore"):
        depth_m = np.where(down > 0.0, height_m / down, np.inf)
    return np.minimum(depth_m, far_depth_m).astype(np.float32)
