"""Cloning the privileged expert on sequence chunks: the warm start's fit, and the imitation regularizer of PPO.

The regularizer (`imitation.epochs` > 0) labels every state of PPO's own rollouts with the expert's action and,
after each PPO update, fits the steering to those labels (the log std is left to PPO). It keeps PPO near the
expert where its reward misleads it, as RAD adds an imitation loss to PPO for its 3DGS-trained policy; it alternates
with PPO's epochs like PPG's auxiliary phase, so sb3-contrib's PPO update stays as it is. The paper's protocol (pure
PPO, no expert) has it off. With `imitation.history_steps` it fits a bounded aggregate of past rollouts (and the warm
start's data) instead of the last rollout alone, as DAgger fits all data gathered so far: a few episodes' mix of
sides then no longer pulls the steering toward it.
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

from drivesim.stages.train.envs import expert_labels


@dataclass
class ChunkData:
    """Sequence chunks: obs (K, L, C, H, W) uint8, starts (K, L), labels (K, L, 1 or 3), LSTM state at each chunk's
    start (h, c) (K, layers, hidden)."""

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


def fit_to_labels(
    model: Any, data: ChunkData, batches: list[np.ndarray], optimizer: torch.optim.Optimizer, memory_weight: float = 0.0
) -> float:
    """Fit the steering to the expert's labels on the given minibatches of chunks (negative log-likelihood; the
    optimizer leaves the std alone), plus, with `memory_weight` > 0 and labels that carry them, `memory_weight` times
    the memory head's squared error on the memory targets (`envs.memory_targets`); the mean loss of the last quarter
    of them."""
    policy = model.policy
    policy.set_training_mode(True)
    memory = memory_weight > 0 and data.labels.shape[-1] > 1 and getattr(policy, "memory_net", None) is not None
    losses = []
    for ids in batches:
        dev = policy.device
        obs = torch.from_numpy(data.obs[ids].reshape(-1, *data.obs.shape[2:])).to(dev)
        h = torch.from_numpy(np.ascontiguousarray(data.h[ids].swapaxes(0, 1))).to(dev)
        c = torch.from_numpy(np.ascontiguousarray(data.c[ids].swapaxes(0, 1))).to(dev)
        labels = torch.from_numpy(data.labels[ids].reshape(-1, data.labels.shape[-1])).to(dev)
        states, starts = RNNStates((h, c), (h, c)), torch.from_numpy(data.starts[ids].reshape(-1)).to(dev)
        if memory:
            log_prob, predicted = policy.clone_outputs(obs.float(), labels[:, :1], states, starts)
            loss = -log_prob.mean() + memory_weight * torch.mean((predicted - labels[:, 1:]) ** 2)
        else:
            _, log_prob, _ = policy.evaluate_actions(obs.float(), labels[:, :1], states, starts)
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
    """Records the expert's action for the state each step starts from (and with `memory` the memory targets,
    `envs.expert_labels`), the last `steps` steps of all envs."""

    def __init__(self, venv: VecEnv, steps: int, memory: bool = False) -> None:
        super().__init__(venv, steps, lambda v: expert_labels(v, memory))

    @property
    def labels(self) -> deque[np.ndarray]:
        """The recorded labels, (n_envs, 1) or (n_envs, 3) each, oldest first."""
        return self.values


class LabelHistory:
    """The newest `capacity_steps` labelled states as sequence chunks, the oldest dropped first: a ring of chunks,
    allocated at the first `add`.

    :param capacity_steps: states kept (rounded down to whole chunks, at least one).
    :param sequence_length: steps per chunk.
    """

    def __init__(self, capacity_steps: int, sequence_length: int) -> None:
        self.capacity = max(1, capacity_steps // sequence_length)
        self.sequence_length = sequence_length
        self._ring: ChunkData | None = None
        self._next = 0
        self._filled = 0

    def __len__(self) -> int:
        return self._filled

    def add(self, data: ChunkData) -> None:
        """Keep `data`'s chunks (the last `capacity` of them when there are more), over the oldest kept."""
        fields = ("obs", "starts", "labels", "h", "c")
        if self._ring is None:
            self._ring = ChunkData(
                *(np.zeros((self.capacity, *getattr(data, f).shape[1:]), getattr(data, f).dtype) for f in fields)
            )
        count = min(len(data.obs), self.capacity)
        slots = (self._next + np.arange(count)) % self.capacity
        for f in fields:
            getattr(self._ring, f)[slots] = getattr(data, f)[len(data.obs) - count :]
        self._next = int((self._next + count) % self.capacity)
        self._filled = min(self.capacity, self._filled + count)

    def data(self) -> ChunkData:
        """The chunks kept (views of the ring, in no particular order)."""
        if self._ring is None:
            raise ValueError("no labelled states kept yet")
        n = self._filled
        r = self._ring
        return ChunkData(r.obs[:n], r.starts[:n], r.labels[:n], r.h[:n], r.c[:n])


