"""Simulated pose sensors along a trajectory: GPS fixes, IMU samples and wheel speed, with realistic errors.

Every series is a dict of numpy arrays keyed with units; times are seconds since the start of the drive.
The GPS error is a first-order Gauss–Markov process per axis (stationary standard deviation sigma, correlation
time tau) plus white noise: the slowly wandering offset real receivers show. ENU -> WGS84 goes through pyproj
(topocentric -> geocentric -> geodetic).
"""

from __future__ import annotations

import numpy as np
from pyproj import Transformer

from drivesim.stages.synth.config import GpsConfig, ImuConfig, WheelConfig
from drivesim.stages.synth.drive import Trajectory

GRAVITY_MPS2 = 9.80665


def enu_to_geodetic(cfg: GpsConfig) -> Transformer:
    """A transformer from the synth world's ENU (x east, y north, z up, metres) to WGS84 (lon deg, lat deg, h m)."""
    return Transformer.from_pipeline(
        "+proj=pipeline"
        f" +step +inv +proj=topocentric +ellps=WGS84 +lat_0={cfg.origin_lat_deg} +lon_0={cfg.origin_lon_deg}"
        f" +h_0={cfg.origin_alt_m}"
        " +step +inv +proj=cart +ellps=WGS84"
        " +step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )


def sample_times_s(duration_s: float, rate_hz: float, phase_s: float = 0.0) -> np.ndarray:
    """Sample times `phase_s + k / rate_hz` within [0, duration_s)."""
    n = int(np.ceil((duration_s - phase_s) * rate_hz - 1e-9))
    return phase_s + np.arange(max(n, 0)) / rate_hz


def gauss_markov(n: int, dt_s: float, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary first-order Gauss–Markov sequence of `n` samples (std `sigma`, correlation time `tau_s`)."""
    phi = np.exp(-dt_s / tau_s)
    drive = rng.normal(0.0, sigma * np.sqrt(1.0 - phi * phi), n)
    drive[0] = rng.normal(0.0, sigma)
    out = np.empty(n)
    # a first-order recursion; scipy.signal.lfilter would do it too, but this is clearer and n is small
    acc = 0.0
    for i in range(n):
        acc = phi * acc + drive[i] if i else drive[0]
        out[i] = acc
    return out


def gps_series(traj: Trajectory, cfg: GpsConfig, duration_s: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """GPS fixes: t_s, lat_deg, lon_deg, alt_m, error_enu_m (N,3) (the error added), true_enu_m (N,3),
    covariance_m2 (N,3,3) (ENU, diagonal: what the receiver reports)."""
    t = sample_times_s(duration_s, cfg.rate_hz)
    st = traj.state(t)
    dt = 1.0 / cfg.rate_hz
    true_enu = np.stack([st["x_m"], st["y_m"], np.zeros_like(t)], axis=-1)
    error = np.stack(
        [
            gauss_markov(len(t), dt, cfg.horizontal_error_m, cfg.correlation_time_s, rng),
            gauss_markov(len(t), dt, cfg.horizontal_error_m, cfg.correlation_time_s, rng),
            gauss_markov(len(t), dt, cfg.vertical_error_m, cfg.correlation_time_s, rng),
        ],
        axis=-1,
    )
    error += rng.normal(0.0, cfg.white_noise_m, error.shape)
    measured = true_enu + error
    lon, lat, alt = enu_to_geodetic(cfg).transform(measured[:, 0], measured[:, 1], measured[:, 2])
    var_h = cfg.horizontal_error_m**2 + cfg.white_noise_m**2
    var_v = cfg.vertical_error_m**2 + cfg.white_noise_m**2
    cov = np.broadcast_to(np.diag([var_h, var_h, var_v]), (len(t), 3, 3)).copy()
    return {
        "t_s": t,
        "lat_deg": np.asarray(lat),
        "lon_deg": np.asarray(lon),
        "alt_m": np.asarray(alt),
        "error_enu_m": error,
        "true_enu_m": true_enu,
        "covariance_m2": cov,
    }


def imu_series(traj: Trajectory, cfg: ImuConfig, duration_s: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """IMU samples in base_link (x fwd, y left, z up): t_s, angular_velocity_radps (N,3),
    linear_acceleration_mps2 (N,3) (specific force: +g on z at rest), and the noise-free yaw_rate_true_radps."""
    t = sample_times_s(duration_s, cfg.rate_hz)
    n = len(t)
    st = traj.state(t)
    true_w = np.zeros((n, 3))
    true_w[:, 2] = st["yaw_rate_radps"]
    true_a = np.stack([st["accel_mps2"], st["lateral_accel_mps2"], np.full(n, GRAVITY_MPS2)], axis=-1)
    dt = 1.0 / cfg.rate_hz
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_radps, 3) + np.cumsum(
        rng.normal(0.0, cfg.gyro_bias_walk_radps * np.sqrt(dt), (n, 3)), axis=0
    )
    accel_bias = rng.normal(0.0, cfg.accel_bias_mps2, 3)
    gyro = true_w + gyro_bias + rng.normal(0.0, cfg.gyro_noise_radps, (n, 3))
    accel = true_a + accel_bias + rng.normal(0.0, cfg.accel_noise_mps2, (n, 3))
    return {
        "t_s": t,
        "angular_velocity_radps": gyro,
        "linear_acceleration_mps2": accel,
        "yaw_rate_true_radps": st["yaw_rate_radps"],
    }


def wheel_series(
    traj: Trajectory, cfg: WheelConfig, duration_s: float, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Wheel-odometry forward speed: t_s, speed_mps (with scale error and noise), speed_true_mps."""
    t = sample_times_s(duration_s, cfg.rate_hz)
    v = traj.speed_mps(t)
    measured = v * (1.0 + cfg.scale_error) + rng.normal(0.0, cfg.noise_mps, len(t))
    return {"t_s": t, "speed_mps": measured, "speed_true_mps": v}
