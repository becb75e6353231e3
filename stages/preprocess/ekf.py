"""Extended Kalman filter with a constant-turn-rate-and-velocity (CTRV) model and a Rauch–Tung–Striebel smoother.

State `[x_m, y_m, yaw_rad, speed_mps, yaw_rate_radps, gyro_bias_radps]` in a local ENU frame (yaw from east,
counter-clockwise). Measurements: position fixes (2D, full covariance, Mahalanobis-gated), yaw rate (from a gyro,
which reads yaw_rate + bias, or from odometry, which reads yaw_rate) and forward speed.

Hand-written rather than taken from filterpy & co.: none is installed, and the per-step cost has to stay at a few
microseconds (scalar updates, no generic matrix algebra) to run a 1-hour drive in seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STATE_SIZE = 6
IX, IY, IYAW, IV, IW, IB = range(STATE_SIZE)


@dataclass
class CtrvNoise:
    """Process noise of the CTRV model (white-noise spectral densities) and the position-fix gate.

    :param accel_std_mps2: std of the unmodelled longitudinal acceleration (m/s^2).
    :param yaw_accel_std_radps2: std of the unmodelled yaw acceleration (rad/s^2).
    :param gyro_bias_walk_radps_per_sqrt_s: random walk of the gyro bias (rad/s/sqrt(s)).
    :param position_walk_m_per_sqrt_s: random walk of the position for model errors (slip, bumps) (m/sqrt(s)).
    :param gate_chi2: Mahalanobis gate (chi-square with 2 dof) above which a position fix is rejected.
    :param gate_reset_s: after rejecting every fix for this long (s), accept the next one (then the filter, not the
        GPS, is assumed to have drifted).
    """

    accel_std_mps2: float = 1.0
    yaw_accel_std_radps2: float = 0.5
    gyro_bias_walk_radps_per_sqrt_s: float = 1e-4
    position_walk_m_per_sqrt_s: float = 0.05
    gate_chi2: float = 13.8
    gate_reset_s: float = 5.0


@dataclass
class Measurements:
    """Measurement events in time order; NaN marks an absent measurement at that event.

    :param t_s: event times (s), non-decreasing.
    :param yaw_rate_radps, yaw_rate_var: yaw-rate measurement and its variance ((rad/s)^2).
    :param yaw_rate_biased: True when the yaw rate comes from a gyro (reads yaw_rate + bias).
    :param speed_mps, speed_var: forward-speed measurement and its variance ((m/s)^2).
    :param fix_xy_m, fix_cov_m2: position fix (K, 2) and its covariance (K, 2, 2).
    """

    t_s: np.ndarray
    yaw_rate_radps: np.ndarray
    yaw_rate_var: np.ndarray
    yaw_rate_biased: np.ndarray
    speed_mps: np.ndarray
    speed_var: np.ndarray
    fix_xy_m: np.ndarray
    fix_cov_m2: np.ndarray


@dataclass
class SmoothedTrack:
    """Filter and smoother output at every event time.

    :param t_s: event times (s).
    :param state: RTS-smoothed states (K, 6) (the filtered ones when smoothing is off).
    :param filtered: forward-filter posteriors (K, 6).
    :param fix_accepted: True where a position fix was used (False where gated out or absent).
    """

    t_s: np.ndarray
    state: np.ndarray
    filtered: np.ndarray
    fix_accepted: np.ndarray


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def ctrv_predict(state: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Propagate one state by `dt_s` with the exact CTRV motion; return (new state, Jacobian F)."""
    x, y, yaw, v, w, b = state.tolist()
    F = np.eye(STATE_SIZE)
    out = state.copy()
    _predict_into(x, y, yaw, v, w, b, dt_s, out, F)
    return out, F


