"""RayVecEnv: training envs as Ray actors behind stable-baselines3's VecEnv interface (`envs.backend: ray`).

Each env lives in its own actor (`EnvWorker`, built once from the same picklable constructor the local VecEnvs use),
spread over the cluster's nodes, so a run can step more envs than this machine has cores. It behaves as SB3's
DummyVecEnv over the same envs: the same seeds give the same observations, rewards, dones and infos; an episode that
ends is reset in its actor at once, its last observation in `info["terminal_observation"]`. `step_async` sends every
env its action and `step_wait` gathers the results, so the envs step in parallel while the learner waits.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.ray_cluster import RaySession, cpus_per_actor, is_lost_worker, kill_actors


class EnvWorker:
    """One env in a Ray actor: SB3's VecEnv calls for one env (`ray.remote` makes it an actor at run time).

    :param env_fn: builds the env (called once, in the actor).
    """

    def __init__(self, env_fn: Callable[[], gymnasium.Env]) -> None:
        self.env = env_fn()

    def spaces(self) -> tuple[gymnasium.Space, gymnasium.Space]:
        """The env's observation and action spaces."""
        return self.env.observation_space, self.env.action_space

    def reset(self, seed: int | None, options: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        """`env.reset(seed=seed, options=...)`: the observation and the reset info."""
        return self.env.reset(seed=seed, **({"options": options} if options else {}))

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, dict[str, Any], dict[str, Any]]:
        """One step in SB3's terms: (obs, reward, done, info, reset info); a finished episode is reset at once."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        done = bool(terminated or truncated)
        info["TimeLimit.truncated"] = bool(truncated and not terminated)
        reset_info: dict[str, Any] = {}
        if done:
            info["terminal_observation"] = obs
            obs, reset_info = self.env.reset()
        return obs, float(reward), done, info, reset_info

    def get_attr(self, name: str) -> Any:
        """An attribute of the env (or of a wrapper)."""
        return self.env.get_wrapper_attr(name)

    def set_attr(self, name: str, value: Any) -> None:
        """Set an attribute of the env (its outermost wrapper, as SB3's SubprocVecEnv does)."""
        setattr(self.env, name, value)

    def env_method(self, name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
        """Call a method of the env (or of a wrapper)."""
        return self.env.get_wrapper_attr(name)(*args, **kwargs)

    def is_wrapped(self, wrapper_class: type[gymnasium.Wrapper]) -> bool:
        """Whether the env is wrapped by `wrapper_class`."""
        from stable_baselines3.common.env_util import is_wrapped

        return is_wrapped(self.env, wrapper_class)

    def render(self) -> Any:
        """The env's render."""
        return self.env.render()

    def close(self) -> None:
        """Close the env."""
        self.env.close()


class RayVecEnv(VecEnv):
    """`len(env_fns)` envs, each in a Ray actor, as an SB3 VecEnv.

    :param env_fns: picklable env constructors (one actor each; every node must be able to run them).
    :param address: the Ray cluster ("auto", host:port); None starts Ray on this machine for the VecEnv's life.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gymnasium.Env]], address: str | None = None) -> None:
        self._session = RaySession(address)
        self._ray = self._session.open()
        self._actors: list[Any] = []
        self._pending: list[Any] = []
        self._closed = False
        try:
            cpus = cpus_per_actor(self._ray, len(env_fns))
            actor_class = self._ray.remote(num_cpus=cpus, scheduling_strategy="SPREAD")(EnvWorker)
            self._actors = [actor_class.remote(fn) for fn in env_fns]
            observation_space, action_space = self._get([self._actors[0].spaces.remote()])[0]
            super().__init__(len(env_fns), observation_space, action_space)
        except BaseException:
            self.close()
            raise

    def _get(self, refs: list[Any]) -> list[Any]:
        """The results of actor calls; a dead actor or an env that failed to start is one line."""
        try:
            return self._ray.get(refs)
        except Exception as e:
            if not is_lost_worker(e):
                raise
            text = str(e).strip()
            last = text.splitlines()[-1][:200] if text else type(e).__name__
            raise DrivesimError(f"a Ray env worker died or could not start its env: {last}") from e

    def _indices(self, indices: VecEnvIndices) -> list[int]:
        return list(self._get_indices(indices))

    def reset(self) -> VecEnvObs:
        """Reset every env (with the seeds and options set since the last reset) and return the observations."""
        calls = [a.reset.remote(self._seeds[i], self._options[i]) for i, a in enumerate(self._actors)]
        results = self._get(calls)
        self.reset_infos = [info for _, info in results]
        self._reset_seeds()
        self._reset_options()
        return _stack([obs for obs, _ in results], self.observation_space)

    def step_async(self, actions: np.ndarray) -> None:
        """Send each env its action (the envs step in parallel)."""
        self._pending = [a.step.remote(action) for a, action in zip(self._actors, actions, strict=True)]

    def step_wait(self) -> VecEnvStepReturn:
        """Gather the steps sent by `step_async`: observations, rewards, dones and infos."""
        results = self._get(self._pending)
        self._pending = []
        self.reset_infos = [r[4] for r in results]
        return (
            _stack([r[0] for r in results], self.observation_space),
            np.array([r[1] for r in results], dtype=np.float32),
            np.array([r[2] for r in results], dtype=bool),
            [r[3] for r in results],
        )

    def close(self) -> None:
        """Close the envs, stop the actors and the Ray this VecEnv started."""
        if self._closed:
            return
        self._closed = True
        if self._actors:
            with contextlib.suppress(Exception):  # a dead actor has nothing left to close
                self._ray.get([a.close.remote() for a in self._actors], timeout=30)
            kill_actors(self._ray, self._actors)
        self._session.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """An attribute of each env."""
        return self._get([self._actors[i].get_attr.remote(attr_name) for i in self._indices(indices)])

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute of each env."""
        self._get([self._actors[i].set_attr.remote(attr_name, value) for i in self._indices(indices)])

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any):
        """Call a method of each env; its results in env order."""
        calls = [
            self._actors[i].env_method.remote(method_name, method_args, method_kwargs) for i in self._indices(indices)
        ]
        return self._get(calls)

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        """Whether each env is wrapped by `wrapper_class`."""
        return self._get([self._actors[i].is_wrapped.remote(wrapper_class) for i in self._indices(indices)])

    def get_images(self) -> Sequence[np.ndarray | None]:
        """Each env's render (rgb_array envs)."""
        return self._get([a.render.remote() for a in self._actors])


def _stack(observations: list[Any], space: gymnasium.Space) -> VecEnvObs:
    """Per-env observations as one batch (per key for a Dict space, per item for a Tuple space)."""
    if isinstance(space, gymnasium.spaces.Dict):
        return {k: np.stack([o[k] for o in observations]) for k in space.spaces}
    if isinstance(space, gymnasium.spaces.Tuple):
        return tuple(np.stack([o[i] for o in observations]) for i in range(len(space.spaces)))
    return np.stack(observations)
