"""The imitation regularizer: expert labels aligned with PPO's rollout states, and cloning that fits them."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv
from test_train import small_config, small_ppo

from drivesim.pipeline.workspace import Workspace
from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.imitation import ExpertLabels, ImitationRegularizer
from drivesim.stages.train.stage import run_training

SHAPE = (3, 16, 40)


class CounterEnv(CostFreeDrivingEnv):
    """The image's brightness is the step within the episode; the expert's label is that step / 100."""

    def _obs(self) -> np.ndarray:
        return np.full(SHAPE, self.steps * 5, np.uint8)

    def expert_action(self) -> np.ndarray:
        return np.array([self.steps / 100.0], np.float32)


def test_labels_belong_to_the_states_ppo_acted_in_and_cloning_fits_them():
    torch.manual_seed(0)
    venv = DummyVecEnv([lambda: CounterEnv(observation_shape=SHAPE, episode_steps=37) for _ in range(2)])
    labelled = ExpertLabels(venv, steps=64)
    model = small_ppo(labelled, [(8, 3, 2), (16, 3, 1)], 1)
    regularizer = ImitationRegularizer(model, labelled, epochs=20, learning_rate=3e-3, seed=0)
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    losses: list[float] = []

    def check() -> None:
        buffer = model.rollout_buffer
        seen.append((buffer.observations[:, :, 0, 0, 0].copy(), np.stack(list(labelled.labels))[:, :, 0]))
        regularizer()
        losses.append(model.logger.name_to_value["train/imitation_loss"])

    model.update_hooks.append(check)
    model.learn(64 * 2 * 4)
    assert len(seen) == 4
    for brightness, labels in seen:  # episodes of 37 steps end inside the 64-step rollouts: resets included
        np.testing.assert_allclose(labels, brightness / 5 / 100, atol=1e-6)
        assert (brightness == 0).sum() >= 2  # an episode start in each env's rollout
    # the steering's negative log-likelihood with its std e^-1 held fixed: a perfect fit gives -0.081, a constant
    # steering at the labels' mean (0.18, rms error 0.1) about -0.044; the cloning gets within 0.055 rms of the labels
    assert losses[-1] < min(losses[0], -0.07), losses
    assert "imitation" in model.time_s


@pytest.mark.parametrize("setting, name", [("imitation.epochs=1", "imitation"), ("lane_aux.epochs=1", "lane_aux")])
def test_a_run_with_an_update_phase_logs_its_loss_and_time(tmp_path, setting, name):
    """The phases after each PPO update (the imitation regularizer, the encoder's lane target) log their loss and
    time in progress.csv."""
    cfg = small_config(512, [setting, "eval.every_steps=0"])
    run = run_training(Workspace(tmp_path / "ws"), cfg).path
    rows = list(csv.DictReader((run / "progress.csv").open()))
    assert len(rows) == 2
    assert all(math.isfinite(float(row[f"loss_{name}_loss"])) for row in rows)
    assert float(rows[-1][f"time_{name}_s"]) > 0
