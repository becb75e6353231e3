"""Per-frame vehicle poses from the trace's sensors: GPS+IMU+speed fusion (CTRV EKF + RTS smoother), odometry,
given poses, ground truth or visual SfM; with speed, curvature and arc length along the path.

World frame: local ENU (x east, y north, z up) with its origin at the first good GPS fix; without GPS, the frame of
the pose source (odometry frame, or the first vehicle pose for given camera poses that are not z-up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pyproj import Transformer
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, Slerp

from drivesim.pipeline.errors import InputError
from drivesim.sim.geometry import invert, wrap_angle
from drivesim.stages.preprocess import ekf
from drivesim.stages.preprocess.config import PoseConfig
from drivesim.stages.preprocess.series import GpsSeries, SensorSeries

NO_SOURCE_MESSAGE = (
    "no GPS, odometry or given poses in the trace; set poses.source=sfm with poses.sfm_scale_m or a speed series"
)


@dataclass
class FusedPoses:
    """Per-frame vehicle poses in the world frame.

    :param t_ns: frame times (N,) int64.
    :param x_m, y_m, z_m: vehicle origin in the world frame (N,).
    :param yaw_rad: heading from world +x, counter-clockwise (N,).
    :param speed_mps: forward speed (N,) (negative when reversing).
    :param curvature_1pm: signed path curvature dyaw/ds, smoothed (N,) (positive = left turn).
    :param arc_length_m: distance travelled since the first frame (N,).
    :param T_world_vehicle: (N, 4, 4).
    :param source: which source produced them ("gps_imu", "odometry", "given", "sfm", "ground_truth").
    :param origin_lat_deg, origin_lon_deg, origin_alt_m: WGS84 of the world origin when GPS-referenced.
    :param residual_m: RMS distance of the fused track to the accepted GPS fixes (m), for GPS fusion.
    :param fixes_used, fixes_rejected: GPS fixes fused / not fused (no fix, too vague, or gated out), for GPS fusion.
    """

    t_ns: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    curvature_1pm: np.ndarray
    arc_length_m: np.ndarray
    T_world_vehicle: np.ndarray
    source: str
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_alt_m: float | None = None
    residual_m: float | None = None
    fixes_used: int | None = None
    fixes_rejected: int | None = None


def camera_poses(T_world_vehicle: np.ndarray, T_vehicle_camera: np.ndarray) -> np.ndarray:
    """T_world_camera (N, 4, 4) of a camera mounted at T_vehicle_camera on each vehicle pose."""
    return T_world_vehicle @ T_vehicle_camera


def enu_transformer(lat0_deg: float, lon0_deg: float, alt0_m: float) -> Transformer:
    """pyproj transform WGS84 (lon, lat, h) -> local ENU (e, n, u) metres about the given origin."""
    lat0, lon0, h0 = float(lat0_deg), float(lon0_deg), float(alt0_m)  # numpy scalars would print as np.float64(...)
    return Transformer.from_pipeline(
        "+proj=pipeline +step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}"
    )


# ---------------------------------------------------------------------------------------------------------------------
# Shared per-frame quantities


def _poses_from_planar(
    x_m: np.ndarray,
    y_m: np.ndarray,
    z_m: np.ndarray,
    yaw_rad: np.ndarray,
    pitch_rad: np.ndarray | None = None,
    roll_rad: np.ndarray | None = None,
) -> np.ndarray:
    """T_world_vehicle = translation (x, y, z) @ Rz(yaw) Ry(pitch) Rx(roll) (level when pitch/roll are None)."""
    T = np.zeros((len(x_m), 4, 4))
    zeros = np.zeros(len(x_m))
    angles = np.column_stack(
        [yaw_rad, zeros if pitch_rad is None else pitch_rad, zeros if roll_rad is None else roll_rad]
    )
    T[:, :3, :3] = Rotation.from_euler("ZYX", angles).as_matrix()
    T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x_m, y_m, z_m
    return T


def _imu_tilt(series: SensorSeries, rel_s, t_query: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Vehicle pitch and roll (rad) at the query times from the IMU's orientation, or None when it has none."""
    imu = series.imu
    if imu is None:
        return None
    q = imu.orientation_xyzw
    ok = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    if ok.sum() < 2:
        return None
    _, pitch, roll = Rotation.from_quat(q[ok]).as_euler("ZYX").T
    t = rel_s(imu.t_ns[ok])
    return np.interp(t_query, t, pitch), wrap_angle(np.interp(t_query, t, np.unwrap(roll)))


