"""The evaluation metrics on hand-made trajectories built with sim/footprint (a sideswipe, a clean pass, a lane
departure, a near miss), and the aggregates' confidence intervals against known values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from eval_fakes import EGO_SIZE_M, lane_departure_record, pass_record

from drivesim.stages.evaluate.metrics import (
    EpisodeRecord,
    aggregate,
    along_track,
    breakdowns,
    clearance_recall,
    difficulty_levels,
    evaluate_episode,
    mean_estimate,
    rate_estimate,
    relative_to_other,
    step_clearances,
)

WIDTH_M = EGO_SIZE_M[1]


def test_clean_pass_keeps_the_lateral_gap_as_clearance():
    lateral = 2.6
    m = evaluate_episode(pass_record(lateral)).metrics
    assert not m.intervention and not m.collision and not m.off_lane and not m.over_rotation
    assert m.success
    # Alongside, both cars are parallel: the gap between their long sides is the offset minus one width.
    assert m.min_clearance_m == pytest.approx(lateral - WIDTH_M, abs=1e-6)
    assert m.max_deviation_m == pytest.approx(lateral, abs=1e-9)
    # Cosine ramp over 12 m of gap: the steepest slope is lateral * pi / (2 * 12), times (v_e - v_f) / v_e = 4/9.
    assert m.max_yaw_rad == pytest.approx(math.atan(lateral * math.pi / 24 * 4 / 9), rel=0.02)


def test_near_miss_is_no_intervention_with_a_small_clearance():
    m = evaluate_episode(pass_record(1.95)).metrics
    assert not m.intervention
    assert m.min_clearance_m == pytest.approx(0.15, abs=1e-6)


def test_sideswipe_is_a_collision_intervention():
    result = evaluate_episode(pass_record(1.5))
    m = result.metrics
    assert m.intervention and m.collision
    assert not m.off_lane and not m.over_rotation and not m.success
    assert m.min_clearance_m == 0.0
    assert result.overlap_m2[-1] > 0 and np.all(result.overlap_m2[:-1] == 0)
    # The episode ended at the first overlap: the ego's side is still < 0.3 m into the front car.
    rel = relative_to_other(result.record)[-1]
    assert rel[0] < 0 and 1.2 < rel[1] < 1.8


def test_overlap_is_found_from_the_polygons_even_when_the_env_flag_is_missing():
    record = pass_record(1.5)
    record.termination["collision"] = False
    assert evaluate_episode(record).metrics.collision


def test_lane_departure_is_an_off_lane_intervention():
    m = evaluate_episode(lane_departure_record(limit_m=2.0)).metrics
    assert m.intervention and m.off_lane and not m.collision
    assert 2.0 < m.max_deviation_m < 2.1
    assert m.max_yaw_rad == pytest.approx(math.atan2(0.6, 8.0))
    assert m.min_clearance_m > 50


def test_limits_alone_flag_off_lane_and_over_rotation():
    record = pass_record(2.6, limits={"max_lateral_m": 2.5, "max_rotation_rad": 0.05})
    m = evaluate_episode(record).metrics
    assert m.off_lane and m.over_rotation and not m.collision and m.intervention and not m.success


def test_record_json_round_trip_keeps_the_metrics():
    record = pass_record(2.0)
    back = EpisodeRecord.from_json(record.to_json())
    a, b = evaluate_episode(record).metrics, evaluate_episode(back).metrics
    assert b.min_clearance_m == pytest.approx(a.min_clearance_m, abs=2e-5)
    assert b.max_deviation_m == pytest.approx(a.max_deviation_m, abs=1e-5)
    assert np.isnan(back.trajectory["tracking_error_m"]).all()


def test_wilson_interval_matches_the_textbook_values():
    est = rate_estimate([True] + [False] * 9)
    assert est.value == pytest.approx(0.1)
    # Wilson 95 % for 1/10: [0.0179, 0.4042].
    assert est.ci_low == pytest.approx(0.0179, abs=1e-3)
    assert est.ci_high == pytest.approx(0.4042, abs=1e-3)
    zero = rate_estimate([False] * 50)
    assert zero.value == 0 and zero.ci_low == 0 and 0.05 < zero.ci_high < 0.08


def test_bootstrap_interval_covers_the_mean_and_is_reproducible():
    values = np.random.default_rng(3).normal(0.3, 0.1, 400)
    a, b = mean_estimate(values), mean_estimate(values)
    assert a == b
    half = 1.96 * values.std(ddof=1) / math.sqrt(values.size)
    assert a.ci_low < a.value < a.ci_high
    assert (a.ci_high - a.ci_low) == pytest.approx(2 * half, rel=0.15)
    assert math.isnan(mean_estimate([float("nan")]).value)


def test_aggregate_counts_each_cause_and_averages_clearance_over_all_episodes():
    records = [pass_record(2.6, seed=0), pass_record(1.95, seed=1), pass_record(1.5, seed=2), lane_departure_record(3)]
    metrics = [evaluate_episode(r).metrics for r in records]
    agg = aggregate(metrics)
    assert agg["intervention"].value == pytest.approx(0.5)
    assert agg["collision"].value == pytest.approx(0.25)
    assert agg["off_lane"].value == pytest.approx(0.25)
    # The headline over all trials (the sideswipe's 0 included); without it, labelled, as the second figure.
    far = metrics[3].min_clearance_m
    assert agg["min_clearance_m"].value == pytest.approx((0.8 + 0.0 + 0.15 + far) / 4, abs=1e-5)
    assert agg["min_clearance_no_collision_m"].value == pytest.approx((0.8 + 0.15 + far) / 3, abs=1e-5)
    assert agg["min_clearance_m"].n == 4 and agg["min_clearance_no_collision_m"].n == 3


def test_breakdown_levels_follow_the_quartiles_and_the_direction():
    values = np.arange(8.0)
    up, edges = difficulty_levels(values, harder_when_larger=True)
    assert up.tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
    assert edges == pytest.approx([1.75, 3.5, 5.25])
    down, _ = difficulty_levels(values, harder_when_larger=False)
    assert down.tolist() == [3, 3, 2, 2, 1, 1, 0, 0]
    levels, _ = difficulty_levels(np.array([1.0, np.nan]), True)
    assert levels[1] == -1


def test_breakdown_puts_interventions_where_the_front_car_is_fast():
    records = []
    for i in range(16):
        r = pass_record(1.5 if i >= 12 else 2.6, seed=i)
        r.episode["other_speed_mps"] = float(i)
        r.episode["initial_lateral_m"] = (-1.0) ** i * (1.0 + i / 16)
        records.append(r)
    metrics = [evaluate_episode(r).metrics for r in records]
    by_factor = {b.factor: b for b in breakdowns(metrics)}
    speed = by_factor["front_car_speed"]
    assert [e.value for e in speed.intervention] == [0.0, 0.0, 0.0, 1.0]
    assert [e.n for e in speed.intervention] == [4, 4, 4, 4]
    # Larger |initial lateral| is easier: the last (fast, crashing) episodes have the largest, so level easy.
    lateral = by_factor["initial_lateral"]
    assert lateral.intervention[0].value == 1.0 and lateral.intervention[3].value == 0.0


def test_along_track_rates_and_deviation():
    clean, swipe = evaluate_episode(pass_record(2.6, seed=0)), evaluate_episode(pass_record(1.5, seed=1))
    track = along_track([clean, swipe], frame_count=200)
    last_swipe_frame = int(swipe.record.trajectory["frame_index"][-1])
    assert track["intervention_rate"][0] == pytest.approx(0.5)  # both start at frame 0
    assert track["visits"][last_swipe_frame + 2] == 1 and track["intervention_rate"][last_swipe_frame + 2] == 0.0
    assert np.isnan(track["intervention_rate"][150]) and track["visits"][150] == 0
    assert track["deviation_m"][0] == pytest.approx(0.0)


def test_clearance_histogram_data_and_recall():
    results = [evaluate_episode(pass_record(lat, seed=i)) for i, lat in enumerate((2.6, 1.95, 1.5))]
    steps = step_clearances(results, below_m=2.0)
    assert steps.size > 0 and steps.max() < 2.0 and steps.min() == 0.0
    mins = np.array([r.metrics.min_clearance_m for r in results])
    recall = clearance_recall(mins, np.array([0.0, 0.1, 0.5, 1.0]))
    assert recall.tolist() == pytest.approx([1 / 3, 1 / 3, 2 / 3, 1.0])


def test_scenario_table_splits_static_moving_and_the_passing_side():
    from dataclasses import replace

    from drivesim.stages.evaluate.metrics import scenario_table

    base = evaluate_episode(pass_record(2.6, seed=0)).metrics
    metrics = [
        replace(base, seed=0, other_speed_mps=0.0, other_lateral_m=-1.5, success=True, intervention=False),
        replace(base, seed=1, other_speed_mps=3.0, other_lateral_m=-1.2, success=False, intervention=True),
        replace(base, seed=2, other_speed_mps=2.0, other_lateral_m=1.4, success=True, intervention=False),
    ]
    rows = {r["scenario"]: r for r in scenario_table(metrics)}
    static = rows["front car nearly static (< 0.5 m/s)"]
    assert static["episodes"] == 1 and static["success"]["value"] == 1.0
    assert rows["front car moving"]["episodes"] == 2 and rows["front car moving"]["intervention"]["value"] == 0.5
    assert rows["passing on the left"]["episodes"] == 2  # the front car right of the lane centre
    assert rows["passing on the right"]["episodes"] == 1
    lane_only = replace(base, other_speed_mps=float("nan"), other_lateral_m=float("nan"))
    assert scenario_table([lane_only]) == []


def test_eval_scenarios_become_env_settings():
    from drivesim.stages.evaluate.config import EvalConfig

    cfg = EvalConfig.model_validate({"scenario": ["static", "pass-left"], "env": {"episode_steps": 50}})
    assert cfg.env_overrides() == {"episode_steps": 50, "other_speed_mps": (0.0, 0.0), "front_side": "right"}
    with pytest.raises(ValueError, match="exclude each other"):
        EvalConfig.model_validate({"scenario": ["pass-left", "pass-right"]})
