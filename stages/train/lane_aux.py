"""An auxiliary target for the image encoder: where the ego is in its lane.

Policies trained on procedural towns may carry the ego's place in the lane only through whatever cue the towns offered
(experiments/steer_bias). The simulator knows that place at every step. With `lane_aux.epochs` > 0, after each PPO
update a linear head on the encoder's features is fitted, together with the encoder, to the ego's lateral offset from
the lane centre and its heading relative to it at each step of the rollout PPO just used (`epochs` passes, mean squared
error on the offsets divided by the task's max_lateral_m and max_rotation_rad), in the picture's frame (a mirrored
episode's offsets mirrored). It alternates with PPO's epochs like PPG's auxiliary phase, as the imitation regularizer
does (stages/train/imitation.py). The head is not part of the policy: it is not saved, and a resumed run starts a new
one.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from drivesim.stages.train.imitation import StepLabels


def lane_positions(venv: VecEnv) -> np.ndarray:
    """Every env's (lateral offset m, heading rad) relative to the lane now, as its picture shows them: (n_envs, 2)."""
    return np.stack([np.asarray(p, np.float32).reshape(2) for p in venv.env_method("lane_position")])


class LanePositionLabels(StepLabels):
    """Records every env's lane position for the state each step starts from, the last `steps` steps of all envs."""

    def __init__(self, venv: VecEnv, steps: int) -> None:
        super().__init__(venv, steps, lane_positions)

    @property
    def positions(self) -> deque[np.ndarray]:
        """The recorded lane positions, (n_envs, 2) each, oldest first."""
        return self.values


class LanePositionAux:
    """After each PPO update: `epochs` passes fitting the encoder and a linear head to the rollout's lane positions.

    :param model: the ChunkedRecurrentPPO. :param labels: the wrapper recording the rollout's lane positions.
    :param epochs: passes per update. :param learning_rate: Adam's (encoder and head).
    :param scales: (max lateral m, max rotation rad) the targets are divided by. :param seed: the minibatch order's.
    """

    def __init__(
        self,
        model: Any,
        labels: LanePositionLabels,
        epochs: int,
        learning_rate: float,
        scales: tuple[float, float],
        seed: int,
    ) -> None:
        self.model, self.labels, self.epochs = model, labels, epochs
        policy = model.policy
        self.head = nn.Linear(policy.features_extractor.features_dim, 2).to(policy.device)
        encoder = list(policy.features_extractor.parameters())
        self.optimizer = torch.optim.Adam([*encoder, *self.head.parameters()], lr=learning_rate)
        self.scales = np.asarray(scales, dtype=np.float32)
        self.rng = np.random.default_rng(seed)
        self.last_loss = float("nan")

    def __call__(self) -> None:
        start = time.perf_counter()
        self._fit()
        self.model.time_s["lane_aux"] = self.model.time_s.get("lane_aux", 0.0) + time.perf_counter() - start

    def _fit(self) -> None:
        buffer, policy = self.model.rollout_buffer, self.model.policy
        if len(self.labels.positions) < buffer.buffer_size:
            return  # fewer labels than rollout steps: not a rollout of this wrapper's env
        targets = np.stack(list(self.labels.positions)[-buffer.buffer_size :]) / self.scales
        obs = buffer.observations.reshape(-1, *buffer.observations.shape[2:])
        targets = targets.reshape(-1, 2).astype(np.float32)
        policy.set_training_mode(True)
        losses = []
        for _ in range(self.epochs):
            order = self.rng.permutation(len(obs))
            for i in range(0, len(obs), self.model.batch_size):
                ids = order[i : i + self.model.batch_size]
                features = policy.extract_features(torch.from_numpy(obs[ids]).to(policy.device).float())
                predicted = self.head(features)
                loss = nn.functional.mse_loss(predicted, torch.from_numpy(targets[ids]).to(policy.device))
                self.optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_([*policy.features_extractor.parameters(), *self.head.parameters()], 1.0)
                self.optimizer.step()
                losses.append(loss.item())
        policy.set_training_mode(False)
        self.last_loss = float(np.mean(losses[-max(1, len(losses) // 4) :])) if losses else float("nan")
        self.model.logger.record("train/lane_aux_loss", self.last_loss)
