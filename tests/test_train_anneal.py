"""The learning rates annealed over the run's budget (`ppo.learning_rate_end_fraction`): by env steps or by the
clock, for PPO and for the update phases, and in a real run's progress.csv."""

from __future__ import annotations

import csv
from types import SimpleNamespace

import pytest
import torch

from drivesim.pipeline.config import load_config
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.train.anneal import anneal_learning_rates, budget_spent, learning_rate_factor
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.stage import run_training

SMALL = [
    "envs.source=cost_free",
    "envs.count=2",
    "ppo.buffer_steps=256",
    "ppo.minibatch_steps=128",
    "ppo.epochs=1",
    "eval.every_steps=0",
    "envs.config.episode_steps=40",
    "policy.sequence_length_steps=16",
    "envs.vec_env=dummy",
]


def test_budget_spent_is_the_further_of_steps_and_time() -> None:
    assert budget_spent(250, 1000, 10.0, 100.0) == pytest.approx(0.25)
    assert budget_spent(250, 1000, 60.0, 100.0) == pytest.approx(0.6)  # the clock runs out first
    assert budget_spent(250, 1000, 60.0, None) == pytest.approx(0.25)
    assert budget_spent(5000, 1000, 0.0, None) == 1.0
    assert learning_rate_factor(0.0, 0.1) == 1.0
    assert learning_rate_factor(0.5, 0.1) == pytest.approx(0.55)
    assert learning_rate_factor(1.0, 0.1) == pytest.approx(0.1)


def _fake_model(phase_rate: float) -> SimpleNamespace:
    phase = SimpleNamespace(optimizer=torch.optim.SGD([torch.nn.Parameter(torch.zeros(2))], lr=phase_rate))
    return SimpleNamespace(num_timesteps=0, update_hooks=[phase], lr_schedule=lambda _: 3e-4, phase=phase)


def test_ppo_and_phase_rates_follow_the_budget() -> None:
    cfg = load_config(TrainConfig, preset="train/lane", overrides=[*SMALL, "total_steps=1000", "time_limit_s=100"])
    cfg = cfg.model_copy(update={"ppo": cfg.ppo.model_copy(update={"learning_rate_end_fraction": 0.0})})
    model, clock = _fake_model(1e-3), {"s": 0.0}
    anneal_learning_rates(model, cfg, lambda: clock["s"])
    model.num_timesteps = 500
    assert model.lr_schedule(1.0) == pytest.approx(cfg.ppo.learning_rate * 0.5)
    clock["s"] = 75.0  # three quarters of the time limit: the clock leads
    model.update_hooks[0]()
    assert model.phase.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * 0.25)
    assert model.lr_schedule(1.0) == pytest.approx(cfg.ppo.learning_rate * 0.25)


def test_a_shorter_time_limit_given_to_the_run_sets_the_pace() -> None:
    """`drivesim run`'s budget can leave less than the config's time limit: the rates fall over what it left."""
    cfg = load_config(TrainConfig, preset="train/lane", overrides=[*SMALL, "total_steps=1000000", "time_limit_s=100"])
    cfg = cfg.model_copy(update={"ppo": cfg.ppo.model_copy(update={"learning_rate_end_fraction": 0.0})})
    model = _fake_model(1e-3)
    anneal_learning_rates(model, cfg, lambda: 25.0, time_limit_s=50.0)
    assert model.lr_schedule(1.0) == pytest.approx(cfg.ppo.learning_rate * 0.5)  # half of 50 s, not a quarter of 100


def test_end_fraction_one_changes_nothing() -> None:
    cfg = load_config(TrainConfig, preset="train/lane", overrides=[*SMALL, "total_steps=1000"])
    model = _fake_model(1e-3)
    schedule, hooks = model.lr_schedule, list(model.update_hooks)
    anneal_learning_rates(model, cfg, lambda: 0.0)
    assert model.lr_schedule is schedule and model.update_hooks == hooks


def test_a_run_logs_its_falling_learning_rate(tmp_path) -> None:
    """Four updates of 256 steps over a 1024-step budget annealed to zero: PPO's rate at each update is the start's
    times the share of the budget left when it began."""
    overrides = [*SMALL, "total_steps=1024", "ppo.learning_rate_end_fraction=0.0"]
    result = run_training(Workspace(tmp_path), load_config(TrainConfig, preset="train/lane", overrides=overrides))
    with open(result.path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    rates = [float(r["train_learning_rate"]) for r in rows]
    start = TrainConfig().ppo.learning_rate
    assert rates == pytest.approx([start * (1 - int(r["steps"]) / 1024) for r in rows], rel=1e-6)
    assert rates[0] > rates[-1] and rates[-1] == pytest.approx(0.0, abs=1e-12)
