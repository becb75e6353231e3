"""The encoder's auxiliary target (issue 19): lane positions aligned with PPO's rollout states and a fit that learns
them (a run that logs it: test_imitation.py)."""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.vec_env import DummyVecEnv
from test_train import small_ppo

from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.lane_aux import LanePositionAux, LanePositionLabels

SHAPE = (3, 16, 40)
SCALES = (2.5, 0.5)


class CounterEnv(CostFreeDrivingEnv):
    """The image is dark with one bright column at the step within the episode (images are standardized one by one,
    so the step must show in where, not how bright); the ego's lane position is a function of that step."""

    def _obs(self) -> np.ndarray:
        image = np.full(SHAPE, 20, np.uint8)
        image[:, :, self.steps % SHAPE[2]] = 235
        return image

    def lane_position(self) -> np.ndarray:
        return np.array([self.steps / 40.0 * SCALES[0], -self.steps / 40.0 * SCALES[1]], np.float32)


def test_lane_positions_belong_to_the_states_ppo_acted_in_and_the_encoder_learns_them():
    torch.manual_seed(0)
    venv = DummyVecEnv([lambda: CounterEnv(observation_shape=SHAPE, episode_steps=37) for _ in range(2)])
    placed = LanePositionLabels(venv, steps=64)
    model = small_ppo(placed, [(8, 3, 2), (16, 3, 1)], 1)
    aux = LanePositionAux(model, placed, epochs=3, learning_rate=3e-3, scales=SCALES, seed=0)
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    losses: list[float] = []

    def check() -> None:
        bright_column = model.rollout_buffer.observations[:, :, 0, 0, :].argmax(axis=-1)
        seen.append((bright_column, np.stack(list(placed.positions))))
        aux()
        losses.append(aux.last_loss)

    model.update_hooks.append(check)
    model.learn(64 * 2 * 4)
    assert len(seen) == 4
    for steps, positions in seen:  # episodes of 37 steps end inside the 64-step rollouts: resets included
        np.testing.assert_allclose(positions[..., 0], steps / 40 * SCALES[0], atol=1e-6)
        np.testing.assert_allclose(positions[..., 1], -steps / 40 * SCALES[1], atol=1e-6)
        assert (steps == 0).sum() >= 2  # an episode start in each env's rollout
    # normalized targets +-step/40 for steps 0..36: their variance about the mean is 0.068 per output (what a
    # constant prediction leaves); a fit of the column's place brings the mean squared error far below it
    assert losses[-1] < 0.02 < losses[0], losses
    assert model.time_s["lane_aux"] > 0
    assert model.logger.name_to_value["train/lane_aux_loss"] == losses[-1]
