"""Overtake starts that can be won (sim/envs/winnable.py): the physical bound on hand-made starts, the env's label and
its redraw option on the small test world, and the evaluation's table of the two groups apart."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium
import pytest
from eval_fakes import pass_record
from sim_worlds import SMALL_VIEW, write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.sim.envs.winnable import OvertakeStart, SteeringLimits, is_winnable, pass_fits, time_to_contact_s
from drivesim.stages.evaluate.metrics import evaluate_episode, winnable_table

LIMITS = SteeringLimits(wheelbase_m=2.7, max_curvature_1pm=0.15, max_steering_rate_radps=1.0, max_rotation_rad=0.5,
                        max_lateral_m=2.5)  # fmt: skip


def _start(gap_m: float, ego_mps: float, other_mps: float, other_lateral_m: float, **kw: float) -> OvertakeStart:
    base = {"ego_lateral_m": 0.0, "ego_yaw_rad": 0.0, "ego_length_m": 4.5, "ego_width_m": 1.9}
    base.update(other_length_m=4.5, other_width_m=1.8)
    return OvertakeStart(gap_m, ego_mps, other_mps, other_lateral_m=other_lateral_m, **{**base, **kw})


def test_a_pass_must_fit_in_the_road_and_time_left() -> None:
    """Not closing, the ego never gets past; closing at 1 m/s on 15 m of gap plus 6 m to pass takes 21 s, 105 m of
    road at 5 m/s: unwinnable with 100 m of road or 20 s left, winnable with 110 m and 25 s."""
    assert not pass_fits(_start(15.0, 3.0, 3.0, 1.0)) and not is_winnable(_start(15.0, 3.0, 3.0, 1.0), LIMITS)
    slow = {"pass_distance_m": 6.0, "road_left_m": 110.0, "time_left_s": 25.0}
    assert pass_fits(_start(15.0, 5.0, 4.0, 1.5, **slow)) and is_winnable(_start(15.0, 5.0, 4.0, 1.5, **slow), LIMITS)
    assert not is_winnable(_start(15.0, 5.0, 4.0, 1.5, **{**slow, "road_left_m": 100.0}), LIMITS)
    assert not is_winnable(_start(15.0, 5.0, 4.0, 1.5, **{**slow, "time_left_s": 20.0}), LIMITS)


def test_the_bound_on_hand_made_starts() -> None:
    # 2 m of bumper gap closing at 8 m/s: 0.25 s, far too little to swerve the 0.85 m it needs.
    close = _start(6.5, 9.0, 1.0, 1.0)
    assert time_to_contact_s(close) == pytest.approx(0.25) and not is_winnable(close, LIMITS)
    # The same cars 15 m apart: over a second to swerve; not closing: never in contact; already beside: clear.
    assert is_winnable(_start(15.0, 9.0, 1.0, 1.0), LIMITS)
    assert time_to_contact_s(_start(6.5, 3.0, 3.0, 1.0)) == math.inf
    assert is_winnable(_start(6.5, 9.0, 1.0, 2.0, ego_lateral_m=-0.2), LIMITS)
    # A car on the lane centre, 15 m ahead: clear on either side of a normal lane, on neither of a narrow one (the
    # ego's centre would leave the lane before its footprint is beside the car's).
    narrow = SteeringLimits(2.7, 0.15, 1.0, 0.5, max_lateral_m=1.0)
    assert is_winnable(_start(15.0, 9.0, 1.0, 0.0), LIMITS) and not is_winnable(_start(15.0, 9.0, 1.0, 0.0), narrow)


@pytest.fixture(scope="module")
def world_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("winnable-world") / "world")


def _env(world_dir: Path, **config: object) -> gymnasium.Env:
    overrides = {**SMALL_VIEW, "front_distance_m": (6.0, 8.0), "other_speed_mps": (0.0, 1.0), **config}
    return gymnasium.make("drivesim/Overtake-v0", world=str(world_dir), meshes=None, mode="eval", config=overrides)


def test_the_env_labels_each_start_and_can_redraw_the_unwinnable(world_dir: Path) -> None:
    """Close, fast starts (front car 6-8 m ahead, ego 4-10 m/s against 0-1 m/s): many cannot be won."""
    env = _env(world_dir)
    labels = {seed: env.reset(seed=seed)[1]["episode"]["winnable"] for seed in range(40)}
    assert 5 <= sum(not w for w in labels.values()) <= 35, labels
    redrawing = _env(world_dir, redraw_unwinnable=True)
    for seed, was in labels.items():
        episode = redrawing.reset(seed=seed)[1]["episode"]
        assert episode["winnable"] and episode["seed"] == seed
        assert ("redraws" in episode) == (not was)  # a winnable start is kept as it was drawn
    again = [redrawing.reset(seed=3)[1]["episode"] for _ in range(2)]
    assert again[0] == again[1]  # the same seed, the same (redrawn) episode
    first = env.reset(seed=next(s for s, w in labels.items() if w))[1]["episode"]
    kept = redrawing.reset(seed=first["seed"])[1]["episode"]
    assert kept == first


def test_the_expert_fails_most_labelled_starts_and_rarely_the_others(world_dir: Path) -> None:
    """The label checked with the privileged expert on the close, fast starts (stepped without rendering)."""
    env = _env(world_dir).unwrapped
    failed: dict[bool, list[bool]] = {True: [], False: []}
    for seed in range(40):
        env.reset_state(seed)
        winnable = env._episode["winnable"]
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            if terminated or truncated:
                break
        failed[winnable].append(not info["success"])
    assert sum(failed[False]) >= 2 / 3 * len(failed[False]) and sum(failed[True]) <= 0.1 * len(failed[True])


def test_evaluation_reports_the_two_groups_apart() -> None:
    records = [pass_record(3.0, seed=s) for s in range(3)] + [pass_record(0.4, seed=s) for s in (3, 4)]
    for record in records:
        record.episode["winnable"] = record.seed < 4  # seed 3 crashes on a winnable start, seed 4 on an unwinnable
    table = winnable_table([evaluate_episode(r).metrics for r in records])
    assert [(row["starts"], row["episodes"]) for row in table] == [("winnable starts", 4), ("unwinnable starts", 1)]
    assert table[0]["success"]["value"] == 0.75 and table[1]["collision"]["value"] == 1.0
    assert table[1]["share"] == 0.2
    unlabelled = [evaluate_episode(pass_record(3.0, seed=s)).metrics for s in range(2)]
    assert winnable_table(unlabelled) == [] and unlabelled[0].winnable is None


def test_a_swerve_to_the_inside_of_a_tight_bend_has_no_steering_to_spare() -> None:
    """A car 1.5 m to the right, 12 m ahead: on a straight road either swerve clears it; in a left bend of radius
    6 m (the steering's limit is 6.7 m here) the ego cannot swerve further left than the bend already turns it, and
    the outside is the car's side; in a gentle bend (radius 100 m) it still can."""
    start = {"gap_m": 12.0, "ego_mps": 8.0, "other_mps": 2.0, "other_lateral_m": -1.5}
    assert is_winnable(_start(**start), LIMITS)
    assert not is_winnable(_start(**start, road_curvature_1pm=1.0 / 6.0), LIMITS)
    assert is_winnable(_start(**start, road_curvature_1pm=0.01), LIMITS)
