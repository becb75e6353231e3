"""ProcessBatchedVecEnv: the episodes of a BatchedVecEnv split over worker processes that step in parallel.

On a machine with several cores the simulator is the part of training that parallelizes: each worker holds a
`BatchedVecEnv` of its share of the episodes (one batched render per step) and steps it while the others step
theirs; the learner's process only sends actions and stacks what comes back. Episode i has seed `seed + i`, as in
one BatchedVecEnv of all the episodes, so both give the same observations, rewards and infos (tests/test_envs.py).

SB3's SubprocVecEnv does this with one process per episode; one process per core, each rendering several
episodes in one call, costs fewer messages and keeps the batched render.
"""

from __future__ import annotations

import contextlib
import multiprocessing
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvObs, VecEnvStepReturn

__all__ = ["ProcessBatchedVecEnv"]


def _worker(connection: Connection, kwargs: dict[str, Any], threads: int) -> None:
    """Serve one BatchedVecEnv over `connection` until told to close."""
    import torch

    from drivesim.sim.envs.vector import BatchedVecEnv

    torch.set_num_threads(threads)
    try:
        venv = BatchedVecEnv(**kwargs)
    except Exception as e:  # noqa: BLE001  (the env's own one-line errors go back to the learner's process)
        connection.send(("error", f"{type(e).__name__}: {e}"))
        connection.close()
        return
    connection.send(("ready", (venv.observation_space, venv.action_space)))
    while True:
        command, payload = connection.recv()
        if command == "step":
            venv.step_async(payload)
            connection.send(venv.step_wait())
        elif command == "reset":
            venv._seeds, venv._options = payload
            obs = venv.reset()
            connection.send((obs, venv.reset_infos))
        elif command == "expert":
            connection.send(venv.expert_actions())
        elif command == "get_attr":
            connection.send(venv.get_attr(*payload))
        elif command == "set_attr":
            connection.send(venv.set_attr(*payload))
        elif command == "env_method":
            name, args, kwargs_, indices = payload
            connection.send(venv.env_method(name, *args, indices=indices, **kwargs_))
        elif command == "close":
            venv.close()
            connection.close()
            return


class ProcessBatchedVecEnv(VecEnv):
    """`n_envs` episodes of `task` in `workers` processes, each a BatchedVecEnv of its share (SB3 VecEnv).

    :param task: a task of sim/envs/registry.py. :param n_envs: number of episodes.
    :param world: a world folder or a list of them. :param meshes: the meshes folder or None (procedural).
    :param mode: "train" or "eval". :param config: an EnvConfig, or a dict of keys over the task's (both pickle).
    :param seed: the first reset of episode i uses seed + i (None: random).
    :param workers: worker processes (at most n_envs). :param worker_threads: torch threads in each worker.
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
        workers: int = 2,
        worker_threads: int = 1,
    ) -> None:
        workers = max(1, min(int(workers), int(n_envs)))
        self._parts = [part.tolist() for part in np.array_split(np.arange(n_envs), workers)]
        context = multiprocessing.get_context("forkserver")  # no torch state forked into the workers
        self._connections: list[Connection] = []
        self._processes = []
        for part in self._parts:
            parent, child = context.Pipe()
            kwargs = {"task": task, "n_envs": len(part), "world": world, "meshes": meshes, "mode": mode,
                      "config": config}  # fmt: skip
            process = context.Process(target=_worker, args=(child, kwargs, worker_threads), daemon=True)
            process.start()
            child.close()
            self._connections.append(parent)
            self._processes.append(process)
        spaces = None
        for connection in self._connections:
            status, payload = connection.recv()
            if status == "error":
                self.close()
                raise ValueError(payload)
            spaces = payload
        assert spaces is not None
        super().__init__(n_envs, spaces[0], spaces[1])
        self._owner = [(k, j) for k, part in enumerate(self._parts) for j in range(len(part))]
        if seed is not None:
            self.seed(seed)

    def reset(self) -> VecEnvObs:
        """Reset every episode (with the seeds of `seed()` the first time)."""
        for connection, part in zip(self._connections, self._parts, strict=True):
            connection.send(("reset", ([self._seeds[i] for i in part], [self._options[i] for i in part])))
        observations = []
        for connection, part in zip(self._connections, self._parts, strict=True):
            obs, infos = connection.recv()
            observations.append(obs)
            for i, info in zip(part, infos, strict=True):
                self.reset_infos[i] = info
        self._reset_seeds()
        self._reset_options()
        return np.concatenate(observations)

    def step_async(self, actions: np.ndarray) -> None:
        """Send each worker its episodes' actions (n_envs, 1)."""
        actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)
        for connection, part in zip(self._connections, self._parts, strict=True):
            connection.send(("step", actions[part[0] : part[-1] + 1]))

    def step_wait(self) -> VecEnvStepReturn:
        """Gather every worker's step (finished episodes restarted, with terminal_observation in their info)."""
        results = [connection.recv() for connection in self._connections]
        obs = np.concatenate([r[0] for r in results])
        rewards = np.concatenate([r[1] for r in results])
        dones = np.concatenate([r[2] for r in results])
        infos = [info for r in results for info in r[3]]
        return obs, rewards, dones, infos

    def expert_actions(self) -> np.ndarray:
        """The privileged expert's actions for every episode now, (n_envs, 1) float32."""
        for connection in self._connections:
            connection.send(("expert", None))
        return np.concatenate([connection.recv() for connection in self._connections])

    def close(self) -> None:
        """Stop the workers."""
        for connection in self._connections:
            with contextlib.suppress(BrokenPipeError, EOFError, OSError):  # a worker that died is closed already
                connection.send(("close", None))
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
        self._connections, self._processes = [], []

    def _by_worker(self, indices: Any) -> dict[int, list[int]]:
        if indices is None:
            indices = range(self.num_envs)
        elif isinstance(indices, int):
            indices = [indices]
        grouped: dict[int, list[int]] = {}
        for i in indices:
            k, j = self._owner[i]
            grouped.setdefault(k, []).append(j)
        return grouped

    def _call(self, command: str, make_payload: Any, indices: Any) -> list[Any]:
        grouped = self._by_worker(indices)
        for k, local in grouped.items():
            self._connections[k].send((command, make_payload(local)))
        out: list[Any] = []
        for k in grouped:
            result = self._connections[k].recv()
            out.extend(result if isinstance(result, list) else [])
        return out

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """An attribute of each env (picklable values only)."""
        return self._call("get_attr", lambda local: (attr_name, local), indices)

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set an attribute of each env."""
        self._call("set_attr", lambda local: (attr_name, value, local), indices)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        """Call a method of each env (picklable results only)."""
        return self._call("env_method", lambda local: (method_name, method_args, method_kwargs, local), indices)

    def env_is_wrapped(self, wrapper_class: type[gymnasium.Wrapper], indices: Any = None) -> list[bool]:
        """The envs are not wrapped."""
        grouped = self._by_worker(indices)
        return [False for local in grouped.values() for _ in local]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """Not available across processes."""
        return [None] * self.num_envs