def _predict_into(
    x: float, y: float, yaw: float, v: float, w: float, b: float, dt: float, out: np.ndarray, F: np.ndarray
) -> None:
    # The CTRV displacement is the chord of the arc: length v*dt*sinc(w*dt/2), direction yaw + w*dt/2. Written this
    # way it has no singularity at w = 0, unlike the usual v/w form.
    u = 0.5 * w * dt
    if abs(u) > 1e-4:
        su, cu = math.sin(u), math.cos(u)
        c = su / u
        dc_dw = 0.5 * dt * (cu - c) / u
    else:
        c = 1.0 - u * u / 6.0
        dc_dw = -0.5 * dt * u / 3.0
    a = yaw + u
    ca, sa = math.cos(a), math.sin(a)
    L = v * dt * c
    out[IX] = x + L * ca
    out[IY] = y + L * sa
    out[IYAW] = _wrap(yaw + w * dt)
    out[IV] = v
    out[IW] = w
    out[IB] = b
    F[IX, IYAW] = -L * sa
    F[IY, IYAW] = L * ca
    F[IX, IV] = dt * c * ca
    F[IY, IV] = dt * c * sa
    F[IX, IW] = v * dt * (dc_dw * ca - c * sa * 0.5 * dt)
    F[IY, IW] = v * dt * (dc_dw * sa + c * ca * 0.5 * dt)
    F[IYAW, IW] = dt


def run_filter_smoother(
    meas: Measurements, x0: np.ndarray, P0: np.ndarray, noise: CtrvNoise, smooth: bool = True
) -> SmoothedTrack:
    """Run the EKF forward over every measurement event, then (when `smooth`) the RTS smoother backward.

    The filter predicts from one event time to the next and applies that event's measurements; priors, posteriors
    and Jacobians are kept for the smoother, whose gains are computed for all steps at once.
    """
    K = len(meas.t_s)
    xs_post = np.empty((K, STATE_SIZE))
    xs_prior = np.empty((K, STATE_SIZE))
    Ps_post = np.empty((K, STATE_SIZE, STATE_SIZE))
    Ps_prior = np.empty((K, STATE_SIZE, STATE_SIZE))
    Fs = np.empty((K, STATE_SIZE, STATE_SIZE))
    accepted = np.zeros(K, dtype=bool)

    t_list = meas.t_s.tolist()
    w_list = meas.yaw_rate_radps.tolist()
    wr_list = meas.yaw_rate_var.tolist()
    wb_list = meas.yaw_rate_biased.tolist()
    v_list = meas.speed_mps.tolist()
    vr_list = meas.speed_var.tolist()
    fx_list = meas.fix_xy_m[:, 0].tolist()
    fy_list = meas.fix_xy_m[:, 1].tolist()
    fix_cov = meas.fix_cov_m2

    x = np.array(x0, dtype=float)
    P = np.array(P0, dtype=float)
    t_prev = t_list[0] if K else 0.0
    first_reject_t = math.nan
    Q = np.zeros((STATE_SIZE, STATE_SIZE))
    pred = np.empty(STATE_SIZE)
    eye = np.eye(STATE_SIZE)
    for k in range(K):
        t = t_list[k]
        dt = t - t_prev
        t_prev = t
        F = Fs[k]
        F[...] = eye
        if dt > 0.0:
            x0_, x1_, x2_, x3_, x4_, x5_ = x.tolist()
            _predict_into(x0_, x1_, x2_, x3_, x4_, x5_, dt, pred, F)
            x[:] = pred
            _process_noise_into(Q, dt, noise)
            P = F @ P @ F.T + Q
        xs_prior[k] = x
        Ps_prior[k] = P

        w = w_list[k]
        if w == w:  # not NaN
            biased = wb_list[k]
            Ph = P[:, IW] + P[:, IB] if biased else P[:, IW].copy()
            s = (Ph[IW] + Ph[IB] if biased else Ph[IW]) + wr_list[k]
            gain = Ph / s
            x += gain * (w - (x[IW] + x[IB] if biased else x[IW]))
            P = P - gain[:, None] * Ph
        v = v_list[k]
        if v == v:
            Ph = P[:, IV].copy()
            gain = Ph / (Ph[IV] + vr_list[k])
            x += gain * (v - x[IV])
            P = P - gain[:, None] * Ph
        fx = fx_list[k]
        if fx == fx:
            P, widened, accepted[k], first_reject_t = _fix_update(
                x, P, fx, fy_list[k], fix_cov[k], t, first_reject_t, noise
            )
            if widened is not None:
                Ps_prior[k] = widened
        x[IYAW] = _wrap(x[IYAW])
        P = 0.5 * (P + P.T)
        xs_post[k] = x
        Ps_post[k] = P

    smoothed = rts_smooth(xs_post, Ps_post, xs_prior, Ps_prior, Fs) if smooth else xs_post
    return SmoothedTrack(t_s=np.asarray(meas.t_s, dtype=float), state=smoothed, filtered=xs_post, fix_accepted=accepted)