class ImitationRegularizer:
    """After each PPO update: `epochs` passes' worth of cloning over the rollout PPO just used, or over the label
    history when one is kept (module docstring).

    :param model: the ChunkedRecurrentPPO. :param labels: the wrapper recording the rollout's expert labels.
    :param epochs: passes per update (in rollouts' worth of minibatches). :param learning_rate: Adam's.
    :param seed: the minibatch order's. :param history_steps: labelled states kept across updates (0: none).
    :param memory_weight: the memory head's loss weight (`fit_to_labels`).
    """

    def __init__(
        self,
        model: Any,
        labels: ExpertLabels,
        epochs: int,
        learning_rate: float,
        seed: int,
        history_steps: int = 0,
        memory_weight: float = 0.0,
    ) -> None:
        self.model, self.labels, self.epochs, self.memory_weight = model, labels, epochs, memory_weight
        self.optimizer = cloning_optimizer(model, learning_rate)
        self.rng = np.random.default_rng(seed)
        self.history = LabelHistory(history_steps, model.sequence_length) if history_steps > 0 else None

    def remember(self, data: ChunkData) -> None:
        """Add labelled chunks gathered elsewhere (the warm start's) to the history; nothing when none is kept."""
        if self.history is not None:
            self.history.add(data)

    def __call__(self) -> None:
        start = time.perf_counter()
        self._fit()
        self.model.time_s["imitation"] = self.model.time_s.get("imitation", 0.0) + time.perf_counter() - start

    def _rollout_chunks(self) -> ChunkData | None:
        """The rollout PPO just used, labelled, as chunks; None when the labels do not cover it."""
        buffer, L = self.model.rollout_buffer, self.model.sequence_length
        if len(self.labels.labels) < buffer.buffer_size:
            return None  # fewer labels than rollout steps: not a rollout of this wrapper's env
        labels = np.stack(list(self.labels.labels)[-buffer.buffer_size :]).astype(np.float32)
        k, n = buffer.buffer_size // L, buffer.n_envs
        # The buffer keeps images as float32; the history keeps them in the observation space's dtype (uint8).
        obs_dtype = self.model.observation_space.dtype
        return ChunkData(
            to_chunks(buffer.observations, L).astype(obs_dtype, copy=False),
            to_chunks(buffer.episode_starts, L),
            to_chunks(labels.reshape(buffer.buffer_size, n, -1), L),
            buffer.chunk_h.reshape(k * n, *buffer.chunk_h.shape[2:]),
            buffer.chunk_c.reshape(k * n, *buffer.chunk_c.shape[2:]),
        )

    def _fit(self) -> None:
        rollout = self._rollout_chunks()
        if rollout is None:
            return
        data = rollout
        if self.history is not None:
            self.history.add(rollout)
            data = self.history.data()
            self.model.logger.record("train/imitation_history_steps", len(self.history) * self.model.sequence_length)
        per_batch = max(1, self.model.batch_size // self.model.sequence_length)
        batches = minibatches(len(data.obs), self.epochs * max(1, len(rollout.obs) // per_batch), per_batch, self.rng)
        loss = fit_to_labels(self.model, data, batches, self.optimizer, self.memory_weight)
        self.model.logger.record("train/imitation_loss", loss)
        self.model.policy.set_training_mode(False)
