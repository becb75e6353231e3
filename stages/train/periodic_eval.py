"""Evaluation during training: whole episodes on held-back seeds with the deterministic policy (eval mode env)."""

from __future__ import annotations

import gymnasium
import numpy as np
import torch

from drivesim.stages.policy_net import DrivingNet
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
        total, length, terms, causes, success = 0.0, 0, {}, {}, False
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
                if terminated or truncated:
                    causes = {k: bool(v) for k, v in (info.get("termination") or {}).items()}
                    success = bool(info.get("success", False))
                    break
        records.append(EpisodeRecord(total, length, terms, causes, success))
    return records


class PeriodicEvaluator:
    """Evaluates the training policy on fixed held-back seeds; the env is made once and kept.

    :param make_env: makes the eval-mode env.
    :param episodes: episodes per evaluation.
    :param first_seed: first held-back seed.
    """

    def __init__(self, make_env, episodes: int, first_seed: int) -> None:  # noqa: ANN001
        self.make_env = make_env
        self.seeds = [first_seed + i for i in range(episodes)]
        self.env: gymnasium.Env | None = None

    def __call__(self, policy) -> dict[str, float]:  # noqa: ANN001
        """eval_* figures of `policy` (a DrivingLstmPolicy)."""
        if self.env is None:
            self.env = self.make_env()
        return summarize_episodes(run_episodes(policy.to_driving_net(), self.env, self.seeds), prefix="eval_")

    def close(self) -> None:
        """Close the env."""
        if self.env is not None:
            self.env.close()