def arc_length(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Cumulative 2D distance along the points, starting at 0."""
    step = np.hypot(np.diff(x_m), np.diff(y_m))
    return np.concatenate([[0.0], np.cumsum(step)])


def smooth_curvature(
    yaw_rate_radps: np.ndarray, speed_mps: np.ndarray, arc_length_m: np.ndarray, min_speed_mps: float, sigma_m: float
) -> np.ndarray:
    """Path curvature dyaw/ds at each sample, smoothed along the arc length (Gaussian, `sigma_m`).

    Least squares of yaw_rate = kappa * speed over the samples near each arc length (a normalised convolution of
    sum(w*v) by sum(v^2)): stopped samples carry no weight, so a parked car reports the curvature of the road where
    it stands instead of yaw_rate/speed noise; where the whole neighbourhood crawls well below `min_speed_mps`, it
    fades to 0.
    """
    v = speed_mps
    if sigma_m <= 0 or len(v) < 3 or arc_length_m[-1] - arc_length_m[0] < 1e-6:
        return yaw_rate_radps * v / (v * v + min_speed_mps**2)
    ds = min(0.1, sigma_m / 4.0)
    n_cells = int(np.floor((arc_length_m[-1] - arc_length_m[0]) / ds)) + 1
    cell = np.clip(np.round((arc_length_m - arc_length_m[0]) / ds).astype(np.int64), 0, n_cells - 1)
    wv = np.bincount(cell, weights=yaw_rate_radps * v, minlength=n_cells)
    vv = np.bincount(cell, weights=v * v, minlength=n_cells)
    count = np.bincount(cell, minlength=n_cells).astype(float)
    sigma_cells = sigma_m / ds
    num = gaussian_filter1d(wv, sigma_cells, mode="nearest")
    den = gaussian_filter1d(vv, sigma_cells, mode="nearest")
    # a prior kappa = 0, weighted like one sample at a tenth of min_speed_mps per sample: it decides only where
    # the whole neighbourhood is (nearly) stopped, and biases a 1 m/s crawl by 1 % when min_speed_mps = 1
    den += (0.1 * min_speed_mps) ** 2 * gaussian_filter1d(count, sigma_cells, mode="nearest")
    return (num / np.maximum(den, 1e-12))[cell]


def _interp_yaw(t_query: np.ndarray, t: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    return wrap_angle(np.interp(t_query, t, np.unwrap(yaw)))


# ---------------------------------------------------------------------------------------------------------------------
# GPS + IMU + speed


def _bin_mean(t_s: np.ndarray, values: np.ndarray, bin_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average samples into time bins of `bin_s`: (bin index, mean time, mean value) per non-empty bin."""
    idx = np.floor(t_s / bin_s).astype(np.int64)
    bins, inverse, counts = np.unique(idx, return_inverse=True, return_counts=True)
    mean_t = np.bincount(inverse, weights=t_s) / counts
    mean_v = np.bincount(inverse, weights=values) / counts
    return bins, mean_t, mean_v


def _yaw_rate_up(imu_w: np.ndarray, orientation_xyzw: np.ndarray) -> np.ndarray:
    """Rotation rate about the gravity-up axis: the body rates rotated by the IMU's tilt where it gives one."""
    w_up = imu_w[:, 2].copy()
    ok = np.all(np.isfinite(orientation_xyzw), axis=1) & (np.linalg.norm(orientation_xyzw, axis=1) > 0.5)
    if ok.any():
        w_up[ok] = Rotation.from_quat(orientation_xyzw[ok]).apply(imu_w[ok])[:, 2]
    return w_up


def _gps_enu(gps: GpsSeries, cfg: PoseConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple]:
    """Good fixes in ENU about the first good fix: (index into gps, e/n/u (M,3), covariance (M,2,2), origin)."""
    cov = gps.covariance_m2[:, :2, :2].copy()
    unknown = gps.covariance_type == 0
    cov[unknown] = np.eye(2) * cfg.gps_default_std_m**2
    var_max = np.maximum(cov[:, 0, 0], cov[:, 1, 1])
    good = (
        (gps.status >= 0)
        & np.isfinite(gps.lat_deg)
        & np.isfinite(gps.lon_deg)
        & np.isfinite(var_max)
        & (var_max <= cfg.gps_max_std_m**2)
    )
    idx = np.flatnonzero(good)
    if len(idx) == 0:
        return idx, np.zeros((0, 3)), np.zeros((0, 2, 2)), (None, None, None)
    alt = np.where(np.isfinite(gps.alt_m), gps.alt_m, 0.0)
    i0 = idx[0]
    origin = (float(gps.lat_deg[i0]), float(gps.lon_deg[i0]), float(alt[i0]))
    e, n, u = enu_transformer(*origin).transform(gps.lon_deg[idx], gps.lat_deg[idx], alt[idx])
    floor = cfg.gps_min_std_m**2
    cov = cov[idx]
    cov[:, 0, 0] = np.maximum(cov[:, 0, 0], floor)
    cov[:, 1, 1] = np.maximum(cov[:, 1, 1], floor)
    return idx, np.column_stack([e, n, u]), cov, origin


def _initial_yaw(t_fix: np.ndarray, xy_fix: np.ndarray, std_m: float, t_w: np.ndarray, w: np.ndarray) -> float:
    """Heading at the first fix from the first clear displacement, corrected for the turn made meanwhile."""
    d = np.hypot(xy_fix[:, 0] - xy_fix[0, 0], xy_fix[:, 1] - xy_fix[0, 1])
    far = np.flatnonzero(d > max(3.0, 4.0 * std_m))
    if len(far) == 0:
        return 0.0
    j = far[0]
    chord = float(np.arctan2(xy_fix[j, 1] - xy_fix[0, 1], xy_fix[j, 0] - xy_fix[0, 0]))
    if len(t_w) < 2:
        return chord
    inside = (t_w >= t_fix[0]) & (t_w <= t_fix[j])
    turned = float(np.trapezoid(w[inside], t_w[inside])) if inside.sum() > 1 else 0.0
    return float(wrap_angle(chord - 0.5 * turned))


Samples = tuple[np.ndarray, np.ndarray]  # (t_s, value)


def _rate_and_speed_samples(series: SensorSeries, rel_s, cfg: PoseConfig) -> tuple[Samples, Samples, float, bool]:
    """Yaw-rate samples (IMU about the vertical, else odometry) and speed samples (speed series, else odometry),
    finite only; with the yaw-rate variance and whether it comes from a (biased) gyro."""
    rates: Samples = (np.zeros(0), np.zeros(0))
    biased, var = False, cfg.imu_yaw_rate_std_radps**2
    if series.imu is not None and len(series.imu.t_ns):
        imu = series.imu
        rates, biased = (rel_s(imu.t_ns), _yaw_rate_up(imu.angular_velocity_radps, imu.orientation_xyzw)), True
    elif series.odometry is not None and len(series.odometry.t_ns):
        rates = (rel_s(series.odometry.t_ns), series.odometry.angular_velocity_radps[:, 2])
        var = cfg.odometry_yaw_rate_std_radps**2
    speeds: Samples = (np.zeros(0), np.zeros(0))
    if series.speed is not None and len(series.speed.t_ns):
        speeds = (rel_s(series.speed.t_ns), series.speed.speed_mps)
    elif series.odometry is not None and len(series.odometry.t_ns):
        speeds = (rel_s(series.odometry.t_ns), series.odometry.linear_velocity_mps[:, 0])
    rates = tuple(a[np.isfinite(rates[1])] for a in rates)
    speeds = tuple(a[np.isfinite(speeds[1])] for a in speeds)
    return rates, speeds, var, biased


def _measurement_events(
    rates: Samples,
    speeds: Samples,
    rate_var: float,
    rate_biased: bool,
    fix_t: np.ndarray,
    fix_xy: np.ndarray,
    fix_cov: np.ndarray,
    cfg: PoseConfig,
) -> tuple[ekf.Measurements, np.ndarray, int]:
    """All measurements as filter events in time order: yaw rate and speed averaged into shared bins of
    1/imu_rate_hz (one event per bin), and one event per fix. Returns (events, the sorting order, bin count)."""
    bin_s = 1.0 / cfg.imu_rate_hz
    wb, wt, wv = _bin_mean(*rates, bin_s)
    sb, st, sv = _bin_mean(*speeds, bin_s)
    grid_bins = np.union1d(wb, sb)
    G = len(grid_bins)
    iw, is_ = np.searchsorted(grid_bins, wb), np.searchsorted(grid_bins, sb)
    g_w, g_v = np.full(G, np.nan), np.full(G, np.nan)
    g_w[iw], g_v[is_] = wv, sv
    g_t, g_n = np.zeros(G), np.zeros(G)
    np.add.at(g_t, iw, wt)
    np.add.at(g_n, iw, 1)
    np.add.at(g_t, is_, st)
    np.add.at(g_n, is_, 1)
    g_t = g_t / np.maximum(g_n, 1)

    F = len(fix_t)
    K = G + F
    order = np.argsort(np.concatenate([g_t, fix_t]), kind="stable")
    nan = np.full(F, np.nan)
    meas = ekf.Measurements(
        t_s=np.concatenate([g_t, fix_t])[order],
        yaw_rate_radps=np.concatenate([g_w, nan])[order],
        yaw_rate_var=np.full(K, rate_var),
        yaw_rate_biased=np.full(K, rate_biased),
        speed_mps=np.concatenate([g_v, nan])[order],
        speed_var=np.full(K, cfg.speed_std_mps**2),
        fix_xy_m=np.concatenate([np.full((G, 2), np.nan), fix_xy])[order],
        fix_cov_m2=np.concatenate([np.tile(np.eye(2), (G, 1, 1)), fix_cov])[order],
    )
    return meas, order, G


def _initial_state(
    meas: ekf.Measurements,
    rates: Samples,
    speeds: Samples,
    fix_t: np.ndarray,
    fix_xy: np.ndarray,
    fix_cov: np.ndarray,
    rate_biased: bool,
    cfg: PoseConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance at the first event: the first fix's position, the heading of the first clear
    displacement. When IMU/speed samples start before the first fix, the distance the vehicle may have covered
    meanwhile widens the position prior, and the smoother dead-reckons back from the fix."""
    std0 = float(np.sqrt(max(fix_cov[0, 0, 0], fix_cov[0, 1, 1])))
    yaw0 = _initial_yaw(fix_t, fix_xy, std0, *rates)
    lead_s = float(fix_t[0] - meas.t_s[0])
    pos_var, yaw_var = std0**2 + 1.0, 0.5**2
    if lead_s > 0:
        before = speeds[0] < fix_t[0]
        v_max = float(np.abs(speeds[1][before]).max()) if before.any() else 30.0
        pos_var += (v_max * lead_s + 1.0) ** 2
        inside = rates[0] < fix_t[0]
        if inside.sum() > 1:
            yaw0 = float(wrap_angle(yaw0 - np.trapezoid(rates[1][inside], rates[0][inside])))
        yaw_var += (0.02 * lead_s) ** 2
    has_speed = len(speeds[1]) > 0
    x0 = np.array([fix_xy[0, 0], fix_xy[0, 1], yaw0, speeds[1][0] if has_speed else 0.0, 0.0, 0.0])
    bias_var = (cfg.gyro_bias_init_std_radps if rate_biased else 0.0) ** 2 + 1e-12
    P0 = np.diag([pos_var, pos_var, yaw_var, (1.0 if has_speed else 10.0) ** 2, 0.2**2, bias_var])
    return x0, P0


def fuse_gps_imu(series: SensorSeries, frame_times_ns: np.ndarray, cfg: PoseConfig) -> FusedPoses:
    """Fuse GPS fixes with IMU yaw rate and speed (wheel / odometry) by the CTRV EKF + RTS smoother.

    Yaw rate comes from the IMU (tilt-compensated, bias estimated) or else the odometry; speed from the speed series
    or else the odometry's forward velocity. Fixes with status -1, a too large covariance, or failing the Mahalanobis
    gate are not used.
    :raises InputError: the trace has no usable GPS fix.
    """
    gps = series.gps
    if gps is None or len(gps.t_ns) == 0:
        raise InputError("source gps_imu needs GPS fixes, and the trace has none")
    gidx, enu, fix_cov, origin = _gps_enu(gps, cfg)
    if len(gidx) == 0:
        raise InputError(
            f"none of the {len(gps.t_ns)} GPS fixes is usable (status -1 or std above "
            f"poses.gps_max_std_m={cfg.gps_max_std_m} m)"
        )
    frame_times_ns = np.asarray(frame_times_ns, dtype=np.int64)
    t0_ns = int(min(gps.t_ns[gidx[0]], frame_times_ns[0] if len(frame_times_ns) else gps.t_ns[gidx[0]]))

    def rel_s(t_ns: np.ndarray) -> np.ndarray:
        return (np.asarray(t_ns, dtype=np.int64) - t0_ns) * 1e-9

    rates, speeds, rate_var, rate_biased = _rate_and_speed_samples(series, rel_s, cfg)
    fix_t = rel_s(gps.t_ns[gidx])
    meas, order, G = _measurement_events(rates, speeds, rate_var, rate_biased, fix_t, enu[:, :2], fix_cov, cfg)
    x0, P0 = _initial_state(meas, rates, speeds, fix_t, enu[:, :2], fix_cov, rate_biased, cfg)
    noise = ekf.CtrvNoise(
        accel_std_mps2=cfg.accel_std_mps2,
        yaw_accel_std_radps2=cfg.yaw_accel_std_radps2,
        gyro_bias_walk_radps_per_sqrt_s=cfg.gyro_bias_walk_radps_per_sqrt_s if rate_biased else 0.0,
        position_walk_m_per_sqrt_s=cfg.position_walk_m_per_sqrt_s,
        gate_chi2=cfg.gps_gate_chi2,
        gate_reset_s=cfg.gps_gate_reset_s,
    )
    track = ekf.run_filter_smoother(meas, x0, P0, noise, smooth=cfg.smoothing)
    states = track.state

    # Residual to the fixes that were used.
    is_fix = np.isfinite(meas.fix_xy_m[:, 0])
    used = is_fix & track.fix_accepted
    residual = (
        float(np.sqrt(np.mean(np.sum((states[used, :2] - meas.fix_xy_m[used]) ** 2, axis=1)))) if used.any() else None
    )

    t_frames = rel_s(frame_times_ns)
    x, y, yaw, v, w = _sample_states(track.t_s, states, t_frames)
    if cfg.use_altitude:
        fix_used_sorted = track.fix_accepted[np.argsort(order)][G:]  # back to the order of `enu`
        zt, zu = fix_t[fix_used_sorted], enu[fix_used_sorted, 2]
        if len(zt) == 0:
            zt, zu = fix_t, enu[:, 2]
        z = np.interp(t_frames, zt, _smooth_in_time(zt, zu, cfg.altitude_smoothing_s))
    else:
        z = np.zeros_like(x)
    tilt = _imu_tilt(series, rel_s, t_frames) if cfg.use_imu_tilt else None
    s = arc_length(x, y)
    kappa = smooth_curvature(w, v, s, cfg.curvature_min_speed_mps, cfg.curvature_smoothing_m)
    return FusedPoses(
        t_ns=frame_times_ns,
        x_m=x,
        y_m=y,
        z_m=z,
        yaw_rad=yaw,
        speed_mps=v,
        curvature_1pm=kappa,
        arc_length_m=s,
        T_world_vehicle=_poses_from_planar(x, y, z, yaw, *(tilt if tilt is not None else (None, None))),
        source="gps_imu",
        origin_lat_deg=origin[0],
        origin_lon_deg=origin[1],
        origin_alt_m=origin[2],
        residual_m=residual,
        fixes_used=int(used.sum()),
        fixes_rejected=int(len(gps.t_ns) - used.sum()),
    )


def _smooth_in_time(t_s: np.ndarray, values: np.ndarray, sigma_s: float) -> np.ndarray:
    if sigma_s <= 0 or len(values) < 3:
        return values
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    return gaussian_filter1d(values, max(sigma_s / max(dt, 1e-3), 1e-3), mode="nearest")


def _sample_states(
    t_s: np.ndarray, states: np.ndarray, t_query: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y, yaw, speed, yaw rate at the query times: interpolated inside, CTRV-extrapolated outside the events."""
    x = np.interp(t_query, t_s, states[:, ekf.IX])
    y = np.interp(t_query, t_s, states[:, ekf.IY])
    yaw = _interp_yaw(t_query, t_s, states[:, ekf.IYAW])
    v = np.interp(t_query, t_s, states[:, ekf.IV])
    w = np.interp(t_query, t_s, states[:, ekf.IW])
    for k in np.flatnonzero((t_query < t_s[0]) | (t_query > t_s[-1])):
        j = 0 if t_query[k] < t_s[0] else -1
        pred, _ = ekf.ctrv_predict(states[j], float(t_query[k] - t_s[j]))
        x[k], y[k], yaw[k] = pred[ekf.IX], pred[ekf.IY], pred[ekf.IYAW]
    return x, y, yaw, v, w


# ---------------------------------------------------------------------------------------------------------------------
# Pose tracks: odometry, given poses, ground truth, SfM


def track_poses(
    t_ns: np.ndarray,
    T_world_vehicle: np.ndarray,
    frame_times_ns: np.ndarray,
    source: str,
    cfg: PoseConfig,
    speed: tuple[np.ndarray, np.ndarray] | None = None,
) -> FusedPoses:
    """Per-frame poses from a track of full vehicle poses (interpolated; speed and curvature from its motion).

    :param speed: optional (t_ns, speed_mps) measured speed, used instead of the track's differentiated speed.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    frame_times_ns = np.asarray(frame_times_ns, dtype=np.int64)
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    t_ns, T_world_vehicle = t_ns[keep], T_world_vehicle[keep]
    t0 = int(min(t_ns[0], frame_times_ns[0]))
    ts = (t_ns - t0) * 1e-9
    tf = (frame_times_ns - t0) * 1e-9
    if len(ts) == 1:
        T = np.repeat(T_world_vehicle[:1], len(tf), axis=0)
    else:
        rot = Slerp(ts, Rotation.from_matrix(T_world_vehicle[:, :3, :3]))(np.clip(tf, ts[0], ts[-1]))
        T = np.zeros((len(tf), 4, 4))
        T[:, :3, :3] = rot.as_matrix()
        T[:, 3, 3] = 1.0
        for i in range(3):
            T[:, i, 3] = np.interp(tf, ts, T_world_vehicle[:, i, 3])
    x, y, z = T[:, 0, 3], T[:, 1, 3], T[:, 2, 3]
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    # Motion from the source track (finer than the frames, when it is), then sampled at the frames.
    if len(ts) > 2:
        px, py = T_world_vehicle[:, 0, 3], T_world_vehicle[:, 1, 3]
        yaw_src = np.unwrap(np.arctan2(T_world_vehicle[:, 1, 0], T_world_vehicle[:, 0, 0]))
        vx, vy = np.gradient(px, ts), np.gradient(py, ts)
        v_src = vx * np.cos(yaw_src) + vy * np.sin(yaw_src)
        w_src = np.gradient(yaw_src, ts)
        v = np.interp(tf, ts, v_src)
        w = np.interp(tf, ts, w_src)
    else:
        v = w = np.zeros(len(tf))
    if speed is not None and len(speed[0]) > 0:
        v = np.interp(tf, (np.asarray(speed[0], dtype=np.int64) - t0) * 1e-9, speed[1])
    s = arc_length(x, y)
    kappa = smooth_curvature(w, v, s, cfg.curvature_min_speed_mps, cfg.curvature_smoothing_m)
    return FusedPoses(
        t_ns=frame_times_ns,
        x_m=x.copy(),
        y_m=y.copy(),
        z_m=z.copy(),
        yaw_rad=yaw,
        speed_mps=v,
        curvature_1pm=kappa,
        arc_length_m=s,
        T_world_vehicle=T,
        source=source,
    )


def _quat_poses(position_m: np.ndarray, orientation_xyzw: np.ndarray) -> np.ndarray:
    T = np.zeros((len(position_m), 4, 4))
    q = orientation_xyzw
    ok = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    T[:, :3, :3] = np.eye(3)
    if ok.any():
        T[ok, :3, :3] = Rotation.from_quat(q[ok]).as_matrix()
    T[:, :3, 3] = position_m
    T[:, 3, 3] = 1.0
    return T


def odometry_track(series: SensorSeries, frame_times_ns: np.ndarray, cfg: PoseConfig) -> FusedPoses:
    """Per-frame poses from the odometry alone (its own frame), speed from its forward velocity.

    :raises InputError: the trace has no odometry.
    """
    odo = series.odometry
    if odo is None or len(odo.t_ns) == 0:
        raise InputError("source odometry needs an odometry series, and the trace has none")
    T = _quat_poses(odo.position_m, odo.orientation_xyzw)
    speed = (odo.t_ns, odo.linear_velocity_mps[:, 0]) if np.isfinite(odo.linear_velocity_mps[:, 0]).all() else None
    return track_poses(odo.t_ns, T, frame_times_ns, "odometry", cfg, speed=speed)


def level_world(T_world_vehicle: np.ndarray) -> np.ndarray:
    """Re-anchor a track whose world is not z-up (e.g. KITTI's first-camera frame) at its first vehicle pose.

    Kept as is when the vehicles' up axes already point along world +z (within 30 degrees on average).
    """
    up = T_world_vehicle[:, :3, 2].mean(axis=0)
    if up[2] > np.cos(np.radians(30.0)) * np.linalg.norm(up):
        return T_world_vehicle
    return invert(T_world_vehicle[0]) @ T_world_vehicle


def given_track(series: SensorSeries, frame_times_ns: np.ndarray, cfg: PoseConfig, T_vehicle_camera: np.ndarray):
    """Per-frame poses from the trace's given camera poses (T_world_vehicle = T_world_camera @ T_camera_vehicle)."""
    given = series.given_poses
    if given is None or len(given.t_ns) == 0:
        raise InputError("source given needs given poses (poses.npz), and the trace has none")
    T = level_world(given.T_world_camera @ invert(T_vehicle_camera))
    speed = (series.speed.t_ns, series.speed.speed_mps) if series.speed is not None else None
    return track_poses(given.t_ns, T, frame_times_ns, "given", cfg, speed=speed)


# ---------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseInputs:
    """What a pose source may read: the trace's series and frame times, and for sfm its frames and intrinsics."""

    series: SensorSeries
    frame_times_ns: np.ndarray
    frames: np.ndarray | None
    K: np.ndarray | None
    T_vehicle_camera: np.ndarray


def estimate_poses(
    series: SensorSeries,
    frame_times_ns: np.ndarray,
    cfg: PoseConfig,
    frames: np.ndarray | None = None,
    K: np.ndarray | None = None,
    T_vehicle_camera: np.ndarray | None = None,
) -> FusedPoses:
    """Per-frame vehicle poses from the best (or the configured) source.

    auto: given poses, else GPS (+IMU, +speed), else odometry. ground_truth and sfm only when asked for;
    sfm needs `frames`, `K` and `T_vehicle_camera`.
    :raises InputError: the chosen source is missing, or there is no source at all.
    """
    frame_times_ns = np.asarray(frame_times_ns, dtype=np.int64)
    if len(frame_times_ns) == 0:
        raise InputError("the trace has no frames to estimate poses for")
    T_vc = np.eye(4) if T_vehicle_camera is None else np.asarray(T_vehicle_camera, dtype=float)
    inputs = PoseInputs(series, frame_times_ns, frames, K, T_vc)
    source = cfg.source if cfg.source != "auto" else _auto_source(series, cfg)
    check_time_overlap(source, _source_times(series, source), frame_times_ns)
    return POSE_SOURCES[source](inputs, cfg)


# Frames this close outside a pose stream's first and last stamp still count as covered: a 1 Hz GPS's first fix
# may come up to a second after the first frame.
OVERLAP_MARGIN_S = 1.0
MIN_COVERED_FRACTION = 0.5
"""Share of the camera frames that must fall within the pose stream's time span; outside it a car would stand still
(poses are held at the stream's ends), so a drive mostly outside it would be a wrong, shorter world."""


def _source_times(series: SensorSeries, source: str) -> np.ndarray | None:
    """The stamps of the stream that times a pose source (None for sfm, which poses the frames themselves)."""
    stream = {
        "given": series.given_poses,
        "gps_imu": series.gps,
        "odometry": series.odometry,
        "ground_truth": series.ground_truth,
    }.get(source)
    return None if stream is None or len(stream.t_ns) == 0 else np.asarray(stream.t_ns, dtype=np.int64)


def check_time_overlap(source: str, stream_t_ns: np.ndarray | None, frame_times_ns: np.ndarray) -> None:
    """Refuse (InputError) when fewer than MIN_COVERED_FRACTION of the frames fall within the pose stream's time span
    (widened by OVERLAP_MARGIN_S): the camera's and the pose stream's clocks do not overlap."""
    if stream_t_ns is None:
        return
    margin_ns = int(OVERLAP_MARGIN_S * 1e9)
    first, last = int(stream_t_ns.min()) - margin_ns, int(stream_t_ns.max()) + margin_ns
    covered = int(np.count_nonzero((frame_times_ns >= first) & (frame_times_ns <= last)))
    if covered >= MIN_COVERED_FRACTION * len(frame_times_ns):
        return
    t0 = int(frame_times_ns[0])

    def span(a_ns: int, b_ns: int) -> str:
        return f"{(a_ns - t0) / 1e9:.1f} s to {(b_ns - t0) / 1e9:.1f} s"

    raise InputError(
        f"the {source} poses cover {covered} of the {len(frame_times_ns)} camera frames in time (poses "
        f"{span(int(stream_t_ns.min()), int(stream_t_ns.max()))}, frames {span(t0, int(frame_times_ns[-1]))} after "
        "the first frame): the clocks of the camera and the pose stream do not overlap; fix the recording's stamps "
        "or choose another pose source (--set poses.source=...)"
    )


def _auto_source(series: SensorSeries, cfg: PoseConfig) -> str:
    """auto: given poses, else GPS (+IMU, +speed), else odometry."""
    if series.given_poses is not None:
        return "given"
    if series.gps is not None and len(_gps_enu(series.gps, cfg)[0]) > 0:
        return "gps_imu"
    if series.odometry is not None:
        return "odometry"
    raise InputError(NO_SOURCE_MESSAGE)


def _ground_truth(inputs: PoseInputs, cfg: PoseConfig) -> FusedPoses:
    gt = inputs.series.ground_truth
    if gt is None or len(gt.t_ns) == 0:
        raise InputError("source ground_truth needs ground_truth.npz (synthetic recordings only)")
    return track_poses(gt.t_ns, gt.T_world_vehicle, inputs.frame_times_ns, "ground_truth", cfg)


def _sfm(inputs: PoseInputs, cfg: PoseConfig) -> FusedPoses:
    if inputs.frames is None or inputs.K is None:
        raise InputError("source sfm needs the trace's frames and intrinsics")
    from drivesim.stages.preprocess.sfm import sfm_track  # pycolmap is slow to import; only load it when used

    series = inputs.series
    speed = (series.speed.t_ns, series.speed.speed_mps) if series.speed is not None else None
    if speed is None and series.odometry is not None:
        speed = (series.odometry.t_ns, series.odometry.linear_velocity_mps[:, 0])
    t_ns, T_world_vehicle = sfm_track(
        inputs.frames,
        inputs.K,
        inputs.frame_times_ns,
        speed,
        cfg.sfm_scale_m,
        inputs.T_vehicle_camera,
        max_width_px=cfg.sfm_image_width_px,
    )
    return track_poses(t_ns, T_world_vehicle, inputs.frame_times_ns, "sfm", cfg, speed=speed)


# poses.source -> the function that estimates the poses from it (the one place that dispatches on the name).
POSE_SOURCES: dict[str, Callable[[PoseInputs, PoseConfig], FusedPoses]] = {
    "given": lambda inputs, cfg: given_track(inputs.series, inputs.frame_times_ns, cfg, inputs.T_vehicle_camera),
    "gps_imu": lambda inputs, cfg: fuse_gps_imu(inputs.series, inputs.frame_times_ns, cfg),
    "odometry": lambda inputs, cfg: odometry_track(inputs.series, inputs.frame_times_ns, cfg),
    "ground_truth": _ground_truth,
    "sfm": _sfm,
}


__all__ = [
    "POSE_SOURCES",
    "FusedPoses",
    "PoseConfig",
    "camera_poses",
    "enu_transformer",
    "estimate_poses",
    "fuse_gps_imu",
    "odometry_track",
    "track_poses",
]