def _process_noise_into(Q: np.ndarray, dt: float, noise: CtrvNoise) -> None:
    """Fill Q with the process noise of a `dt` step: discretised white-noise acceleration and yaw acceleration (the
    speed-position coupling neglected), the position walk and the gyro bias walk."""
    q_al = noise.yaw_accel_std_radps2**2
    Q[IX, IX] = Q[IY, IY] = noise.position_walk_m_per_sqrt_s**2 * dt
    Q[IV, IV] = noise.accel_std_mps2**2 * dt
    Q[IW, IW] = q_al * dt
    Q[IYAW, IYAW] = q_al * dt**3 / 3.0
    Q[IYAW, IW] = Q[IW, IYAW] = q_al * dt**2 / 2.0
    Q[IB, IB] = noise.gyro_bias_walk_radps_per_sqrt_s**2 * dt


def _fix_update(
    x: np.ndarray,
    P: np.ndarray,
    fx: float,
    fy: float,
    R: np.ndarray,
    t: float,
    first_reject_t: float,
    noise: CtrvNoise,
) -> tuple[np.ndarray, np.ndarray | None, bool, float]:
    """The position fix (fx, fy) with covariance R at time t, gated: updates x in place; returns (P after, the prior
    widened by the innovation when the gate was reset (else None), accepted, the time of the first rejection of the
    current run of rejections (NaN when none))."""
    S = P[:2, :2] + R
    r0, r1 = fx - x[IX], fy - x[IY]
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    i00, i01, i11 = S[1, 1] / det, -S[0, 1] / det, S[0, 0] / det
    d2 = r0 * (i00 * r0 + i01 * r1) + r1 * (i01 * r0 + i11 * r1)
    widened = None
    if d2 > noise.gate_chi2:
        if first_reject_t != first_reject_t:  # NaN: the first rejection of a run
            return P, widened, False, t
        if t - first_reject_t <= noise.gate_reset_s:
            return P, widened, False, first_reject_t
        # The filter, not the receiver, has drifted: widen the position prior by the innovation (as extra process
        # noise at this step, so the smoother sees it too) and take the fix.
        P[IX, IX] += r0 * r0
        P[IY, IY] += r1 * r1
        widened = P.copy()
        S = P[:2, :2] + R
        det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
        i00, i01, i11 = S[1, 1] / det, -S[0, 1] / det, S[0, 0] / det
    PHt = P[:, :2]
    gain = PHt @ np.array([[i00, i01], [i01, i11]])
    x += gain @ np.array([r0, r1])
    return P - gain @ PHt.T, widened, True, math.nan


def rts_smooth(
    x_post: np.ndarray, P_post: np.ndarray, x_prior: np.ndarray, P_prior: np.ndarray, F: np.ndarray
) -> np.ndarray:
    """Rauch–Tung–Striebel smoothed states from the filter's posteriors, priors and Jacobians (F[k]: k-1 -> k)."""
    K = len(x_post)
    if K < 2:
        return x_post.copy()
    # The gains C_k = P_k F_{k+1}^T P_prior_{k+1}^-1 do not depend on the smoothed values: solve them all at once.
    FP = F[1:] @ P_post[:-1]
    C = np.swapaxes(np.linalg.solve(P_prior[1:], FP), -1, -2)
    out = np.empty_like(x_post)
    out[-1] = x_post[-1]
    diff = np.empty(STATE_SIZE)
    for k in range(K - 2, -1, -1):
        np.subtract(out[k + 1], x_prior[k + 1], out=diff)
        diff[IYAW] = _wrap(diff[IYAW])
        out[k] = x_post[k] + C[k] @ diff
        out[k, IYAW] = _wrap(out[k, IYAW])
    return out
