"""Pure pursuit onto offset paths generated from the road."""

from __future__ import annotations

import numpy as np
import pytest

from drivesim.sim.agents import Agent, LateralProfile, ReferencePath, pursue_profile, track_arc
from drivesim.sim.dynamics import BicycleState, rk3_step, steering_for_curvature, steering_rate_command


def _road() -> ReferencePath:
    arc = np.arange(0.0, 300.0, 1.0)
    curvature = np.where(arc > 100.0, 0.01, 0.0)
    yaw = np.concatenate([[0.0], np.cumsum(curvature[:-1])])
    x = np.concatenate([[0.0], np.cumsum(np.cos(yaw[:-1]))])
    y = np.concatenate([[0.0], np.cumsum(np.sin(yaw[:-1]))])
    return ReferencePath({"arc_length_m": arc, "x_m": x, "y_m": y, "yaw_rad": yaw, "curvature_1pm": curvature})


@pytest.mark.parametrize("offset_m", [1.5, -2.0])
def test_pure_pursuit_converges_onto_an_offset_path(offset_m: float) -> None:
    """Starting on the lane centre, gain 0.8 / lookahead 5 m settles within 0.1 m of the offset on the straight."""
    road = _road()
    agent = Agent(BicycleState(0.0, 0.0, 0.0, 0.0, 6.0), 4.5, 1.9, 6.0, LateralProfile.constant(offset_m))
    arc, lateral = 0.0, 0.0
    for _ in range(130):  # 13 s, about 78 m: still on the straight
        kappa = pursue_profile(agent, road, arc)
        target = steering_for_curvature(kappa, 2.7)
        rate = steering_rate_command(agent.state.steering_rad, target, 1.0, 0.1)
        agent.state = rk3_step(agent.state, rate, 0.0, 0.1, 2.7)
        arc, lateral = track_arc(road, agent.state.x_m, agent.state.y_m, arc)
    assert lateral == pytest.approx(offset_m, abs=0.1)


def test_lane_changes_move_between_the_offsets() -> None:
    """A follow profile changes lanes at random places between the given offsets, with ramps."""
    profile = LateralProfile.lane_changes(np.random.default_rng(0), 0.0, 300.0, (1.5, 0.0, -1.5), 1.5)
    values = np.array([profile(s) for s in np.arange(0.0, 300.0, 1.0)])
    assert values[0] == 1.5 and len(np.unique(np.round(values, 6))) > 3
    assert set(np.round(profile.offset_m, 6)) <= {1.5, 0.0, -1.5}
