"""The start state and the privileged expert: cars start steering with the road's curve, and the expert's swerves
around the front car neither overshoot the lane nor over-rotate."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest
from sim_worlds import SMALL_VIEW, write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.sim.dynamics import curvature_of_steering


@pytest.fixture(scope="module")
def bend_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("bend") / "world", length_m=220.0, curve_from_m=0.0)


@pytest.fixture(scope="module")
def straight_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("straight") / "world", length_m=260.0, curve_from_m=1e9)


def test_every_car_starts_steering_with_the_road(bend_world: Path) -> None:
    """In a bend of radius 80 m, the ego and the front car start on the bend's curvature, not straight ahead."""
    env = gymnasium.make("drivesim/Overtake-v0", world=str(bend_world), mode="eval", config=SMALL_VIEW)
    u = env.unwrapped
    for seed in range(3):
        env.reset(seed=seed)
        wheelbase_m = u.config.wheelbase_m
        for agent in u.sim.agents:
            assert curvature_of_steering(agent.state.steering_rad, wheelbase_m) == pytest.approx(1.0 / 80.0, rel=1e-6)
    # Driving the lane expert from the lane centre, the ego stays on the bend (a straight start would drift out).
    lane = gymnasium.make(
        "drivesim/Lane-v0", world=str(bend_world), mode="eval",
        config={**SMALL_VIEW, "initial_lateral_m": 0.0, "initial_yaw_rad": 0.0},
    )  # fmt: skip
    lane.reset(seed=0)
    lateral_m = []
    for _ in range(30):
        _, _, terminated, truncated, info = lane.step(lane.unwrapped.expert_action())
        lateral_m.append(info["state"]["q_lat_m"])
        assert not (terminated or truncated)
    assert np.max(np.abs(lateral_m)) < 0.05


def test_expert_swerves_stay_in_the_lane(straight_world: Path) -> None:
    """On a straight road, over 40 starts, no expert episode ends off the lane or over-rotated, and its widest
    swerve keeps 0.3 m inside the lane limit."""
    env = gymnasium.make("drivesim/Overtake-v0", world=str(straight_world), mode="eval", config=SMALL_VIEW)
    u = env.unwrapped
    widest_m, ends = 0.0, []
    for seed in range(40):
        env.reset(seed=seed)
        while True:
            _, _, terminated, truncated, info = env.step(u.expert_action())
            widest_m = max(widest_m, abs(info["state"]["q_lat_m"]))
            if terminated or truncated:
                break
        ends.append(info["termination"])
    assert not any(end["off_lane"] or end["over_rotation"] for end in ends)
    assert widest_m <= u.config.max_lateral_m - 0.3
    assert sum(end["collision"] for end in ends) <= 0.1 * len(ends)
