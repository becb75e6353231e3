"""Evaluation during training: whole episodes on held-back seeds with the deterministic policy (eval mode env)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.vec_env import VecEnv

from drivesim.policy.net import DrivingNet
from drivesim.stages.train.callbacks import EpisodeRecord, summarize_episodes


def run_episodes(
    net: DrivingNet, env: gymnasium.Env, seeds: list[int], max_steps: int = 100_000
) -> list[EpisodeRecord]:
    """One episode per seed with the deterministic policy; their returns, terms, termination causes and success."""
    records = []
    net.eval()
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        state = net.initial_state(1)
        start = torch.ones(1)
        total, length, terms, causes, success, contact = 0.0, 0, {}, {}, False, False
        with torch.no_grad():
            for _ in range(max_steps):
                mean, _, state = net.step(torch.from_numpy(np.ascontiguousarray(obs))[None], state, start)
                start = torch.zeros(1)
                action = np.clip(mean.numpy()[0], -1.0, 1.0).astype(np.float32)
                obs, reward, terminated, truncated, info = env.step(action)
                total += float(reward)
                length += 1
                for name, value in (info.get("rewards") or {}).items():
                    terms[name] = terms.get(name, 0.0) + float(value)
                contact |= (info.get("state") or {}).get("overlap_frac", 0.0) > 0.0
                if terminated or truncated:
                    causes = {k: bool(v) for k, v in (info.get("termination") or {}).items()}
                    success = bool(info.get("success", False))
                    break
        records.append(EpisodeRecord(total, length, terms, causes, success, contact))
    return records


def run_episodes_batched(net: DrivingNet, venv: VecEnv, max_steps: int = 100_000) -> list[EpisodeRecord]:
    """The first episode of every env of `venv` at once (one batched step for all), deterministic policy."""
    n = venv.num_envs
    net.eval()
    obs = venv.reset()
    state = net.initial_state(n)
    start = torch.ones(n)
    totals, lengths = np.zeros(n), np.zeros(n, dtype=int)
    terms: list[dict[str, float]] = [{} for _ in range(n)]
    contact = np.zeros(n, dtype=bool)
    records: list[EpisodeRecord | None] = [None] * n
    with torch.no_grad():
        for _ in range(max_steps):
            mean, _, state = net.step(torch.from_numpy(np.ascontiguousarray(obs)), state, start)
            obs, rewards, dones, infos = venv.step(np.clip(mean.numpy(), -1.0, 1.0).astype(np.float32))
            start = torch.from_numpy(dones.astype(np.float32))
            for i in range(n):
                if records[i] is not None:
                    continue  # its first episode is over; the env runs on (auto-reset) until all are
                totals[i] += float(rewards[i])
                lengths[i] += 1
                for name, value in (infos[i].get("rewards") or {}).items():
                    terms[i][name] = terms[i].get(name, 0.0) + float(value)
                contact[i] |= (infos[i].get("state") or {}).get("overlap_frac", 0.0) > 0.0
                if dones[i]:
                    causes = {k: bool(v) for k, v in (infos[i].get("termination") or {}).items()}
                    records[i] = EpisodeRecord(
                        float(totals[i]),
                        int(lengths[i]),
                        terms[i],
                        causes,
                        bool(infos[i].get("success", False)),
                        bool(contact[i]),
                    )
            if all(r is not None for r in records):
                break
    return [r for r in records if r is not None]


class PeriodicEvaluator:
    """Evaluates the training policy on fixed held-back seeds, all episodes at once in one vectorized env (made
    once and kept; env i's episode has seed first_seed + i).

    :param make_vec: makes the eval-mode VecEnv with one env per episode.
    :param first_seed: first held-back seed.
    """

    def __init__(self, make_vec: Callable[[], VecEnv], first_seed: int) -> None:
        self.make_vec = make_vec
        self.first_seed = first_seed
        self.venv: VecEnv | None = None

    def __call__(self, policy: Any) -> dict[str, float]:
        """eval_* figures of `policy` (a DrivingLstmPolicy)."""
        if self.venv is None:
            self.venv = self.make_vec()
        self.venv.seed(self.first_seed)
        return summarize_episodes(run_episodes_batched(policy.to_driving_net(), self.venv), prefix="eval_")

    def close(self) -> None:
        """Close the envs."""
        if self.venv is not None:
            self.venv.close()
