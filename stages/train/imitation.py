"""Cloning the privileged expert on sequence chunks: the warm start's fit, and the imitation regularizer of PPO.

The regularizer (`imitation.epochs` > 0) labels every state of PPO's own rollouts with the expert's action and,
after each PPO update, fits the steering to those labels (the log std is left to PPO). It keeps PPO near the
expert where its reward misleads it, as RAD adds an imitation loss to PPO for its 3DGS-trained policy; it alternates
with PPO's epochs like PPG's auxiliary phase, so sb3-contrib's PPO update stays as it is. The paper's protocol (pure
PPO, no expert) has it off.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from drivesim.stages.train.envs import expert_actions


@dataclass
class ChunkData:
    """Sequence chunks: obs (K, L, C, H, W) uint8, starts (K, L), labels (K, L, 1), LSTM state at each chunk's start
    (h, c) (K, layers, hidden)."""

    obs: np.ndarray
    starts: np.ndarray
    labels: np.ndarray
    h: np.ndarray
    c: np.ndarray


def to_chunks(a: np.ndarray, sequence_length: int) -> np.ndarray:
    """(T, n, ...) per-step arrays -> (T // L * n, L, ...) chunks; chunk id = time chunk * n + env."""
    k, n = a.shape[0] // sequence_length, a.shape[1]
    return a.reshape(k, sequence_length, n, *a.shape[2:]).swapaxes(1, 2).reshape(k * n, sequence_length, *a.shape[2:])


def minibatches(total: int, batches: int, chunks_per_batch: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`batches` minibatches of chunk ids drawn from all `total` chunks, each id once per pass over them."""
    passes = -(-batches * chunks_per_batch // total)
    ids = np.concatenate([rng.permutation(total) for _ in range(passes)])
    size = max(1, min(chunks_per_batch, total))
    return [ids[i * size : (i + 1) * size] for i in range(batches)]


def fit_to_labels(model: Any, data: ChunkData, batches: list[np.ndarray], optimizer: torch.optim.Optimizer) -> float:
    """Fit the steering to the expert's labels on the given minibatches of chunks (negative log-likelihood; the
    optimizer leaves the std alone); the mean loss of the last quarter of them."""
    policy = model.policy
    policy.set_training_mode(True)
    losses = []
    for ids in batches:
        dev = policy.device
        obs = torch.from_numpy(data.obs[ids].reshape(-1, *data.obs.shape[2:])).to(dev)
        h = torch.from_numpy(np.ascontiguousarray(data.h[ids].swapaxes(0, 1))).to(dev)
        c = torch.from_numpy(np.ascontiguousarray(data.c[ids].swapaxes(0, 1))).to(dev)
        _, log_prob, _ = policy.evaluate_actions(
            obs.float(),
            torch.from_numpy(data.labels[ids].reshape(-1, 1)).to(dev),
            RNNStates((h, c), (h, c)),
            torch.from_numpy(data.starts[ids].reshape(-1)).to(dev),
        )
        loss = -log_prob.mean()
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()
        losses.append(loss.item())
    return float(np.mean(losses[-max(1, len(losses) // 4) :])) if losses else float("nan")


def cloning_optimizer(model: Any, learning_rate: float) -> torch.optim.Adam:
    """Adam over the policy's parameters but the log std (cloning would shrink it and leave PPO no exploration)."""
    params = [p for name, p in model.policy.named_parameters() if name != "log_std"]
    return torch.optim.Adam(params, lr=learning_rate)


class StepLabels(VecEnvWrapper):
    """Records `read(venv)`, an (n_envs, k) array about the state each step starts from, for the last `steps` steps
    of all envs (in `values`, oldest first): labels aligned with the observations PPO's rollout buffer holds."""

    def __init__(self, venv: VecEnv, steps: int, read: Callable[[VecEnv], np.ndarray]) -> None:
        super().__init__(venv)
        self.read = read
        self.values: deque[np.ndarray] = deque(maxlen=steps)

    def reset(self) -> Any:
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        self.values.append(self.read(self.venv))
        self.venv.step_async(actions)

    def step_wait(self) -> Any:
        return self.venv.step_wait()


class ExpertLabels(StepLabels):
    """Records the expert's action for the state each step starts from, the last `steps` steps of all envs."""

    def __init__(self, venv: VecEnv, steps: int) -> None:
        super().__init__(venv, steps, expert_actions)

    @property
    def labels(self) -> deque[np.ndarray]:
        """The recorded expert actions, (n_envs, 1) each, oldest first."""
        return self.values


class ImitationRegularizer:
    """After each PPO update: `epochs` passes of cloning over the rollout PPO just used (module docstring).

    :param model: the ChunkedRecurrentPPO. :param labels: the wrapper recording the rollout's expert labels.
    :param epochs: passes per update. :param learning_rate: Adam's. :param seed: the minibatch order's.
    """

    def __init__(self, model: Any, labels: ExpertLabels, epochs: int, learning_rate: float, seed: int) -> None:
        self.model, self.labels, self.epochs = model, labels, epochs
        self.optimizer = cloning_optimizer(model, learning_rate)
        self.rng = np.random.default_rng(seed)

    def __call__(self) -> None:
        start = time.perf_counter()
        self._fit()
        self.model.time_s["imitation"] = self.model.time_s.get("imitation", 0.0) + time.perf_counter() - start

    def _fit(self) -> None:
        buffer, L = self.model.rollout_buffer, self.model.sequence_length
        if len(self.labels.labels) < buffer.buffer_size:
            return  # fewer labels than rollout steps: not a rollout of this wrapper's env
        labels = np.stack(list(self.labels.labels)[-buffer.buffer_size :]).astype(np.float32)
        k, n = buffer.buffer_size // L, buffer.n_envs
        data = ChunkData(
            to_chunks(buffer.observations, L),
            to_chunks(buffer.episode_starts, L),
            to_chunks(labels.reshape(buffer.buffer_size, n, -1), L),
            buffer.chunk_h.reshape(k * n, *buffer.chunk_h.shape[2:]),
            buffer.chunk_c.reshape(k * n, *buffer.chunk_c.shape[2:]),
        )
        per_batch = max(1, self.model.batch_size // L)
        batches = minibatches(k * n, self.epochs * max(1, k * n // per_batch), per_batch, self.rng)
        loss = fit_to_labels(self.model, data, batches, self.optimizer)
        self.model.logger.record("train/imitation_loss", loss)
        self.model.policy.set_training_mode(False)
