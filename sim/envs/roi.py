"""The region of a world's sim image that the policy sees (its region of interest, x0, y0, w, h in pixels).

Three ways, in the env config's order: `roi_px` as given; `roi_fov_deg`, a window of fixed angles placed by the
world's intrinsics and camera mounting, so that worlds from different cameras (a synthetic town at 320 x 200 and
~80 degrees, a KITTI drive at 320 x 96 and ~81 degrees with its horizon mid-image) show the policy the same slice
of the scene; else the largest region with the observation's aspect at the bottom of the image.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drivesim.sim.envs.config import EnvConfig

Roi = tuple[int, int, int, int]


def default_roi(width_px: int, height_px: int, config: EnvConfig) -> Roi:
    """The largest region with the observation's aspect, centred across, at the bottom of the image."""
    aspect = config.observation_width_px / config.observation_height_px
    w, h = width_px, round(width_px / aspect)
    if h > height_px:
        w, h = round(height_px * aspect), height_px
    return ((width_px - w) // 2, height_px - h, w, h)


def straight_ahead_px(K: np.ndarray, T_vehicle_camera: np.ndarray) -> tuple[float, float]:
    """(column, row) where the vehicle's forward direction meets the image: the centre of the horizon."""
    forward_cam = np.asarray(T_vehicle_camera, float)[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    if forward_cam[2] <= 1e-6:
        raise ValueError("the camera does not look forward (the vehicle's x axis is behind its image plane)")
    u, v, _ = np.asarray(K, float) @ (forward_cam / forward_cam[2])
    return float(u), float(v)


def angular_roi(world: Any, config: EnvConfig) -> Roi:
    """The window `roi_fov_deg` wide, with the observation's aspect, centred on the straight-ahead direction and
    with the horizon `roi_horizon_fraction` of its height from the top. Raises ValueError when the image is too
    small for it (saying which field of view would fit)."""
    fx, fy = float(world.K[0, 0]), float(world.K[1, 1])
    column, row = straight_ahead_px(world.K, world.T_vehicle_camera)
    width = 2.0 * fx * math.tan(math.radians(config.roi_fov_deg) / 2.0)
    height = width / (config.observation_width_px / config.observation_height_px) * fy / fx
    x0, y0 = column - width / 2.0, row - config.roi_horizon_fraction * height
    slack = min(x0, y0, world.width_px - (x0 + width), world.height_px - (y0 + height))
    if slack < -0.5:
        scale = min(
            column / (width / 2.0),
            (world.width_px - column) / (width / 2.0),
            row / (config.roi_horizon_fraction * height) if config.roi_horizon_fraction > 0 else math.inf,
            (world.height_px - row) / ((1.0 - config.roi_horizon_fraction) * height),
        )
        fits_deg = 2.0 * math.degrees(math.atan(scale * width / 2.0 / fx))
        raise ValueError(
            f"{getattr(world, 'root', 'the world')}: its {world.width_px} x {world.height_px} image has no room for a "
            f"{config.roi_fov_deg:g} degree view with the horizon at {config.roi_horizon_fraction:.0%} of its height; "
            f"at most {math.floor(fits_deg * 10) / 10:g} degrees fit (set env roi_fov_deg lower)"
        )
    x0 = min(max(x0, 0.0), world.width_px - width)
    y0 = min(max(y0, 0.0), world.height_px - height)
    return (round(x0), round(y0), min(round(width), world.width_px), min(round(height), world.height_px))


def roi_for(world: Any, config: EnvConfig) -> Roi:
    """The region of `world`'s sim image that the policy sees under `config` (module docstring)."""
    if config.roi_px is not None:
        return tuple(int(v) for v in config.roi_px)
    if config.roi_fov_deg is not None:
        return angular_roi(world, config)
    return default_roi(world.width_px, world.height_px, config)
