"""What happens during `learn()`: episode statistics from `info`, the progress bar, and after every update the logs
(progress.csv, TensorBoard), the periodic evaluation on held-back seeds and the checkpoint."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback

from drivesim.stages.train.best import BestPolicy
from drivesim.stages.train.run_files import (
    CHECKPOINTS,
    LAST_CHECKPOINT,
    PROGRESS_CSV,
    torch_save_atomic,
    write_progress,
)


@dataclass
class EpisodeRecord:
    """One finished episode: return, length, summed reward terms, the termination causes, success, and whether the
    footprints ever overlapped (`contact`: what evaluation counts as a collision, whatever training's threshold)."""

    return_: float
    length: int
    terms: dict[str, float]
    causes: dict[str, bool]
    success: bool
    contact: bool = False


def summarize_episodes(episodes: list[EpisodeRecord], prefix: str = "") -> dict[str, float]:
    """Means over episodes: return, length, success rate, each reward term, each termination cause's rate."""
    if not episodes:
        return {}
    head = prefix or "ep_"
    out = {
        f"{prefix}episodes": float(len(episodes)),
        f"{head}return_mean": float(np.mean([e.return_ for e in episodes])),
        f"{head}length_mean": float(np.mean([e.length for e in episodes])),
        f"{head}success_rate": float(np.mean([e.success for e in episodes])),
        f"{head}contact_rate": float(np.mean([e.contact for e in episodes])),
    }
    names = sorted({k for e in episodes for k in e.terms})
    for name in names:
        out[f"{prefix}reward_{name}"] = float(np.mean([e.terms.get(name, 0.0) for e in episodes]))
    causes = sorted({k for e in episodes for k in e.causes})
    for cause in causes:
        out[f"{prefix}term_{cause}"] = float(np.mean([e.causes.get(cause, False) for e in episodes]))
    return out


class EpisodeTracker:
    """Adds up `info["rewards"]` per env and records an `EpisodeRecord` when an env's episode ends."""

    def __init__(self, n_envs: int) -> None:
        self.returns = np.zeros(n_envs)
        self.lengths = np.zeros(n_envs, dtype=int)
        self.terms: list[dict[str, float]] = [{} for _ in range(n_envs)]
        self.contact = np.zeros(n_envs, dtype=bool)
        self.finished: list[EpisodeRecord] = []

    def step(self, rewards: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """Account one vector step."""
        self.returns += rewards
        self.lengths += 1
        for i, info in enumerate(infos):
            for name, value in (info.get("rewards") or {}).items():
                self.terms[i][name] = self.terms[i].get(name, 0.0) + float(value)
            self.contact[i] |= (info.get("state") or {}).get("overlap_frac", 0.0) > 0.0
            if dones[i]:
                causes = {k: bool(v) for k, v in (info.get("termination") or {}).items()}
                self.finished.append(
                    EpisodeRecord(
                        float(self.returns[i]),
                        int(self.lengths[i]),
                        self.terms[i],
                        causes,
                        bool(info.get("success", False)),
                        bool(self.contact[i]),
                    )
                )
                self.returns[i], self.lengths[i], self.terms[i], self.contact[i] = 0.0, 0, {}, False

    def take(self) -> list[EpisodeRecord]:
        """The episodes finished since the last call."""
        out, self.finished = self.finished, []
        return out


@dataclass
class RunState:
    """Counters carried across a resume."""

    wall_s: float = 0.0
    episodes: int = 0
    rows: list[dict[str, Any]] = field(default_factory=list)


class TrainingCallback(BaseCallback):
    """Progress bar with env steps/s; after every update: a progress.csv row, TensorBoard, evaluation, checkpoint.

    :param run_dir: the run folder.
    :param n_envs: training envs.
    :param total_steps: the run's target in env steps (for the bar).
    :param state: counters restored on resume.
    :param evaluate: `evaluate(policy) -> dict of eval_* figures`, or None.
    :param eval_every_steps: evaluation period [env steps] (0: never).
    :param checkpoint_every_steps: numbered checkpoint period [env steps].
    :param progress: (rich Progress, task id) or None.
    :param timing: `timing() -> dict` of time spent so far (rollout, optimization, simulator) [s].
    :param time_limit_s: stop learn() once the run's training wall time exceeds this [s].
    :param extra_checkpoint: `extra_checkpoint() -> dict` of more to keep in each checkpoint (reward statistics).
    :param best: keeps the weights of the best evaluation (checkpoints/best.pt), or None.
    """

    def __init__(
        self,
        run_dir: Path,
        n_envs: int,
        total_steps: int,
        state: RunState,
        evaluate: Callable[[Any], dict[str, float]] | None,
        eval_every_steps: int,
        checkpoint_every_steps: int,
        progress: Any = None,
        timing: Callable[[], dict] | None = None,
        time_limit_s: float | None = None,
        extra_checkpoint: Callable[[], dict] | None = None,
        best: BestPolicy | None = None,
    ) -> None:
        super().__init__()
        self.best = best
        self.time_limit_s = time_limit_s
        self.extra_checkpoint = extra_checkpoint or dict
        self.run_dir = run_dir
        self.tracker = EpisodeTracker(n_envs)
        self.total_steps = total_steps
        self.state = state
        self.evaluate = evaluate
        self.eval_every_steps = eval_every_steps
        self.checkpoint_every_steps = checkpoint_every_steps
        self.progress = progress
        self.timing = timing or dict
        self._t0 = time.perf_counter()
        self._wall0 = state.wall_s
        self._steps0 = 0
        self._last_bar = 0.0
        self._last_update_time = self._t0
        self._last_update_steps = 0

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()
        self._steps0 = self.model.num_timesteps
        self._last_update_time, self._last_update_steps = self._t0, self._steps0
        self.model.update_hooks.append(self.after_update)

    def wall_s(self) -> float:
        """Training wall time of the run so far, across resumes [s]."""
        return self._wall0 + time.perf_counter() - self._t0

    def _on_step(self) -> bool:
        # The env's own rewards: with reward normalization, locals["rewards"] are the scaled ones.
        get_original = getattr(self.training_env, "get_original_reward", None)
        rewards = get_original() if get_original is not None else self.locals["rewards"]
        self.tracker.step(rewards, self.locals["dones"], self.locals["infos"])
        if self.time_limit_s is not None and self.wall_s() > self.time_limit_s:
            return False  # SB3 stops learn() here; the weights are those of the last update
        now = time.perf_counter()
        if self.progress is not None and now - self._last_bar > 0.5:
            self._last_bar = now
            rate = (self.model.num_timesteps - self._steps0) / max(now - self._t0, 1e-9)
            progress, task = self.progress
            # Time left at this rate (not counting the warm start before it), or to the time limit if sooner.
            left_s = (self.total_steps - self.model.num_timesteps) / max(rate, 1e-9)
            if self.time_limit_s is not None:
                left_s = min(left_s, max(self.time_limit_s - self.wall_s(), 0.0))
            description = f"train {rate:5.0f} env steps/s"
            progress.update(task, completed=self.model.num_timesteps, description=description, left_s=left_s)
        return True

    def after_update(self) -> None:
        """Called by ChunkedRecurrentPPO after each PPO update: log, maybe evaluate, checkpoint."""
        steps = int(self.model.num_timesteps)
        now = time.perf_counter()
        episodes = self.tracker.take()
        self.state.episodes += len(episodes)
        recent_rate = (steps - self._last_update_steps) / max(now - self._last_update_time, 1e-9)
        self._last_update_time, self._last_update_steps = now, steps
        row: dict[str, Any] = {
            "steps": steps,
            "wall_s": round(self.wall_s(), 2),
            "steps_per_s": round(recent_rate, 1),
            "steps_per_s_run": round((steps - self._steps0) / max(now - self._t0, 1e-9), 1),
            "episodes_total": self.state.episodes,
        }
        row.update({f"time_{k}_s": round(v, 2) for k, v in self.timing().items()})
        row.update(summarize_episodes(episodes))
        for key, value in self.model.logger.name_to_value.items():
            if key.startswith("train/"):
                row[key.replace("train/", "loss_" if "loss" in key else "train_")] = float(value)
        due = self.eval_every_steps > 0 and (steps // self.eval_every_steps) > (
            self._prev_steps() // self.eval_every_steps
        )
        if self.evaluate is not None and (due or steps >= self.total_steps):
            row.update(self.evaluate(self.model.policy))
            if self.best is not None:
                self.best.offer(row, steps, self.policy_checkpoint)
        for key, value in row.items():
            if isinstance(value, float | int) and key != "steps" and math.isfinite(float(value)):
                self.model.logger.record(f"drivesim/{key}", float(value))
        self.model.logger.dump(steps)
        # The checkpoint first: progress.csv never gets ahead of it (a resume drops rows past the checkpoint).
        self.save_checkpoint()
        self.state.rows.append(row)
        write_progress(self.run_dir / PROGRESS_CSV, self.state.rows)

    def _prev_steps(self) -> int:
        return int(self.state.rows[-1]["steps"]) if self.state.rows else 0

    def policy_checkpoint(self) -> dict[str, Any]:
        """What acting and resuming the policy needs: its weights and the reward statistics."""
        return {"policy": self.model.policy.driving_net_state(), **self.extra_checkpoint()}

    def save_checkpoint(self) -> None:
        """checkpoints/last.pt (and a numbered copy when one is due): weights, optimizer, counters."""
        steps = int(self.model.num_timesteps)
        checkpoint = {
            "policy": self.model.policy.driving_net_state(),
            "optimizer": self.model.policy.optimizer.state_dict(),
            "num_timesteps": steps,
            "n_updates": self.model.updates_done,
            "wall_s": float(self.wall_s()),
            "episodes": int(self.state.episodes),
            "torch_rng": torch.get_rng_state(),
            **self.extra_checkpoint(),
        }
        folder = self.run_dir / CHECKPOINTS
        torch_save_atomic(folder / LAST_CHECKPOINT, checkpoint)
        prev = self._prev_steps()
        if (
            self.checkpoint_every_steps > 0
            and steps // self.checkpoint_every_steps > prev // self.checkpoint_every_steps
        ):
            torch_save_atomic(folder / f"step-{steps:09d}.pt", checkpoint)
