"""Kinematic bicycle with RK3: exact circular arcs, the steering-rate limit."""

from __future__ import annotations

import math

import pytest

from drivesim.sim.dynamics import BicycleState, rk3_step, steering_for_curvature, steering_rate_command

WHEELBASE_M = 2.7


def test_rk3_follows_the_exact_circular_arc() -> None:
    """Constant steering and speed drive a circle of radius L / tan δ; 10 s at 0.1 s stays within 1 mm of it."""
    curvature = 0.05
    state = BicycleState(0.0, 0.0, 0.0, steering_for_curvature(curvature, WHEELBASE_M), 8.0)
    for _ in range(100):
        state = rk3_step(state, 0.0, 0.0, 0.1, WHEELBASE_M)
    heading = curvature * 8.0 * 10.0
    exact_x, exact_y = math.sin(heading) / curvature, (1.0 - math.cos(heading)) / curvature
    assert math.hypot(state.x_m - exact_x, state.y_m - exact_y) < 1e-3
    assert state.yaw_rad == pytest.approx(heading, abs=1e-6)


def test_rk3_is_third_order() -> None:
    """Halving the step divides the position error by 8 or more (an Euler step would only halve it)."""

    def error(dt: float) -> float:
        state = BicycleState(0.0, 0.0, 0.0, 0.4, 10.0)
        for _ in range(round(2.0 / dt)):
            state = rk3_step(state, 0.0, 0.0, dt, WHEELBASE_M)
        k = math.tan(0.4) / WHEELBASE_M
        h = k * 20.0
        return math.hypot(state.x_m - math.sin(h) / k, state.y_m - (1 - math.cos(h)) / k)

    assert error(0.2) / error(0.1) > 7.0
    assert error(0.1) < 1e-5


def test_steering_rate_limit() -> None:
    """A full-lock command is reached at the rate limit, never faster; a small one in one step."""
    rate = steering_rate_command(0.0, 0.5, 1.0, 0.1)
    assert rate == pytest.approx(1.0)
    state = BicycleState(0.0, 0.0, 0.0, 0.0, 5.0)
    for _ in range(3):
        state = rk3_step(state, steering_rate_command(state.steering_rad, 0.5, 1.0, 0.1), 0.0, 0.1, WHEELBASE_M)
    assert state.steering_rad == pytest.approx(0.3, abs=1e-9)
    assert steering_rate_command(0.3, 0.32, 1.0, 0.1) == pytest.approx(0.2)
