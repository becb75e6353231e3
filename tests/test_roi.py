"""The policy's region of the image: in degrees it is the same slice of the scene on different cameras."""

from __future__ import annotations

import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pydantic
import pytest
from sim_worlds import write_test_world

from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.roi import angular_roi, roi_for, straight_ahead_px


def camera(width_px: int, height_px: int, focal_px: float, cx: float, cy: float, pitch_down_rad: float):
    """A world-like camera: optical z forward and pitched down, x right, y down (vehicle x forward, y left, z up)."""
    K = np.array([[focal_px, 0, cx], [0, focal_px, cy], [0, 0, 1.0]])
    s, c = math.sin(pitch_down_rad), math.cos(pitch_down_rad)
    R = np.array([[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]])  # columns: camera x, y, z in the vehicle frame
    T = np.eye(4)
    T[:3, :3] = R
    return SimpleNamespace(K=K, T_vehicle_camera=T, width_px=width_px, height_px=height_px, root="cam")


TOWN = camera(320, 200, 190.7, 159.7, 99.7, 0.052)  # the synthetic towns' camera: 3 degrees down
KITTI = camera(320, 96, 185.9, 156.9, 43.9, -0.008)  # a KITTI drive's, cropped at 320 x 96, level


def angles_deg(world, roi) -> tuple[float, float, float]:
    """Left and right edge angles from straight ahead, and the horizon's height in the region (fraction)."""
    column, row = straight_ahead_px(world.K, world.T_vehicle_camera)
    x0, y0, w, h = roi
    fx = world.K[0, 0]
    left = math.degrees(math.atan((x0 - column) / fx))
    right = math.degrees(math.atan((x0 + w - column) / fx))
    return left, right, (row - y0) / h


def test_the_horizon_is_where_the_pitch_puts_it():
    assert straight_ahead_px(TOWN.K, TOWN.T_vehicle_camera)[1] == pytest.approx(99.7 - 190.7 * math.tan(0.052), 0.1)
    assert straight_ahead_px(KITTI.K, KITTI.T_vehicle_camera)[1] > 43.9  # looking a little up: horizon lower


def test_degrees_give_the_same_slice_on_a_town_and_a_kitti_camera():
    config = EnvConfig(roi_fov_deg=60)
    town, kitti = angles_deg(TOWN, roi_for(TOWN, config)), angles_deg(KITTI, roi_for(KITTI, config))
    assert town[0] == pytest.approx(-30, abs=0.5) and town[1] == pytest.approx(30, abs=0.5)
    assert kitti[0] == pytest.approx(-30, abs=0.5) and kitti[1] == pytest.approx(30, abs=0.5)
    assert town[2] == pytest.approx(0.45, abs=0.02) and kitti[2] == pytest.approx(0.45, abs=0.02)
    # the pixel defaults do not: the whole town image width (80 degrees) against KITTI's central 240 px (66)
    town_px, kitti_px = angles_deg(TOWN, roi_for(TOWN, EnvConfig())), angles_deg(KITTI, roi_for(KITTI, EnvConfig()))
    assert town_px[1] - town_px[0] > kitti_px[1] - kitti_px[0] + 10
    assert abs(town_px[2] - kitti_px[2]) > 0.25


def test_a_view_too_wide_for_the_image_names_the_widest_that_fits():
    with pytest.raises(ValueError, match=r"320 x 96 image has no room for a 75 degree view") as error:
        angular_roi(KITTI, EnvConfig(roi_fov_deg=75))
    fits_deg = float(str(error.value).split("at most ")[1].split(" degrees")[0])
    assert 60 < fits_deg < 75
    x0, y0, w, h = angular_roi(KITTI, EnvConfig(roi_fov_deg=fits_deg))
    assert x0 >= 0 and y0 >= 0 and x0 + w <= 320 and y0 + h <= 96


def test_pixels_and_degrees_together_are_refused():
    with pytest.raises(pydantic.ValidationError, match="roi_px and roi_fov_deg both given"):
        EnvConfig(roi_px=(0, 0, 100, 40), roi_fov_deg=60)


def test_eval_refuses_a_camera_too_narrow_for_the_view_in_one_line(tmp_path):
    world = write_test_world(tmp_path / "world")  # 80 x 50 at 90 degrees: room for about 80 degrees at 45 %
    result = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(tmp_path / "ws"), "eval", "--task", "lane",
         "--policy", "expert", "--world", str(world), "--episodes", "2", "--set", "env.roi_fov_deg=120"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert "no room for a 120 degree view" in result.stderr and "degrees fit" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "ws" / "eval").exists()
