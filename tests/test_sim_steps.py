"""The per-step timing behind the speed figures: a step counts as car-drawn exactly when the other car changes the
ego's view, and the figures are taken over the steps they name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sim_worlds import SMALL_VIEW, write_test_world

from drivesim.bench.sim_steps import StepTimes, make_env, recording_car_drawn, time_env_steps


@pytest.fixture(scope="module")
def world_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("sim-steps") / "world")


def test_car_drawn_is_where_the_car_changes_the_view(world_dir: Path) -> None:
    """Over overtake evaluation episodes, the recorded flag of each step is True exactly when rendering the same
    request without the other car gives a different image."""
    env = make_env("overtake", str(world_dir), None, "eval", SMALL_VIEW)
    u = env.unwrapped
    env.reset(seed=1)
    flags, changed, episode = [], [], 1
    with recording_car_drawn() as calls:
        for _ in range(80):
            _, _, terminated, truncated, _ = env.step(u.expert_action())
            flags.append(bool(calls[-1][0]))
            frame, x, y, yaw, cars = u.view_request()
            with_car = u.sim.renderer.render([frame], [x], [y], [yaw], [cars]).rgb
            without = u.sim.renderer.render([frame], [x], [y], [yaw], [[]]).rgb
            changed.append(bool((with_car != without).any()))
            if terminated or truncated:
                episode += 1
                env.reset(seed=episode)
    assert flags == changed
    assert 0 < sum(flags) < len(flags), "the test needs steps with and without the car drawn"


def test_time_env_steps_counts_the_car_drawn_steps_it_was_asked_for(world_dir: Path) -> None:
    env = make_env("overtake", str(world_dir), None, "eval", SMALL_VIEW)
    times = time_env_steps(env, steps=10, seed=0, car_drawn_steps=15, max_steps=400)
    assert times.car_drawn.sum() >= 15 and len(times.ms) >= 10
    assert (times.ms > 0).all() and set(times.part_ms) >= {"warp", "raster", "harmonize"}
    # A car-drawn step runs the raster; a step without the car draws nothing (its raster time is the visibility test).
    assert times.part_ms["raster"][times.car_drawn].min() > 0
    lane = time_env_steps(make_env("lane", str(world_dir), None, "train", SMALL_VIEW), steps=12, seed=0)
    assert len(lane.ms) == 12 and lane.car_drawn_share == 0.0 and np.isnan(lane.median_ms(True))


def test_step_times_figures_are_over_the_steps_they_name() -> None:
    times = StepTimes(
        ms=np.array([1.0, 9.0, 2.0, 8.0, 7.0]),
        car_drawn=np.array([False, True, False, True, True]),
        part_ms={"warp": np.array([0.5, 1.0, 0.5, 1.0, 1.0]), "raster": np.array([0.0, 3.0, 0.0, 3.0, 3.0])},
    )
    assert times.median_ms(True) == 8.0 and times.median_ms(False) == 1.5 and times.median_ms() == 7.0
    assert times.car_drawn_share == pytest.approx(0.6)
    parts = times.mean_part_ms(True)
    assert parts["raster"] == 3.0 and parts["total"] == 8.0 and parts["other"] == pytest.approx(4.0)
    summary = times.summary()
    assert summary["car_drawn_steps"] == 3 and summary["median_ms_car_drawn"] == 8.0
