"""`drivesim run`'s budget for the whole chain: training stops at what the stages before it left, the learning rates
anneal over that, and the run stays the chain's run (a re-run finds it fresh)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from drivesim.chain.budget import ChainBudget, chain_budget
from drivesim.chain.run import load_run_preset
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.run import effective_time_limit_s
from drivesim.stages.train.stage import run_training

SMALL = [
    "envs.source=cost_free",
    "envs.count=2",
    "ppo.buffer_steps=128",
    "ppo.minibatch_steps=64",
    "ppo.epochs=1",
    "eval.every_steps=0",
    "envs.config.episode_steps=40",
    "envs.vec_env=dummy",
    "warm_start.method=none",
]


def test_training_gets_what_the_stages_before_it_left_and_at_least_its_minimum() -> None:
    budget = ChainBudget(budget_s=3600.0, after_training_s=420.0, min_training_s=600.0)
    # 20 min of depth and world building: training stops 3600 - 420 s after the chain's start, 53 min later.
    assert budget.training_stop_by(began=100.0, now=1300.0) == pytest.approx(100.0 + 3180.0)
    # 55 min before training: the minimum is given, and the chain overruns its hour.
    assert budget.training_stop_by(began=100.0, now=100.0 + 3300.0) == pytest.approx(100.0 + 3300.0 + 600.0)
    assert ChainBudget().training_stop_by(began=0.0, now=5.0) is None  # no budget: the stages' own limits


def test_the_deadline_shortens_the_time_limit_never_lengthens_it() -> None:
    now = time.monotonic()
    assert effective_time_limit_s(3600.0, 0.0, None) == 3600.0
    assert effective_time_limit_s(3600.0, 120.0, now + 600.0) == pytest.approx(720.0, abs=1.0)  # warm start counted
    assert effective_time_limit_s(300.0, 0.0, now + 600.0) == 300.0
    assert effective_time_limit_s(None, 0.0, now + 60.0) == pytest.approx(60.0, abs=1.0)
    assert effective_time_limit_s(3600.0, 50.0, now - 10.0) == pytest.approx(50.0)  # past the deadline: stop now


def test_a_bad_chain_budget_is_one_line(tmp_path: Path) -> None:
    assert chain_budget(load_run_preset("recording")).budget_s == 3600.0
    with pytest.raises(ConfigError, match="chain: unknown config key 'budget_min'"):
        chain_budget({"chain": {"budget_min": 60}})
    with pytest.raises(ConfigError, match="chain"):
        chain_budget(load_run_preset("recording", overrides=["chain.budget_s=-5"]))


def test_a_run_given_a_deadline_takes_its_time_limit_from_it_and_stops_there(tmp_path: Path) -> None:
    cfg = load_config(TrainConfig, preset="train/lane", overrides=[*SMALL, "total_steps=512"])
    assert cfg.time_limit_s is None
    far = run_training(Workspace(tmp_path / "far"), cfg, stop_by=time.monotonic() + 600.0)
    assert far.summary.steps == 512  # ends by its steps, long before the deadline
    assert far.summary.time_limit_s is not None and 300.0 < far.summary.time_limit_s <= 600.0  # less the setup
    config = (far.path / "config.json").read_text()
    assert '"time_limit_s": null' in config  # the deadline is not the run's config: a re-run finds the run fresh

    past = run_training(Workspace(tmp_path / "past"), cfg, stop_by=time.monotonic() - 1.0)
    assert past.summary.time_limit_s == 0.0 and past.summary.steps < 512  # stopped at its first step
    assert (past.path / "policy.pt").is_file()  # and finished like any run that used its time
