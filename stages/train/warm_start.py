"""Warm start: behaviour cloning from the privileged expert on the states the learner visits (DAgger), then a fit
of the value head to the cloned policy's returns, before PPO.

Written against the policy's own `evaluate_actions` over fixed-length sequence chunks with their LSTM states (the
`imitation` package pins an old stable-baselines3 and its behaviour cloning ignores the LSTM state). Round 0 drives
with the expert; round i drives with the expert with probability beta**i per step and env, else with the learner
(stochastic, as PPO will), and always records the expert's label; after each round the learner is fitted to all
data gathered so far (`epochs` passes). The log std of the steering is not fitted (cloning would shrink it to
nothing and leave PPO no exploration).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from sb3_contrib.common.recurrent.type_aliases import RNNStates
from stable_baselines3.common.vec_env import VecEnv

from drivesim.stages.train.config import WarmStartConfig
from drivesim.stages.train.envs import expert_labels
from drivesim.stages.train.imitation import ChunkData, cloning_optimizer, fit_to_labels, minibatches, to_chunks
from drivesim.stages.train.recurrent import ChunkedRecurrentPPO, ChunkedRolloutBuffer


def _on(policy: Any, array: np.ndarray) -> torch.Tensor:
    """An array as a tensor on the policy's device."""
    return torch.from_numpy(array).to(policy.device)


