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
from drivesim.stages.train.imitation import ChunkData, ExpertLabels, ImitationRegularizer, LabelHistory
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


def _chunks(first: int, count: int, length: int = 4, hidden: int = 8) -> ChunkData:
    """`count` chunks whose every value is its chunk number, counting from `first`."""
    ids = np.arange(first, first + count, dtype=np.float32)
    return ChunkData(
        np.broadcast_to(ids[:, None, None, None, None], (count, length, *SHAPE)).astype(np.uint8),
        np.broadcast_to(ids[:, None], (count, length)).copy(),
        np.broadcast_to(ids[:, None, None], (count, length, 1)).copy(),
        np.broadcast_to(ids[:, None, None], (count, 1, hidden)).copy(),
        np.broadcast_to(ids[:, None, None], (count, 1, hidden)).copy(),
    )


def test_the_label_history_keeps_the_newest_chunks_and_drops_the_oldest():
    history = LabelHistory(capacity_steps=10 * 4 + 3, sequence_length=4)  # 10 whole chunks
    history.add(_chunks(0, 6))
    assert len(history) == 6
    history.add(_chunks(6, 7))  # 13 chunks seen: 0-2 dropped
    kept = history.data()
    assert len(history) == 10
    assert sorted(kept.labels[:, 0, 0].tolist()) == list(range(3, 13))
    for field in (kept.obs, kept.starts, kept.h, kept.c):  # every field of a slot belongs to the same chunk
        np.testing.assert_array_equal(field.reshape(10, -1).min(axis=1), kept.labels[:, 0, 0])
        np.testing.assert_array_equal(field.reshape(10, -1).max(axis=1), kept.labels[:, 0, 0])
    history.add(_chunks(100, 25))  # more than it holds: the last 10
    assert sorted(history.data().labels[:, 0, 0].tolist()) == list(range(115, 125))


def test_with_a_history_the_regularizer_fits_past_rollouts_too():
    torch.manual_seed(0)
    venv = DummyVecEnv([lambda: CounterEnv(observation_shape=SHAPE, episode_steps=37) for _ in range(2)])
    labelled = ExpertLabels(venv, steps=64)
    model = small_ppo(labelled, [(8, 3, 2), (16, 3, 1)], 1)
    regularizer = ImitationRegularizer(model, labelled, epochs=2, learning_rate=3e-3, seed=0, history_steps=3 * 128)
    regularizer.remember(
        _chunks(200, 2, model.sequence_length, model.policy.lstm_actor.hidden_size)
    )  # as the warm start hands its data over
    kept: list[int] = []

    def fit() -> None:
        regularizer()
        kept.append(len(regularizer.history) * model.sequence_length)
        stored = regularizer.history.data()
        assert stored.obs.dtype == np.uint8
        # the states' labels stay theirs: brightness = step * 5, label = step / 100 (the warm start's: chunk number)
        own = stored.labels[:, 0, 0] < 100
        np.testing.assert_allclose(stored.labels[own, :, 0], stored.obs[own, :, 0, 0, 0] / 5 / 100, atol=1e-6)

    model.update_hooks.append(fit)
    model.learn(64 * 2 * 4)
    steps = 2 * model.sequence_length
    assert kept == [steps + 128, steps + 256, 384, 384]  # a rollout is 128 labelled states; 384 kept at most


def test_a_run_hands_the_warm_starts_labels_to_the_regularizers_history(tmp_path):
    """With a history, the first update's cloning already draws from the warm start's labelled states."""
    warm = ["warm_start.method=expert", "warm_start.iterations=1", "warm_start.steps_per_iteration=256"]
    fits = ["imitation.epochs=1", "imitation.history_steps=640", "warm_start.value_fit_steps=64"]
    cfg = small_config(512, [*warm, *fits, "eval.every_steps=0"])
    run = run_training(Workspace(tmp_path / "ws"), cfg).path
    rows = list(csv.DictReader((run / "progress.csv").open()))
    # 256 warm-start states, then 256 per rollout, 640 at most
    assert [float(row["train_imitation_history_steps"]) for row in rows] == [512.0, 640.0]
