"""The synthetic road and the drive along it: curvature bounds, continuity, arc length, kinematics."""

from __future__ import annotations

import numpy as np
import pytest

from drivesim.stages.synth.config import DriveConfig, RoadConfig
from drivesim.stages.synth.drive import Trajectory, arc_length_at
from drivesim.stages.synth.road import build_centreline


@pytest.fixture(scope="module", params=[0, 1, 7, 12345])
def road(request):
    return build_centreline(RoadConfig(length_m=1500.0), np.random.default_rng(request.param))


def test_lane_curvature_is_bounded_by_the_config_and_the_road_does_bend(road):
    lane = road.offset(-1.75)
    assert np.max(np.abs(lane.curvature_1pm)) <= 1.0 / 30.0 + 1e-9
    assert np.max(np.abs(road.offset(1.75).curvature_1pm)) <= 1.0 / 30.0 + 1e-9
    # not a straight line: a 1.5 km road has real bends
    assert np.max(np.abs(lane.curvature_1pm)) > 1.0 / 100.0


def test_heading_and_curvature_are_continuous(road):
    ds = np.diff(road.arc_length_m)
    assert np.max(np.abs(np.diff(road.yaw_rad))) <= np.max(np.abs(road.curvature_1pm)) * ds.max() + 1e-9
    # clothoids: curvature changes linearly, never jumps
    assert np.max(np.abs(np.diff(road.curvature_1pm))) < 0.01 * ds.max()
    # heading from the positions agrees with the stored heading
    chord_yaw = np.arctan2(np.diff(road.y_m), np.diff(road.x_m))
    mid_yaw = 0.5 * (road.yaw_rad[1:] + road.yaw_rad[:-1])
    assert np.max(np.abs(np.angle(np.exp(1j * (chord_yaw - mid_yaw))))) < 1e-4


def test_arc_length_matches_the_polyline_length(road):
    for path in (road, road.offset(-1.75), road.offset(1.75)):
        seg = np.hypot(np.diff(path.x_m), np.diff(path.y_m))
        assert np.allclose(np.diff(path.arc_length_m), seg, rtol=1e-4, atol=1e-6)
        assert path.length_m == pytest.approx(seg.sum(), rel=1e-5)


def test_lane_centre_is_offset_by_half_a_lane(road):
    lane = road.offset(-1.75)
    assert np.allclose(np.hypot(lane.x_m - road.x_m, lane.y_m - road.y_m), 1.75)
    # to the right of the direction of travel: the cross product tangent x offset points down
    tx, ty = np.cos(road.yaw_rad), np.sin(road.yaw_rad)
    cross = tx * (lane.y_m - road.y_m) - ty * (lane.x_m - road.x_m)
    assert np.all(cross < 0)


def test_the_road_does_not_loop_back_onto_itself(road):
    yaw = road.yaw_rad - road.yaw_rad[0]
    assert np.max(np.abs(yaw)) < np.deg2rad(45.0 + 100.0 + 1.0)


def test_trajectory_speed_arc_length_and_yaw_rate_agree():
    path = build_centreline(RoadConfig(length_m=600.0), np.random.default_rng(3)).offset(-1.75)
    cfg = DriveConfig(duration_s=40.0, speed_mps=10.0, speed_variation_mps=2.0, speed_period_s=16.0)
    traj = Trajectory(path, cfg)
    t = np.linspace(0.0, cfg.duration_s, 4001)
    st = traj.state(t)
    assert st["speed_mps"].min() >= 8.0 - 1e-9 and st["speed_mps"].max() <= 12.0 + 1e-9
    # arc length is the integral of speed, acceleration its derivative
    assert np.allclose(np.gradient(st["arc_length_m"], t, edge_order=2), st["speed_mps"], atol=1e-3)
    assert np.allclose(np.gradient(st["speed_mps"], t, edge_order=2), st["accel_mps2"], atol=1e-3)
    assert arc_length_at(cfg, 0.0) == pytest.approx(cfg.start_m)
    # integrating the yaw rate gives the heading change
    heading = st["yaw_rad"][0] + np.concatenate(
        [[0.0], np.cumsum(0.5 * (st["yaw_rate_radps"][1:] + st["yaw_rate_radps"][:-1]) * np.diff(t))]
    )
    assert np.max(np.abs(heading - st["yaw_rad"])) < 2e-3


def test_drive_past_the_end_of_the_road_is_refused():
    path = build_centreline(RoadConfig(length_m=100.0), np.random.default_rng(0)).offset(-1.75)
    traj = Trajectory(path, DriveConfig(duration_s=60.0))
    with pytest.raises(ValueError, match="lane is"):
        traj.state(59.0)