def _collect(
    model: ChunkedRecurrentPPO,
    venv: VecEnv,
    steps_per_env: int,
    chunk_steps: int,
    beta: float,
    rng: np.random.Generator,
    carry: dict,
    memory: bool = False,
) -> tuple[ChunkData, float]:
    """Drive `steps_per_env` steps per env (expert with probability beta); return `chunk_steps`-long chunks, labelled
    with the expert's action (and with `memory` the memory targets), and the expert share."""
    policy, L, n = model.policy, chunk_steps, venv.num_envs
    layers, hidden = policy.lstm_actor.num_layers, policy.lstm_actor.hidden_size
    steps_per_env = max(L, steps_per_env // L * L)
    obs_buf = np.zeros((steps_per_env, n, *venv.observation_space.shape), np.uint8)
    starts = np.zeros((steps_per_env, n), np.float32)
    labels = np.zeros((steps_per_env, n, 3 if memory else 1), np.float32)
    hs = np.zeros((steps_per_env // L, n, layers, hidden), np.float32)
    cs = np.zeros_like(hs)
    expert_used = 0
    for t in range(steps_per_env):
        obs, start, state = carry["obs"], carry["start"], carry["state"]
        if t % L == 0:
            hs[t // L] = state[0].cpu().numpy().swapaxes(0, 1)
            cs[t // L] = state[1].cpu().numpy().swapaxes(0, 1)
        with torch.no_grad():
            learner, _, _, new_state = policy.forward(
                _on(policy, obs), RNNStates(state, state), _on(policy, start.astype(np.float32))
            )
        label = expert_labels(venv, memory)
        use_expert = rng.random(n) < beta
        expert_used += int(use_expert.sum())
        action = np.where(use_expert[:, None], label[:, :1], learner.cpu().numpy().reshape(n, -1))
        obs_buf[t], starts[t], labels[t] = obs, start, label
        next_obs, _, dones, _ = venv.step(np.clip(action, -1.0, 1.0).astype(np.float32))
        carry.update(obs=next_obs, start=dones.astype(np.float32), state=new_state.pi)
    k = steps_per_env // L

    data = ChunkData(
        to_chunks(obs_buf, L),
        to_chunks(starts, L),
        to_chunks(labels, L),
        hs.reshape(k * n, layers, hidden),
        cs.reshape(k * n, layers, hidden),
    )
    return data, expert_used / (steps_per_env * n)


def _concat(a: ChunkData | None, b: ChunkData) -> ChunkData:
    if a is None:
        return b
    return ChunkData(
        *(
            np.concatenate([x, y])
            for x, y in zip((a.obs, a.starts, a.labels, a.h, a.c), (b.obs, b.starts, b.labels, b.h, b.c), strict=True)
        )
    )


def _fit_value(
    model: ChunkedRecurrentPPO, venv: VecEnv, steps_per_env: int, epochs: int, lr: float, carry: dict
) -> float:
    """Fit the value head alone to GAE returns of the cloned policy (two rounds: returns, fit, returns, fit)."""
    policy, L, n = model.policy, model.sequence_length, venv.num_envs
    steps_per_env = max(L, steps_per_env // L * L)
    lstm = policy.lstm_actor
    buffer = ChunkedRolloutBuffer(
        steps_per_env,
        venv.observation_space,
        venv.action_space,
        (steps_per_env, lstm.num_layers, n, lstm.hidden_size),
        policy.device,
        gae_lambda=model.gae_lambda,
        gamma=model.gamma,
        n_envs=n,
        sequence_length=L,
    )
    policy.set_training_mode(False)
    dones = np.zeros(n, bool)
    for _ in range(steps_per_env):
        obs, start, state = carry["obs"], carry["start"], carry["state"]
        with torch.no_grad():
            actions, values, log_probs, new_state = policy.forward(
                _on(policy, obs), RNNStates(state, state), _on(policy, start.astype(np.float32))
            )
        actions_np = actions.cpu().numpy()
        next_obs, rewards, dones, infos = venv.step(np.clip(actions_np, -1.0, 1.0))
        buffer.add(obs, actions_np, rewards, start, values, log_probs, lstm_states=RNNStates(state, state))
        carry.update(obs=next_obs, start=dones.astype(np.float32), state=new_state.pi)
    optimizer = torch.optim.Adam(policy.value_net.parameters(), lr=lr)
    loss_value = float("nan")
    for _ in range(2):
        with torch.no_grad():
            last = policy.predict_values(_on(policy, carry["obs"]), carry["state"], _on(policy, carry["start"]))
        buffer.compute_returns_and_advantage(last_values=last, dones=dones)
        for _ in range(max(1, epochs // 2)):
            for batch in buffer.get(model.batch_size):
                values, _, _ = policy.evaluate_actions(
                    batch.observations.float(), batch.actions, batch.lstm_states, batch.episode_starts
                )
                loss = torch.mean((batch.returns - values.flatten()) ** 2)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                loss_value = loss.item()
        with torch.no_grad():  # the values the second round's returns bootstrap from
            for ids in np.array_split(np.arange(steps_per_env * n // L), max(1, steps_per_env * n // L // 64)):
                batch = buffer.chunk_samples(ids)
                values, _, _ = policy.evaluate_actions(
                    batch.observations.float(), batch.actions, batch.lstm_states, batch.episode_starts
                )
                k, env = ids // n, ids % n
                t = k[:, None] * L + np.arange(L)[None, :]
                buffer.values[t, np.broadcast_to(env[:, None], t.shape)] = values.cpu().numpy().reshape(len(ids), L)
    return loss_value


def warm_start(
    model: ChunkedRecurrentPPO,
    venv: VecEnv,
    cfg: WarmStartConfig,
    seed: int,
    report: Callable[[str], None] = print,
    keep: Callable[[ChunkData], None] | None = None,
    memory_weight: float = 0.0,
) -> dict[str, float]:
    """DAgger from the expert, then the value fit; returns figures for the log (losses, expert share per round).
    `keep`, when given, receives all the labelled chunks gathered (for the imitation regularizer's history);
    `memory_weight` > 0 also fits the policy's memory head (`imitation.fit_to_labels`)."""
    rng = np.random.default_rng(seed)
    policy = model.policy
    layers, hidden = policy.lstm_actor.num_layers, policy.lstm_actor.hidden_size
    n = venv.num_envs
    zeros = torch.zeros(layers, n, hidden, device=policy.device)
    carry = {"obs": venv.reset(), "start": np.ones(n, np.float32), "state": (zeros, zeros.clone())}
    optimizer = cloning_optimizer(model, cfg.learning_rate)
    chunk_steps = cfg.sequence_length_steps or model.sequence_length
    chunks_per_batch = max(1, model.batch_size // chunk_steps)
    data: ChunkData | None = None
    figures: dict[str, float] = {}
    for round_ in range(cfg.iterations):
        beta = cfg.beta**round_
        memory = memory_weight > 0 and getattr(policy, "memory_net", None) is not None
        new, share = _collect(model, venv, cfg.steps_per_iteration // n, chunk_steps, beta, rng, carry, memory)
        data = _concat(data, new)
        # `epochs` passes over all data so far: round i costs i + 1 times round 0 (36 rounds' worth for 8 rounds).
        # Passes over one round's size instead would cost less but make 4.5x fewer gradient steps for 8 rounds and
        # left a weaker warm start (experiments/NOTEBOOK.md).
        batches = minibatches(
            len(data.obs), cfg.epochs * max(1, len(data.obs) // chunks_per_batch), chunks_per_batch, rng
        )
        loss = fit_to_labels(model, data, batches, optimizer, memory_weight)
        figures[f"warm_start_bc_loss_{round_}"] = loss
        report(
            f"warm start round {round_}: expert drove {share:.0%} of {len(new.obs) * chunk_steps} "
            f"steps; cloning loss {loss:.3f} over {len(data.obs) * chunk_steps} labelled steps"
        )
    if keep is not None and data is not None:
        keep(data)
    value_loss = _fit_value(model, venv, cfg.value_fit_steps // n, cfg.value_fit_epochs, cfg.learning_rate, carry)
    figures["warm_start_value_loss"] = value_loss
    report(f"warm start: value head fitted to the cloned policy's returns (loss {value_loss:.3f})")
    policy.set_training_mode(False)
    return figures
