"""Where training gets its environments: drivesim's simulator (one or several worlds) or the cost-free stand-in."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.registry import task_spec


def _limit_worker_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


class _StoppableSubprocVecEnv(SubprocVecEnv):
    """SB3's SubprocVecEnv whose close after a step interrupted mid-way (Ctrl-C, SIGTERM) does not hang.

    SB3's close waits for every worker's reply to the step under way, but the replies read before the interrupt are
    gone, so it would wait forever on those; here the workers are stopped instead (their envs hold nothing to save).
    """

    def close(self) -> None:  # noqa: D102
        if self.waiting and not self.closed:
            for process in self.processes:
                process.terminate()
            for process in self.processes:
                process.join(timeout=10)
            for remote in self.remotes:
                remote.close()
            self.closed = True
            return
        super().close()


@dataclass
class EnvSource:
    """Makes the training, vectorized and evaluation environments of a run.

    :param task: a task of the registry (sim/envs/registry.py).
    :param worlds: world folders (episodes are drawn from all of them); empty with `cost_free`.
    :param meshes: the vehicle mesh library folder, or None for the procedural one.
    :param config: the env config (`EnvsConfig.config`: the task's with the run's keys on top; pydantic models
        pickle for worker processes); None: the task's own (`default_config()`).
    :param cost_free: use `CostFreeDrivingEnv` instead of the simulator (speed of the learner alone; tests).
    :param worker_threads: torch threads in each subprocess worker (an env made in this process leaves them as they
        are: the learner's).
    :param processes: worker processes of the batched envs (1: in this process).
    """

    task: str
    worlds: list[Path] = field(default_factory=list)
    meshes: Path | None = None
    config: EnvConfig | None = None
    cost_free: bool = False
    worker_threads: int = 1
    processes: int = 1

    def _world_arg(self) -> Any:
        return str(self.worlds[0]) if len(self.worlds) == 1 else [str(w) for w in self.worlds]

    def env_fn(self, mode: str = "train") -> Callable[[], gymnasium.Env]:
        """A picklable constructor of one env (for subprocess workers too)."""
        return _EnvFn(self, mode)

    def make_env(self, mode: str = "train") -> gymnasium.Env:
        """One env in this process."""
        return self.env_fn(mode)()

    def make_vec(self, count: int, kind: str, seed: int, mode: str = "train", address: str | None = None) -> VecEnv:
        """`count` envs as an SB3 VecEnv; kind batched | subproc | dummy | ray (batched needs the simulator; ray
        puts each env in a Ray actor on the cluster at `address`, None = Ray started on this machine)."""
        if kind == "ray":
            from drivesim.stages.train.ray_vecenv import RayVecEnv

            venv = RayVecEnv([self.env_fn(mode) for _ in range(count)], address=address)
            venv.seed(seed)
            return venv
        if kind == "batched" and not self.cost_free:
            batch = (self.task, count, self._world_arg(), None if self.meshes is None else str(self.meshes), mode)
            if self.processes > 1 and count > 1:
                from drivesim.sim.envs.parallel import ProcessBatchedVecEnv

                return ProcessBatchedVecEnv(
                    *batch, self.env_config(), seed, workers=self.processes, worker_threads=self.worker_threads
                )
            from drivesim.sim.envs.vector import BatchedVecEnv

            venv: VecEnv = BatchedVecEnv(*batch, self.env_config(), seed)
            return venv
        if kind == "subproc" and count > 1:
            venv = _StoppableSubprocVecEnv([self.env_fn(mode) for _ in range(count)], start_method="forkserver")
        else:
            venv = DummyVecEnv([self.env_fn(mode) for _ in range(count)])
        venv.seed(seed)
        return venv

    def env_config(self) -> EnvConfig:
        """The env config every env of the source gets: `config`, else the task's own."""
        return self.config if self.config is not None else task_spec(self.task).config_with()

    def resolved_env_config(self, env: gymnasium.Env) -> dict[str, Any]:
        """The full env config of a made env (its `config` when it has one), else the source's; `roi_px` resolved
        to the region the policy sees when every world of the run has the same one (else left null; left null too
        when the region is given in degrees, `roi_fov_deg`, which places it on any camera)."""
        unwrapped = env.unwrapped
        config = getattr(unwrapped, "config", None)
        if not hasattr(config, "model_dump"):
            return self.env_config().model_dump(mode="json")
        resolved = config.model_dump(mode="json")
        roi_of = getattr(unwrapped, "roi_px_of", None)
        if callable(roi_of) and resolved.get("roi_fov_deg") is None:
            rois = {tuple(int(v) for v in roi_of(i)) for i in range(len(unwrapped.worlds))}
            if len(rois) == 1:
                resolved["roi_px"] = list(rois.pop())
        return resolved

    def max_curvature_1pm(self, env: gymnasium.Env) -> float | None:
        """The curvature of a full steering action, when the env config says it."""
        config = getattr(env.unwrapped, "config", None)
        value = getattr(config, "max_curvature_1pm", None)
        return None if value is None else float(value)


@dataclass
class _EnvFn:
    source: EnvSource
    mode: str
    maker_pid: int = field(default_factory=os.getpid)
    """The process that made this constructor: an env made there leaves its torch threads to the learner."""

    def __call__(self) -> gymnasium.Env:
        if os.getpid() != self.maker_pid:  # a subprocess or Ray worker: one env among several on the cores
            _limit_worker_threads(self.source.worker_threads)
        if self.source.cost_free:
            from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv

            env_config = self.source.env_config()
            return CostFreeDrivingEnv(env_config.observation_shape, episode_steps=env_config.episode_steps)
        import drivesim.sim.envs  # noqa: F401  (registers the drivesim envs)

        meshes = None if self.source.meshes is None else str(self.source.meshes)
        return gymnasium.make(
            task_spec(self.source.task).env_id,
            world=self.source._world_arg(),
            meshes=meshes,
            mode=self.mode,
            config=self.source.env_config(),
        )


MEMORY_OUTPUTS = 2
"""Columns of `memory_targets`: the other car's forward and left offsets from the ego."""


def memory_targets(venv: VecEnv) -> np.ndarray:
    """Where the other car is from each env's ego now (`DrivingEnv.memory_target`): (n_envs, 2) float32."""
    own = getattr(venv, "memory_targets", None)
    if callable(own):
        return np.asarray(own(), np.float32).reshape(venv.num_envs, -1)
    return np.stack([np.asarray(a, np.float32).reshape(-1) for a in venv.env_method("memory_target")])


def expert_labels(venv: VecEnv, memory: bool) -> np.ndarray:
    """The cloning's labels for every env now: the expert's action, then with `memory` the memory targets:
    (n_envs, 1) or (n_envs, 3) float32."""
    actions = expert_actions(venv)
    return np.hstack([actions, memory_targets(venv)]) if memory else actions


def expert_actions(venv: VecEnv) -> np.ndarray:
    """The privileged expert's action for every env of `venv` now: (n_envs, 1) float32."""
    own = getattr(venv, "expert_actions", None)
    if callable(own):
        return np.asarray(own(), np.float32).reshape(venv.num_envs, -1)
    return np.stack([np.asarray(a, np.float32).reshape(-1) for a in venv.env_method("expert_action")])
