"""Kinematic bicycle model `[x, y, φ, δ, v]` (paper eq. 1) integrated with third-order Runge–Kutta.

    ẋ = v cos φ,  ẏ = v sin φ,  φ̇ = v tan(δ) / L,  δ̇ = u_δ,  v̇ = u_a

x, y in metres (world frame), φ yaw in radians, δ front-wheel steering angle in radians, v speed in m/s, L the
wheelbase in metres, u_δ the steering rate in rad/s and u_a the acceleration in m/s². The policy commands a bounded
path curvature; `steering_rate_command` turns it into the u_δ that tracks it under a steering-rate limit.
Plain Python floats throughout: one agent's step is a few microseconds, numpy would be slower for scalars.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class BicycleState:
    """One vehicle's state: position (m), yaw (rad), steering angle (rad), speed (m/s)."""

    x_m: float
    y_m: float
    yaw_rad: float
    steering_rad: float = 0.0
    speed_mps: float = 0.0


def _derivative(
    yaw: float, steer: float, speed: float, u_steer: float, u_accel: float, wheelbase_m: float
) -> tuple[float, float, float, float, float]:
    return (
        speed * math.cos(yaw),
        speed * math.sin(yaw),
        speed * math.tan(steer) / wheelbase_m,
        u_steer,
        u_accel,
    )


def rk3_step(
    state: BicycleState, u_steer_radps: float, u_accel_mps2: float, dt_s: float, wheelbase_m: float
) -> BicycleState:
    """The state after `dt_s` with constant inputs, by Kutta's third-order Runge–Kutta scheme."""
    s0 = (state.x_m, state.y_m, state.yaw_rad, state.steering_rad, state.speed_mps)
    k1 = _derivative(s0[2], s0[3], s0[4], u_steer_radps, u_accel_mps2, wheelbase_m)
    s1 = [a + 0.5 * dt_s * b for a, b in zip(s0, k1, strict=True)]
    k2 = _derivative(s1[2], s1[3], s1[4], u_steer_radps, u_accel_mps2, wheelbase_m)
    s2 = [a - dt_s * b + 2.0 * dt_s * c for a, b, c in zip(s0, k1, k2, strict=True)]
    k3 = _derivative(s2[2], s2[3], s2[4], u_steer_radps, u_accel_mps2, wheelbase_m)
    out = [a + dt_s / 6.0 * (b + 4.0 * c + d) for a, b, c, d in zip(s0, k1, k2, k3, strict=True)]
    return BicycleState(out[0], out[1], out[2], out[3], max(0.0, out[4]))


def steering_for_curvature(curvature_1pm: float, wheelbase_m: float) -> float:
    """The steering angle (rad) whose circle has the given curvature (1/m, + = left)."""
    return math.atan(curvature_1pm * wheelbase_m)


def curvature_of_steering(steering_rad: float, wheelbase_m: float) -> float:
    """The path curvature (1/m) of a steering angle."""
    return math.tan(steering_rad) / wheelbase_m


def steering_rate_command(steering_rad: float, target_rad: float, max_rate_radps: float, dt_s: float) -> float:
    """u_δ (rad/s) that reaches `target_rad` within `dt_s` if the rate limit allows, else the limit toward it."""
    rate = (target_rad - steering_rad) / dt_s
    return max(-max_rate_radps, min(max_rate_radps, rate))
