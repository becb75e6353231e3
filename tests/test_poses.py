"""Pose estimation on synthetic drives with known ground truth: GPS+IMU+speed fusion, odometry, given poses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from drivesim.pipeline.errors import InputError
from drivesim.sim.geometry import camera_mount, wrap_angle
from drivesim.stages.preprocess import ekf
from drivesim.stages.preprocess.poses import (
    PoseConfig,
    camera_poses,
    enu_transformer,
    estimate_poses,
    fuse_gps_imu,
    odometry_track,
)
from drivesim.stages.preprocess.series import (
    GivenPoses,
    GpsSeries,
    GroundTruthPoses,
    ImuSeries,
    OdometrySeries,
    SensorSeries,
    SpeedSeries,
    load_series,
)

ORIGIN = (48.0, 11.0, 500.0)


@dataclass
class Truth:
    t_s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    v: np.ndarray
    w: np.ndarray

    def at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.interp(t_s, self.t_s, self.x),
            np.interp(t_s, self.t_s, self.y),
            wrap_angle(np.interp(t_s, self.t_s, np.unwrap(self.yaw))),
        )


def simulate_truth(duration_s: float, speed_fn, yaw_rate_fn, yaw0_rad: float = 0.3) -> Truth:
    """Integrate a planar drive at 1 kHz from speed(t) and yaw_rate(t)."""
    t = np.arange(0.0, duration_s + 1e-9, 1e-3)
    v, w = speed_fn(t), yaw_rate_fn(t)
    yaw = yaw0_rad + np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * 1e-3)])
    vx, vy = v * np.cos(yaw), v * np.sin(yaw)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * 1e-3)]) + 5.0
    y = np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * 1e-3)]) - 3.0
    return Truth(t, x, y, yaw, v, w)


def sensors_from_truth(
    truth: Truth,
    rng: np.random.Generator,
    gps_std_m: float = 1.0,
    gps_hz: float = 10.0,
    imu_hz: float = 100.0,
    speed_hz: float = 50.0,
    gyro_bias_radps: float = 0.02,
    gyro_std_radps: float = 0.01,
    speed_std_mps: float = 0.05,
    t0_ns: int = 1_700_000_000_000_000_000,
) -> SensorSeries:
    """GPS (lat/lon with white noise), IMU (biased, noisy yaw rate) and wheel speed sampled from a true drive."""
    end = truth.t_s[-1]
    tg = np.arange(0.0, end, 1.0 / gps_hz)
    gx, gy, _ = truth.at(tg)
    gx = gx + rng.normal(0, gps_std_m, len(tg))
    gy = gy + rng.normal(0, gps_std_m, len(tg))
    to_geo = enu_transformer(*ORIGIN)
    lon, lat, alt = to_geo.transform(gx, gy, np.full(len(tg), 2.0), direction="INVERSE")
    cov = np.zeros((len(tg), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = gps_std_m**2
    cov[:, 2, 2] = (2 * gps_std_m) ** 2
    gps = GpsSeries(
        t_ns=t0_ns + np.round(tg * 1e9).astype(np.int64),
        lat_deg=lat,
        lon_deg=lon,
        alt_m=alt,
        status=np.zeros(len(tg), np.int8),
        covariance_m2=cov,
        covariance_type=np.full(len(tg), 2, np.uint8),
    )
    ti = np.arange(0.0, end, 1.0 / imu_hz)
    gyro = np.zeros((len(ti), 3))
    gyro[:, 2] = np.interp(ti, truth.t_s, truth.w) + gyro_bias_radps + rng.normal(0, gyro_std_radps, len(ti))
    acc = np.zeros((len(ti), 3))
    acc[:, 2] = 9.81
    imu = ImuSeries(
        t_ns=t0_ns + np.round(ti * 1e9).astype(np.int64),
        angular_velocity_radps=gyro,
        linear_acceleration_mps2=acc,
        orientation_xyzw=np.full((len(ti), 4), np.nan),
    )
    ts = np.arange(0.0, end, 1.0 / speed_hz)
    speed = SpeedSeries(
        t_ns=t0_ns + np.round(ts * 1e9).astype(np.int64),
        speed_mps=np.interp(ts, truth.t_s, truth.v) + rng.normal(0, speed_std_mps, len(ts)),
    )
    return SensorSeries(gps=gps, imu=imu, speed=speed)


def frame_times(
    truth: Truth, hz: float = 10.0, t0_ns: int = 1_700_000_000_000_000_000
) -> tuple[np.ndarray, np.ndarray]:
    tf = np.arange(0.05, truth.t_s[-1] - 0.05, 1.0 / hz)
    return tf, t0_ns + np.round(tf * 1e9).astype(np.int64)


def position_error(truth: Truth, tf: np.ndarray, fused) -> np.ndarray:
    """Distance of the fused track to the truth, both in the ENU frame about ORIGIN (the fused one is about the
    first fix: a few metres away, so the two frames differ by a shift only)."""
    x, y, _ = truth.at(tf)
    dx = dy = 0.0
    if fused.origin_lat_deg is not None:
        dx, dy, _ = enu_transformer(*ORIGIN).transform(fused.origin_lon_deg, fused.origin_lat_deg, fused.origin_alt_m)
    return np.hypot(fused.x_m + dx - x, fused.y_m + dy - y)


def circle_truth(radius_m: float = 40.0, speed_mps: float = 10.0, duration_s: float = 60.0) -> Truth:
    return simulate_truth(
        duration_s, lambda t: np.full_like(t, speed_mps), lambda t: np.full_like(t, speed_mps / radius_m)
    )


@pytest.mark.parametrize("yaw_rate_radps", [0.4, 1e-6, 0.0, -0.25])
def test_ctrv_prediction_is_the_exact_arc_and_its_jacobian_matches_finite_differences(yaw_rate_radps):
    state = np.array([3.0, -2.0, 0.7, 12.0, yaw_rate_radps, 0.01])
    dt = 0.8
    pred, F = ekf.ctrv_predict(state, dt)
    w, yaw, v = yaw_rate_radps, 0.7, 12.0
    if abs(w) > 1e-9:
        x = 3.0 + v / w * (np.sin(yaw + w * dt) - np.sin(yaw))
        y = -2.0 + v / w * (np.cos(yaw) - np.cos(yaw + w * dt))
    else:
        x, y = 3.0 + v * dt * np.cos(yaw), -2.0 + v * dt * np.sin(yaw)
    np.testing.assert_allclose(pred[:3], [x, y, yaw + w * dt], atol=1e-9)
    numeric = np.zeros((6, 6))
    for j in range(6):
        h = 1e-6
        plus, _ = ekf.ctrv_predict(state + h * np.eye(6)[j], dt)
        minus, _ = ekf.ctrv_predict(state - h * np.eye(6)[j], dt)
        numeric[:, j] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(F, numeric, atol=1e-6)


def test_rts_beats_gps_noise_on_a_circle_with_gyro_bias():
    truth = circle_truth()
    series = sensors_from_truth(truth, np.random.default_rng(0), gps_std_m=1.0, gyro_bias_radps=0.02)
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms < 0.4, f"RMS position error {rms:.3f} m with 1 m GPS noise"
    _, _, yaw = truth.at(tf)
    yaw_err = np.abs(wrap_angle(fused.yaw_rad - yaw))
    assert np.degrees(yaw_err[10:-10]).max() < 2.0
    assert fused.source == "gps_imu"
    assert fused.origin_lat_deg == pytest.approx(series.gps.lat_deg[0])
    # the residual to the fixes is about the GPS noise (sqrt(2) * 1 m for 2D), not the filter's error
    assert 1.1 < fused.residual_m < 1.7
    # the causal filter alone is worse than the smoother
    filtered = fuse_gps_imu(series, tf_ns, PoseConfig(smoothing=False))
    assert np.sqrt(np.mean(position_error(truth, tf, filtered) ** 2)) > rms


def test_curvature_speed_and_arc_length_on_a_constant_radius_arc():
    truth = circle_truth(radius_m=40.0, speed_mps=10.0)
    series = sensors_from_truth(truth, np.random.default_rng(1))
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    inner = slice(20, -20)
    kappa = fused.curvature_1pm[inner]
    assert np.all(np.abs(kappa - 1 / 40.0) < 0.1 / 40.0), (kappa.min(), kappa.max())
    assert np.abs(fused.speed_mps[inner] - 10.0).max() < 0.2
    travelled = 10.0 * (tf[-1] - tf[0])
    assert fused.arc_length_m[-1] == pytest.approx(travelled, rel=0.01)
    assert fused.arc_length_m[0] == 0.0 and np.all(np.diff(fused.arc_length_m) >= 0)


def test_curvature_sign_and_straight_segments_on_an_s_curve():
    # straight 10 s, left arc (R=50 m) 10 s, right arc (R=25 m) 10 s, at 8 m/s
    def w(t):
        return np.where(t < 10, 0.0, np.where(t < 20, 8.0 / 50.0, -8.0 / 25.0))

    truth = simulate_truth(30.0, lambda t: np.full_like(t, 8.0), w)
    series = sensors_from_truth(truth, np.random.default_rng(2))
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    k = fused.curvature_1pm
    assert np.abs(k[(tf > 1) & (tf < 8)]).max() < 0.003
    assert np.abs(k[(tf > 12) & (tf < 18)] - 1 / 50).max() < 0.1 / 50
    assert np.abs(k[(tf > 22) & (tf < 28)] + 1 / 25).max() < 0.1 / 25


def test_standstill_keeps_position_heading_and_curvature_steady():
    # 15 s on a 50 m arc at 10 m/s, brake to 0 in 3 s, stand 10 s (GPS noise goes on), pull away, 10 s more
    def speed(t):
        return np.interp(t, [0, 15, 18, 28, 31, 41], [10, 10, 0, 0, 10, 10])

    truth = simulate_truth(41.0, speed, lambda t: speed(t) / 50.0)
    series = sensors_from_truth(truth, np.random.default_rng(8))
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    assert np.sqrt(np.mean(err**2)) < 0.4
    stopped = (tf > 18.5) & (tf < 27.5)
    assert np.ptp(fused.arc_length_m[stopped]) < 0.3  # GPS jitter does not make the parked car travel
    assert np.degrees(np.ptp(np.unwrap(fused.yaw_rad[stopped]))) < 1.0
    # the road's curvature where it stands (1/50 m), not yaw_rate/speed noise at v = 0
    assert np.abs(fused.curvature_1pm[stopped] - 0.02).max() < 0.002
    assert np.abs(fused.speed_mps[stopped]).max() < 0.1
    moving = (tf > 2) & (tf < 13)
    assert np.abs(fused.curvature_1pm[moving] - 0.02).max() < 0.002


def test_gps_outage_of_five_seconds_is_bridged_by_imu_and_speed():
    truth = circle_truth(radius_m=60.0, speed_mps=12.0, duration_s=40.0)
    series = sensors_from_truth(truth, np.random.default_rng(3))
    t_gps = (series.gps.t_ns - series.gps.t_ns[0]) * 1e-9
    keep = (t_gps < 20.0) | (t_gps >= 25.0)
    g = series.gps
    series.gps = GpsSeries(*(getattr(g, f)[keep] for f in g.__dataclass_fields__))
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    in_gap = (tf > 20.0) & (tf < 25.0)
    assert err[in_gap].max() < 1.0, f"max error in the 5 s gap {err[in_gap].max():.2f} m (60 m travelled)"
    assert np.sqrt(np.mean(err**2)) < 0.5


def test_frames_before_the_first_fix_and_after_the_last_sample():
    truth = circle_truth(radius_m=60.0, speed_mps=10.0, duration_s=30.0)
    series = sensors_from_truth(truth, np.random.default_rng(9))
    g = series.gps
    late = (g.t_ns - g.t_ns[0]) >= 3_000_000_000  # the receiver gets its first fix 3 s (30 m) into the drive
    series.gps = GpsSeries(*(getattr(g, f)[late] for f in g.__dataclass_fields__))
    tf, tf_ns = frame_times(truth)
    tf_ns = np.concatenate([tf_ns, tf_ns[-1] + np.arange(1, 6) * 100_000_000])  # 0.5 s past every sensor
    tf = np.concatenate([tf, tf[-1] + np.arange(1, 6) * 0.1])
    truth = circle_truth(radius_m=60.0, speed_mps=10.0, duration_s=31.0)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    assert err[tf < 3.0].max() < 1.0, f"dead-reckoned back from the first fix: max {err[tf < 3.0].max():.2f} m"
    assert err[tf > tf[-6]].max() < 1.0, "extrapolated past the last sample"
    assert np.sqrt(np.mean(err**2)) < 0.4


def test_bad_fixes_are_rejected():
    truth = circle_truth(radius_m=50.0, speed_mps=10.0, duration_s=40.0)
    rng = np.random.default_rng(4)
    series = sensors_from_truth(truth, rng)
    g = series.gps
    n = len(g.t_ns)
    # status -1 fixes far away, isolated 50 m jumps that claim 1 m accuracy, and fixes with 30 m std
    no_fix = np.arange(20, n, 37)
    jumps = np.arange(30, n, 41)
    vague = np.arange(45, n, 53)
    g.status[no_fix] = -1
    g.lat_deg[no_fix] += 0.01
    g.lat_deg[jumps] += 50.0 / 111_000.0
    g.covariance_m2[vague, 0, 0] = g.covariance_m2[vague, 1, 1] = 30.0**2
    g.lon_deg[vague] += 40.0 / 74_000.0
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    assert err.max() < 1.0, f"max error {err.max():.2f} m: a bad fix got through"
    assert np.sqrt(np.mean(err**2)) < 0.4
    bad = len(set(no_fix) | set(jumps) | set(vague))
    assert fused.fixes_rejected >= bad
    assert fused.fixes_rejected < bad + 0.02 * n  # the gate rejects little else


def test_a_lasting_gps_shift_is_followed_after_the_gate_reset():
    truth = circle_truth(radius_m=80.0, speed_mps=10.0, duration_s=40.0)
    series = sensors_from_truth(truth, np.random.default_rng(10))
    g = series.gps
    shifted = (g.t_ns - g.t_ns[0]) >= 15_000_000_000  # e.g. the receiver switches to a corrected solution
    g.lat_deg[shifted] += 20.0 / 111_000.0
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig(gps_gate_reset_s=5.0))
    x, y, _ = truth.at(tf)
    dx, dy, _ = enu_transformer(*ORIGIN).transform(fused.origin_lon_deg, fused.origin_lat_deg, fused.origin_alt_m)
    to_shifted = np.hypot(fused.x_m + dx - x, fused.y_m + dy - (y + 20.0))
    assert to_shifted[tf > 25.0].max() < 1.0  # it trusts the fixes again instead of dead-reckoning forever
    assert 45 <= fused.fixes_rejected <= 60  # the 5 s of fixes (10 Hz) before the reset, and no more


def test_gps_only_without_imu_or_speed_still_tracks():
    truth = circle_truth(radius_m=80.0, speed_mps=8.0, duration_s=40.0)
    series = sensors_from_truth(truth, np.random.default_rng(5), gps_std_m=0.5)
    series.imu = series.speed = None
    tf, tf_ns = frame_times(truth)
    fused = fuse_gps_imu(series, tf_ns, PoseConfig())
    err = position_error(truth, tf, fused)
    assert np.sqrt(np.mean(err**2)) < 0.4
    assert np.abs(fused.speed_mps[20:-20] - 8.0).max() < 0.5


def _odometry_from_truth(truth: Truth, hz: float = 20.0, t0_ns: int = 1_700_000_000_000_000_000) -> OdometrySeries:
    to = np.arange(0.0, truth.t_s[-1], 1.0 / hz)
    x, y, yaw = truth.at(to)
    q = np.zeros((len(to), 4))
    q[:, 2], q[:, 3] = np.sin(yaw / 2), np.cos(yaw / 2)
    lin = np.zeros((len(to), 3))
    lin[:, 0] = np.interp(to, truth.t_s, truth.v)
    ang = np.zeros((len(to), 3))
    ang[:, 2] = np.interp(to, truth.t_s, truth.w)
    return OdometrySeries(
        t_ns=t0_ns + np.round(to * 1e9).astype(np.int64),
        position_m=np.column_stack([x, y, np.zeros_like(x)]),
        orientation_xyzw=q,
        linear_velocity_mps=lin,
        angular_velocity_radps=ang,
    )


def test_odometry_only_path():
    truth = circle_truth(radius_m=30.0, speed_mps=6.0, duration_s=30.0)
    series = SensorSeries(odometry=_odometry_from_truth(truth))
    tf, tf_ns = frame_times(truth)
    fused = estimate_poses(series, tf_ns, PoseConfig())
    assert fused.source == "odometry"
    assert position_error(truth, tf, fused).max() < 0.05
    assert np.abs(fused.speed_mps - 6.0).max() < 1e-6
    assert np.abs(fused.curvature_1pm[20:-20] - 1 / 30).max() < 0.05 / 30
    assert fused.origin_lat_deg is None and fused.residual_m is None
    same = odometry_track(series, tf_ns, PoseConfig())
    np.testing.assert_allclose(same.T_world_vehicle, fused.T_world_vehicle)


def test_auto_prefers_given_then_gps_then_odometry_and_ground_truth_only_on_request():
    truth = circle_truth(duration_s=20.0)
    series = sensors_from_truth(truth, np.random.default_rng(6))
    series.odometry = _odometry_from_truth(truth)
    tf, tf_ns = frame_times(truth)
    assert estimate_poses(series, tf_ns, PoseConfig()).source == "gps_imu"
    assert estimate_poses(series, tf_ns, PoseConfig(source="odometry")).source == "odometry"
    with pytest.raises(InputError, match="ground_truth"):
        estimate_poses(series, tf_ns, PoseConfig(source="ground_truth"))
    series.gps.status[:] = -1
    assert estimate_poses(series, tf_ns, PoseConfig()).source == "odometry"
    with pytest.raises(InputError, match="none of the"):
        estimate_poses(series, tf_ns, PoseConfig(source="gps_imu"))


def test_given_camera_poses_in_kitti_convention_become_z_up_vehicle_poses():
    truth = circle_truth(radius_m=30.0, speed_mps=6.0, duration_s=20.0)
    odo = _odometry_from_truth(truth, hz=10.0)
    T_vc = camera_mount(1.5, 0.0, 1.6, pitch_down_rad=0.05)
    T_wv = np.zeros((len(odo.t_ns), 4, 4))
    yaw = 2 * np.arctan2(odo.orientation_xyzw[:, 2], odo.orientation_xyzw[:, 3])
    T_wv[:, 0, 0], T_wv[:, 0, 1], T_wv[:, 1, 0], T_wv[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    T_wv[:, 2, 2] = T_wv[:, 3, 3] = 1
    T_wv[:, :3, 3] = odo.position_m
    # KITTI: the world is the first camera's optical frame
    T_wc = np.linalg.inv(T_wv[0] @ T_vc) @ T_wv @ T_vc
    series = SensorSeries(given_poses=GivenPoses(odo.t_ns, T_wc))
    fused = estimate_poses(series, odo.t_ns, PoseConfig(), T_vehicle_camera=T_vc)
    assert fused.source == "given"
    expected = np.linalg.inv(T_wv[0]) @ T_wv  # the first vehicle pose becomes the world origin, z up
    np.testing.assert_allclose(fused.T_world_vehicle, expected, atol=1e-9)
    assert fused.yaw_rad[0] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(camera_poses(fused.T_world_vehicle, T_vc), expected @ T_vc, atol=1e-9)
    assert np.abs(fused.speed_mps[5:-5] - 6.0).max() < 0.05


def test_ground_truth_only_when_asked_and_then_exact():
    truth = circle_truth(radius_m=30.0, speed_mps=6.0, duration_s=20.0)
    odo = _odometry_from_truth(truth, hz=50.0)
    T = np.tile(np.eye(4), (len(odo.t_ns), 1, 1))
    yaw = 2 * np.arctan2(odo.orientation_xyzw[:, 2], odo.orientation_xyzw[:, 3])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    T[:, :3, 3] = odo.position_m
    series = sensors_from_truth(truth, np.random.default_rng(11))
    series.ground_truth = GroundTruthPoses(odo.t_ns, T)
    tf, tf_ns = frame_times(truth)
    assert estimate_poses(series, tf_ns, PoseConfig()).source == "gps_imu"  # the honest path by default
    gt = estimate_poses(series, tf_ns, PoseConfig(source="ground_truth"))
    assert gt.source == "ground_truth"
    x, y, yaw_true = truth.at(tf)
    assert np.hypot(gt.x_m - x, gt.y_m - y).max() < 0.01
    assert np.abs(wrap_angle(gt.yaw_rad - yaw_true)).max() < 1e-3
    assert np.abs(gt.curvature_1pm[20:-20] - 1 / 30).max() < 0.02 / 30


def test_sfm_metric_scale_from_path_length_or_speed():
    from drivesim.stages.preprocess.sfm import metric_scale

    t_ns = np.arange(11, dtype=np.int64) * 100_000_000  # 1 s
    unit_path = np.column_stack([np.linspace(0, 2, 11), np.zeros(11), np.zeros(11)])  # 2 SfM units
    assert metric_scale(t_ns, unit_path, None, 30.0) == pytest.approx(15.0)
    speed = (np.arange(0, 21, dtype=np.int64) * 50_000_000, np.full(21, 12.0))  # 12 m/s for 1 s
    assert metric_scale(t_ns, unit_path, speed, None) == pytest.approx(6.0)
    with pytest.raises(InputError, match="sfm_scale_m"):
        metric_scale(t_ns, unit_path, None, None)
    with pytest.raises(InputError, match="does not move"):
        metric_scale(t_ns, np.zeros((11, 3)), speed, None)


def test_missing_every_source_is_one_clear_input_error():
    with pytest.raises(InputError, match="no GPS, odometry or given poses in the trace; set poses.source=sfm"):
        estimate_poses(SensorSeries(), np.arange(10, dtype=np.int64) * 100_000_000, PoseConfig())
    with pytest.raises(InputError, match="frames and intrinsics"):
        estimate_poses(SensorSeries(), np.arange(10, dtype=np.int64), PoseConfig(source="sfm"))


def test_load_series_round_trip_and_bad_shape(tmp_path):
    truth = circle_truth(duration_s=5.0)
    series = sensors_from_truth(truth, np.random.default_rng(7))
    np.savez(tmp_path / "gps.npz", **vars(series.gps))
    np.savez(tmp_path / "speed.npz", **vars(series.speed))
    loaded = load_series(tmp_path)
    assert loaded.imu is None and loaded.odometry is None and loaded.given_poses is None
    np.testing.assert_array_equal(loaded.gps.lat_deg, series.gps.lat_deg)
    np.testing.assert_array_equal(loaded.speed.t_ns, series.speed.t_ns)
    np.savez(
        tmp_path / "imu.npz", t_ns=series.imu.t_ns, angular_velocity_radps=series.imu.angular_velocity_radps[:, :2]
    )
    with pytest.raises(InputError, match=r"imu.npz: imu series lacks"):
        load_series(tmp_path)
    np.savez(
        tmp_path / "imu.npz",
        t_ns=series.imu.t_ns,
        angular_velocity_radps=series.imu.angular_velocity_radps[:, :2],
        linear_acceleration_mps2=series.imu.linear_acceleration_mps2,
        orientation_xyzw=series.imu.orientation_xyzw,
    )
    with pytest.raises(InputError, match=r"imu.angular_velocity_radps has shape"):
        load_series(tmp_path)
