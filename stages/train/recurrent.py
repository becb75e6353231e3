"""RecurrentPPO with fixed-length sequence chunks: no padding, one fused LSTM pass per minibatch.

sb3-contrib's `RecurrentRolloutBuffer` cuts each minibatch into sequences at episode starts and pads them to the
longest, copying every sequence through a Python list; with many short episodes most of a minibatch is padding.
Here each env's rollout is cut into chunks of `sequence_length` steps (the LSTM state at each chunk's first step is
stored during the rollout), a minibatch is a random set of whole chunks gathered with one fancy index, and episode
starts inside a chunk are handled exactly by `run_lstm` (the state is zeroed there). Observations stay uint8 in the
buffer; the encoder's parameter-free preprocessing (pooling, standardization) runs once per update, not per epoch.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.buffers import RecurrentRolloutBuffer
from sb3_contrib.common.recurrent.type_aliases import RecurrentRolloutBufferSamples, RNNStates
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper


class ChunkedRolloutBuffer(RecurrentRolloutBuffer):
    """Rollout buffer yielding minibatches of whole fixed-length chunks (see the module docstring).

    :param buffer_size: steps per env per rollout (a multiple of sequence_length).
    :param observation_space: the image space (uint8).
    :param action_space: the action space.
    :param hidden_state_shape: (n_steps, lstm layers, n_envs, hidden).
    :param device: torch device.
    :param gae_lambda: GAE lambda.
    :param gamma: discount.
    :param n_envs: envs.
    :param sequence_length: chunk length [steps].
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        hidden_state_shape: tuple[int, int, int, int],
        device: torch.device | str = "cpu",
        gae_lambda: float = 1.0,
        gamma: float = 0.99,
        n_envs: int = 1,
        sequence_length: int = 16,
    ) -> None:
        if buffer_size % sequence_length:
            raise ValueError(f"rollout length {buffer_size} is not a multiple of the chunk length {sequence_length}")
        self.sequence_length = sequence_length
        self.preprocessed: np.ndarray | None = None
        """Observations after the encoder's preprocessing (set for the duration of an update), else None."""
        super().__init__(
            buffer_size, observation_space, action_space, hidden_state_shape, device, gae_lambda, gamma, n_envs
        )

    def reset(self) -> None:
        # RolloutBuffer's reset only: the per-step LSTM states of sb3-contrib's buffer are not needed.
        RolloutBuffer.reset(self)
        _, layers, n_envs, hidden = self.hidden_state_shape
        chunks = self.buffer_size // self.sequence_length
        self.chunk_h = np.zeros((chunks, n_envs, layers, hidden), dtype=np.float32)
        self.chunk_c = np.zeros((chunks, n_envs, layers, hidden), dtype=np.float32)

    def add(self, *args: Any, lstm_states: RNNStates, **kwargs: Any) -> None:
        """Add one step; keep the LSTM state (before this step) when the step opens a chunk."""
        if self.pos % self.sequence_length == 0:
            k = self.pos // self.sequence_length
            self.chunk_h[k] = lstm_states.pi[0].cpu().numpy().swapaxes(0, 1)
            self.chunk_c[k] = lstm_states.pi[1].cpu().numpy().swapaxes(0, 1)
        RolloutBuffer.add(self, *args, **kwargs)

    def get(self, batch_size: int | None = None) -> Generator[RecurrentRolloutBufferSamples, None, None]:
        """Minibatches of batch_size // sequence_length random whole chunks (sequence-major)."""
        assert self.full, "Rollout buffer must be full before sampling from it"
        chunks = (self.buffer_size // self.sequence_length) * self.n_envs
        per_batch = max(1, (batch_size or self.buffer_size * self.n_envs) // self.sequence_length)
        order = np.random.permutation(chunks)
        for start in range(0, chunks, per_batch):
            yield self.chunk_samples(order[start : start + per_batch])

    def chunk_samples(self, chunk_ids: np.ndarray) -> RecurrentRolloutBufferSamples:
        """The steps of chunks `chunk_ids` (chunk id k * n_envs + e: env e's k-th `sequence_length` steps), in order."""
        k, env = chunk_ids // self.n_envs, chunk_ids % self.n_envs
        t = k[:, None] * self.sequence_length + np.arange(self.sequence_length)[None, :]
        e = np.broadcast_to(env[:, None], t.shape)

        def take(array: np.ndarray) -> torch.Tensor:
            picked = array[t, e]
            return torch.from_numpy(picked.reshape(-1, *picked.shape[2:])).to(self.device)

        h = torch.from_numpy(np.ascontiguousarray(self.chunk_h[k, env].swapaxes(0, 1))).to(self.device)
        c = torch.from_numpy(np.ascontiguousarray(self.chunk_c[k, env].swapaxes(0, 1))).to(self.device)
        returns = take(self.returns)
        return RecurrentRolloutBufferSamples(
            observations=take(self.observations if self.preprocessed is None else self.preprocessed),
            actions=take(self.actions),
            old_values=take(self.values),
            old_log_prob=take(self.log_probs),
            advantages=take(self.advantages),
            returns=returns,
            lstm_states=RNNStates((h, c), (h, c)),
            episode_starts=take(self.episode_starts),
            mask=torch.ones_like(returns),
        )


class TimedVecEnv(VecEnvWrapper):
    """Adds up the wall time spent inside the envs' step (the simulator's share of a rollout)."""

    def __init__(self, venv: VecEnv) -> None:
        super().__init__(venv)
        self.step_time_s = 0.0

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        start = time.perf_counter()
        out = self.venv.step_wait()
        self.step_time_s += time.perf_counter() - start
        return out

    def step_async(self, actions: np.ndarray) -> None:
        start = time.perf_counter()
        self.venv.step_async(actions)
        self.step_time_s += time.perf_counter() - start


class ChunkedRecurrentPPO(RecurrentPPO):
    """sb3-contrib RecurrentPPO with `ChunkedRolloutBuffer` and a record of where the time goes.

    :param sequence_length: chunk length [steps].
    :param rollout_threads: torch threads while collecting a rollout (None: as set for the process); the thread
        count the optimization runs with is restored after each rollout.
    (other parameters: RecurrentPPO's)
    """

    def __init__(
        self, *args: Any, sequence_length: int = 16, rollout_threads: int | None = None, **kwargs: Any
    ) -> None:
        self.sequence_length = int(sequence_length)
        self.rollout_threads = rollout_threads
        self.time_s = {"rollout": 0.0, "optimization": 0.0}
        self.update_hooks: list[Callable[[], None]] = []
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        lstm = self.policy.lstm_actor
        self.rollout_buffer = ChunkedRolloutBuffer(
            self.n_steps,
            self.observation_space,
            self.action_space,
            (self.n_steps, lstm.num_layers, self.n_envs, lstm.hidden_size),
            self.device,
            gamma=self.gamma,
            gae_lambda=self.gae_lambda,
            n_envs=self.n_envs,
            sequence_length=self.sequence_length,
        )

    @property
    def updates_done(self) -> int:
        """Gradient updates made so far (over every epoch and minibatch), as SB3 logs them in `train/n_updates`."""
        return int(self._n_updates)

    @updates_done.setter
    def updates_done(self, count: int) -> None:
        # SB3 keeps this counter private (`_n_updates`, no public setter); a resumed run sets it here, in this one
        # place, so that the update count it logs and checkpoints goes on from the checkpoint's.
        self._n_updates = int(count)

    def collect_rollouts(self, *args: Any, **kwargs: Any) -> bool:
        start = time.perf_counter()
        threads = torch.get_num_threads()
        if self.rollout_threads is not None:
            torch.set_num_threads(self.rollout_threads)
        try:
            return super().collect_rollouts(*args, **kwargs)
        finally:
            torch.set_num_threads(threads)
            self.time_s["rollout"] += time.perf_counter() - start

    def train(self) -> None:
        start = time.perf_counter()
        prepare = getattr(self.policy, "preprocess_observations", None)
        if prepare is not None:
            self.rollout_buffer.preprocessed = prepare(self.rollout_buffer.observations)
            self.policy.observations_preprocessed = True
        try:
            super().train()
        finally:
            self.rollout_buffer.preprocessed = None
            if prepare is not None:
                self.policy.observations_preprocessed = False
        self.time_s["optimization"] += time.perf_counter() - start
        for hook in self.update_hooks:
            hook()
