"""BatchedVecEnv: n episodes of one task stepped in one process, their views rendered in one batched call.

It behaves as SB3's DummyVecEnv over n single envs (same seeds -> same observations, rewards and infos; automatic
reset with `terminal_observation` in the info), but the views of all episodes that share a world are rendered by one
`ViewSynthesizer.render` call, which is where the time goes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvObs, VecEnvStepReturn

from drivesim.sim.envs.base import DrivingEnv
from drivesim.sim.envs.registry import task_spec
from drivesim.sim.simulator import render_requests


class BatchedVecEnv(VecEnv):
    """`n_envs` episodes of `task` in this process (SB3 VecEnv); one batched render per world per step.

    :param task: a task of the registry (sim/envs/registry.py). :param n_envs: number of episodes stepped together.
    :param world: a world folder, a World or a list of them. :param meshes: the meshes folder or None (procedural).
    :param mode: "train" or "eval". :param config: EnvConfig or a dict of overrides.
    :param seed: the first reset of episode i uses seed + i (None: random).
    """

    def __init__(
        self,
        task: str,
        n_envs: int,
        world: Any,
        meshes: Any = None,
        mode: str = "train",
        config: Any = None,
        seed: int | None = None,
    ) -> None:
        cls = task_spec(task).env_class()
        first = cls(world=world, meshes=meshes, mode=mode, config=config)
        self.envs: list[DrivingEnv] = [first]
        for _ in range(n_envs - 1):
            env = cls(world=first.worlds, meshes=None, mode=mode, config=first.config)
            env.vehicles, env._renderers, env._timings = first.vehicles, first._renderers, first._timings
            self.envs.append(env)
        super().__init__(n_envs, first.observation_space, first.action_space)
        self._actions: np.ndarray | None = None
        if seed is not None:
            self.seed(seed)

    @property
    def timings_ms(self) -> dict[str, float]:
        """Cumulative ms per part over all episodes since `reset_timings()`."""
        return self.envs[0].timings_ms

    def reset_timings(self) -> None:
        """Zero the timings and step counts."""
        for env in self.envs:
            env.reset_timings()

    def _render(self, indices: Sequence[int]) -> dict[int, np.ndarray]:
        """Views of the given episodes, one render call per renderer (world)."""
        groups: dict[int, list[int]] = {}
        for i in indices:
            groups.setdefault(id(self.envs[i].sim.renderer), []).append(i)
        views: dict[int, np.ndarray] = {}
        for members in groups.values():
            renderer = self.envs[members[0]].sim.renderer
            rgb = render_requests(renderer, [self.envs[i].view_request() for i in members], self.envs[0]._timings)
            views.update(zip(members, rgb, strict=True))
        return views

    def reset(self) -> VecEnvObs:
        """Reset every episode (with the seeds of `seed()` the first time) and render them in one call."""
        for i, env in enumerate(self.envs):
            env.reset_state(self._seeds[i])
            self.reset_infos[i] = env._info(reset=True)
        views = self._render(range(self.num_envs))
        self._reset_seeds()
        return np.stack([env.observation_from(views[i]) for i, env in enumerate(self.envs)])

    def step_async(self, actions: np.ndarray) -> None:
        """Store the actions (n_envs, 1)."""
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def step_wait(self) -> VecEnvStepReturn:
        """Advance every episode, render all in one call; finished episodes restart (terminal_observation)."""
        n = self.num_envs
        rewards = np.zeros(n, dtype=np.float32)
        dones = np.zeros(n, dtype=bool)
        infos: list[dict] = []
        for i, env in enumerate(self.envs):
            reward, terminated, truncated, info = env.advance(self._actions[i])
            rewards[i], dones[i] = reward, terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            infos.append(info)
        done_idx = [i for i in range(n) if dones[i]]
        if done_idx:
            final = self._render(done_idx)
            for i in done_idx:
                infos[i]["terminal_observation"] = self.envs[i].observation_from(final[i])
                self.envs[i].reset_state(None)
                self.reset_infos[i] = self.envs[i]._info(reset=True)
        views = self._render(range(n))
        obs = np.stack([env.observation_from(views[i]) for i, env in enumerate(self.envs)])
        return obs, rewards, dones, infos

    def expert_actions(self) -> np.ndarray:
        """The privileged expert's actions for every episode now, (n_envs, 1) float32."""
        return np.stack([env.expert_action() for env in self.envs])

    def memory_targets(self) -> np.ndarray:
        """Every episode's `memory_target` now, (n_envs, 2) float32."""
        return np.stack([env.memory_target() for env in self.envs])

    def close(self) -> None:
        """Nothing to release."""

    def _indices(self, indices: Any) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """An attribute of each env."""
        return [getattr(self.envs[i], attr_name) for i in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set an attribute of each env."""
        for i in self._indices(indices):
            setattr(self.envs[i], attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        """Call a method of each env."""
        return [getattr(self.envs[i], method_name)(*method_args, **method_kwargs) for i in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: Any = None) -> list[bool]:
        """The envs are not wrapped."""
        return [False for _ in self._indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """The last view of each episode."""
        return [env.render() for env in self.envs]
