"""Closed-loop evaluation episodes with fixed seeds, in worker processes, each written to disk as it ends.

Episode i of an evaluation with seed S is `env.reset(seed=S + i)` driven by the policy (deterministic actions, its
recurrent state reset at the episode's start) until the env ends it. An episode depends only on its seed, so one
worker or many give the same numbers. Each worker is a process (`spawn`: no torch state is forked) that builds the
env and loads the policy once, then runs the seeds it is given; it writes `episodes/<seed>.json` atomically (a
temporary file moved into place) the moment the episode ends, so an interrupted evaluation loses at most the
episodes in flight and `run_episodes` skips the seeds already on disk when it is started again.
"""

from __future__ import annotations

import json
import os
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.processes import end_with_parent, stop_processes
from drivesim.stages.evaluate.metrics import TRAJECTORY_FIELDS, EpisodeRecord, evaluate_episode

if TYPE_CHECKING:
    from drivesim.sim.episode_mcap import EpisodeCapture
    from drivesim.stages.evaluate.record import RecordPlan

EPISODES_DIR = "episodes"


class Policy(Protocol):
    """What the rollout needs of a policy (LoadedPolicy, OnnxPolicy and the expert have it)."""

    def initial_state(self, n: int) -> Any: ...

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]: ...


@dataclass(frozen=True)
class EnvFactory:
    """How a worker builds its env (picklable, so `spawn` workers can rebuild it).

    :param env_id: the gymnasium id, e.g. "drivesim/Overtake-v0".
    :param kwargs: keyword arguments of `gymnasium.make` (world, meshes, mode, config).
    :param entry_point: "module:Class" to register `env_id` with first when it is not registered (a user's own env).
    :param trusted: whether `entry_point` may name a class outside drivesim's envs (`--trust-entry-point`); either
        way it must be a `gymnasium.Env` subclass (`stages/evaluate/entry_point.py`).
    """

    env_id: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    entry_point: str | None = None
    trusted: bool = False

    def __call__(self) -> Any:
        """A new env."""
        import gymnasium

        if self.env_id.startswith("drivesim/"):
            import drivesim.sim.envs  # noqa: F401  (registers the drivesim envs)
        if self.entry_point is not None and self.env_id not in gymnasium.registry:
            from drivesim.stages.evaluate.entry_point import env_class

            # The checked class itself, so gymnasium imports and calls nothing else than what was checked.
            gymnasium.register(self.env_id, entry_point=env_class(self.entry_point, self.trusted))
        return gymnasium.make(self.env_id, **self.kwargs)


class ExpertPolicy:
    """The env's privileged expert (`env.unwrapped.expert_action()`) behind the policy interface."""

    def __init__(self, env: Any) -> None:
        self.env = env

    def initial_state(self, n: int) -> None:
        """The expert keeps no state."""
        return None

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """The expert's action for the env's current state, shaped (1, 1)."""
        return np.asarray(self.env.unwrapped.expert_action(), dtype=np.float32).reshape(1, -1), None


class RandomPolicy:
    """Uniform random steering in [-1, 1] (the baseline of the learning tables), drawn from the episode's seed so
    an episode is the same in any worker."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.rng = np.random.default_rng(0)

    def initial_state(self, n: int) -> None:
        """No state."""
        return None

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """A random action, shaped (1, 1)."""
        if bool(np.asarray(episode_start).reshape(-1)[0]):
            self.rng = np.random.default_rng(self.env.unwrapped.np_random_seed)  # the seed of the env's reset
        return self.rng.uniform(-1.0, 1.0, (1, 1)).astype(np.float32), None


class StraightPolicy:
    """No steering at all (action 0 at every step): the baseline that shows how much of a lane task a drive's own
    geometry already passes."""

    def initial_state(self, n: int) -> None:
        """No state."""
        return None

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, Any]:
        """Zero steering, shaped (1, 1)."""
        return np.zeros((1, 1), dtype=np.float32), None


@dataclass(frozen=True)
class PolicySpec:
    """Which policy to evaluate (picklable): "expert", a run folder ("run") or an ONNX file ("onnx").

    :param kind: "expert", "random", "straight", "run" or "onnx".
    :param path: the run folder or the .onnx file (None for the expert).
    """

    kind: str
    path: str | None = None

    @classmethod
    def parse(cls, text: str) -> PolicySpec:
        """`expert`, a path ending in `.onnx`, or a run folder."""
        if text in ("expert", "random", "straight"):
            return cls(text)
        if text.lower().endswith(".onnx"):
            return cls("onnx", str(Path(text).absolute()))
        return cls("run", str(Path(text).absolute()))

    @property
    def label(self) -> str:
        """A short name: "expert", the run folder's name or the ONNX file's stem."""
        return self.kind if self.path is None else Path(self.path).stem if self.kind == "onnx" else Path(self.path).name

    def load(self, env: Any) -> Policy:
        """The policy (DrivesimError with one line for a bad run folder or ONNX file)."""
        if self.kind == "expert":
            return ExpertPolicy(env)
        if self.kind == "random":
            return RandomPolicy(env)
        if self.kind == "straight":
            return StraightPolicy()
        if self.kind == "run":
            from drivesim.policy.run_folder import load_policy

            return load_policy(Path(self.path))
        try:
            from drivesim.policy.onnx_runtime import OnnxPolicy
        except ImportError as e:
            raise DrivesimError("this version of drivesim cannot run ONNX policies (no policy.onnx_runtime)") from e
        return OnnxPolicy(Path(self.path))


def env_limits(env: Any) -> dict[str, float]:
    """The env's Z_lat / Z_rot / Z_pass when its config names them (recorded with each episode), else {}."""
    config = getattr(env.unwrapped, "config", None)
    limits = {}
    for key, names in (
        ("max_lateral_m", ("max_lateral_m", "z_lat_m", "off_lane_m", "max_q_lat_m")),
        ("max_rotation_rad", ("max_rotation_rad", "z_rot_rad", "max_q_rot_rad")),
        ("pass_distance_m", ("pass_distance_m",)),
    ):
        for name in names:
            value = getattr(config, name, None)
            if isinstance(value, int | float):
                limits[key] = float(value)
                break
    return limits


def run_episode(
    env: Any,
    policy: Policy,
    seed: int,
    task: str,
    limits: dict[str, float] | None = None,
    capture: EpisodeCapture | None = None,
) -> EpisodeRecord:
    """One closed-loop episode from `env.reset(seed=seed)` until the env ends it; `capture` (when given) keeps each
    step's observation and info for a recording (`stages/evaluate/record.py`)."""
    obs, info = env.reset(seed=seed)
    if capture is not None:
        capture.add(obs, info, 0.0)
    rows = [_state_row(info.get("state", {}), 0.0)]
    state = policy.initial_state(1)
    episode_start = np.ones(1, dtype=bool)
    total = 0.0
    while True:
        action, state = policy.predict(obs[None], state, episode_start, deterministic=True)
        action = np.asarray(action, dtype=np.float32).reshape(-1)
        episode_start = np.zeros(1, dtype=bool)
        obs, reward, terminated, truncated, step_info = env.step(action)
        total += float(reward)
        rows.append(_state_row(step_info.get("state", {}), float(action[0])))
        if capture is not None:
            capture.add(obs, step_info, float(action[0]))
        if terminated or truncated:
            break
    termination = {k: bool(v) for k, v in step_info.get("termination", {}).items()}
    termination.setdefault("time_limit", bool(truncated and not terminated))
    trajectory = {name: np.array([r[i] for r in rows], dtype=float) for i, name in enumerate(TRAJECTORY_FIELDS)}
    return EpisodeRecord(
        seed=int(seed),
        task=task,
        episode=_json_safe(info.get("episode", {})),
        trajectory=trajectory,
        termination=termination,
        success=bool(step_info.get("success", False)),
        return_=total,
        limits=dict(limits or {}),
    )


def _state_row(state: dict[str, Any], action: float) -> tuple[float, ...]:
    values = {**state, "action": action}
    return tuple(float(values.get(name, np.nan)) for name in TRAJECTORY_FIELDS)


def _json_safe(data: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, np.generic):
            value = value.item()
        out[key] = value if isinstance(value, str | int | float | bool | type(None)) else str(value)
    return out


def write_episode(folder: Path, record: EpisodeRecord) -> Path:
    """Write `folder/<seed>.json` atomically (temporary file, then os.replace)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{record.seed}.json"
    tmp = folder / f".{record.seed}.json.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(record.to_json(), separators=(",", ":")) + "\n")
    os.replace(tmp, path)
    return path


def read_episode(path: Path) -> EpisodeRecord | None:
    """An episode file, or None when it is unreadable (it is then run again)."""
    try:
        return EpisodeRecord.from_json(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def completed_seeds(folder: Path, seeds: Iterable[int]) -> set[int]:
    """The seeds whose episode files are on disk and readable (the folder is listed once, each file read once)."""
    try:
        with os.scandir(folder) as entries:
            on_disk = {entry.name for entry in entries if entry.is_file()}
    except (FileNotFoundError, NotADirectoryError):
        return set()
    return {s for s in set(seeds) if f"{s}.json" in on_disk and read_episode(folder / f"{s}.json") is not None}


def seeds_to_run(folder: Path, seeds: list[int]) -> list[int]:
    """The seeds of `seeds` (in their order) whose episode file is not in `folder` yet, found in one pass."""
    done = completed_seeds(folder, seeds)
    return [s for s in seeds if s not in done]


@dataclass(frozen=True)
class EpisodeDone:
    """What the progress display learns of each finished episode."""

    seed: int
    intervention: bool
    steps: int


# One env and policy per worker process, built once by `_init_worker`.
_WORKER: dict[str, Any] = {}


def _init_worker(
    env_factory: EnvFactory,
    policy_spec: PolicySpec,
    task: str,
    folder: str,
    parent_pid: int | None = None,
    record: RecordPlan | None = None,
) -> None:
    if parent_pid is not None:  # a worker process: it ends with the evaluation, whatever ends that
        end_with_parent(parent_pid)
    limit_worker_threads()
    env = env_factory()
    _WORKER.update(env=env, policy=policy_spec.load(env), task=task, folder=Path(folder), limits=env_limits(env))
    if record is not None:
        from drivesim.stages.evaluate.record import EpisodeRecorder

        _WORKER["recorder"] = EpisodeRecorder(record, task, _WORKER["limits"])


def limit_worker_threads() -> None:
    """One thread per worker: workers already use every core, and one thread keeps the numbers identical."""
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass


def _worker_episode(seed: int) -> EpisodeDone:
    recorder = _WORKER.get("recorder")
    capture = recorder.begin(seed) if recorder is not None else None
    record = run_episode(_WORKER["env"], _WORKER["policy"], seed, _WORKER["task"], _WORKER["limits"], capture)
    intervention = evaluate_episode(record).metrics.intervention
    if recorder is not None:  # the recording first: an episode on disk has its recording
        recorder.end(capture, intervention)
    write_episode(_WORKER["folder"], record)
    return EpisodeDone(seed, intervention, record.steps)


def default_workers() -> int:
    """One worker per core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


WORKER_MEMORY_BYTES = 600 * 2**20
"""Memory one worker process is counted for: its imports alone (torch, onnxruntime, gymnasium, drivesim's envs) take
about 300 MiB resident, and its env, renderer buffers and policy come on top."""


def capped_workers(requested: int | None, episodes: int) -> tuple[int, str | None]:
    """Worker processes for `episodes` episodes: `requested` (None: one per core) capped by the episodes, by the
    cores this process may use and by the memory available now (`WORKER_MEMORY_BYTES` each); with one line for the
    user when the cores or the memory lowered a requested number (None otherwise).
    """
    import psutil

    cores = default_workers()
    available = psutil.virtual_memory().available
    by_memory = max(1, int(available // WORKER_MEMORY_BYTES))
    wanted = min(cores if requested is None else max(1, requested), max(1, episodes))
    workers = min(wanted, cores, by_memory)
    if requested is None or workers >= wanted:
        return workers, None
    why = (
        f"{cores} cores available to this process"
        if workers == cores
        else f"{available / 2**30:.1f} GiB of memory available, about {WORKER_MEMORY_BYTES / 2**20:.0f} MiB per worker"
    )
    return workers, f"--workers {requested} lowered to {workers}: {why}"


def run_episodes(
    env_factory: EnvFactory,
    policy_spec: PolicySpec,
    task: str,
    seeds: list[int],
    folder: Path,
    workers: int = 1,
    on_episode: Callable[[EpisodeDone], None] | None = None,
    record: RecordPlan | None = None,
) -> int:
    """Run every seed whose episode file is not in `folder` yet; returns how many episodes were run now.

    :param env_factory: builds the env (once per worker).
    :param policy_spec: the policy (loaded once per worker).
    :param task: the task name recorded with each episode.
    :param seeds: every seed of the evaluation.
    :param folder: where `<seed>.json` files go (and are found when resuming).
    :param workers: worker processes; 1 runs in this process.
    :param on_episode: called in this process after each episode (progress display).
    :param record: which episodes the workers write as MCAP recordings (`stages/evaluate/record.py`); None: none.
    """
    todo = seeds_to_run(folder, seeds)
    if not todo:
        return 0
    if workers <= 1:
        _init_worker(env_factory, policy_spec, task, str(folder), record=record)
        try:
            for seed in todo:
                done = _worker_episode(seed)
                if on_episode:
                    on_episode(done)
        finally:
            _close_worker()
        return len(todo)
    ctx = get_context("spawn")
    with ProcessPoolExecutor(
        max_workers=min(workers, len(todo)),
        mp_context=ctx,
        initializer=_init_worker,
        initargs=(env_factory, policy_spec, task, str(folder), os.getpid(), record),
    ) as pool:
        # A bounded number in flight, so Ctrl-C stops soon and the pool does not queue every seed up front.
        pending = set()
        queue = deque(todo)
        try:
            while queue or pending:
                while queue and len(pending) < 2 * workers:
                    pending.add(pool.submit(_worker_episode, queue.popleft()))
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    done = future.result()
                    if on_episode:
                        on_episode(done)
        except BaseException:
            # Ctrl-C, SIGTERM or an error: stop the workers now rather than wait for their episodes in flight.
            for future in pending:
                future.cancel()
            workers_alive = list(getattr(pool, "_processes", {}).values())  # the pool offers no public handle
            pool.shutdown(wait=False, cancel_futures=True)
            stop_processes(workers_alive)
            raise
    return len(todo)


def remove_stale_temporaries(folder: Path) -> int:
    """Remove the `.<seed>.json.<pid>.tmp` files a killed worker left half-written; returns how many."""
    stale = list(folder.glob(".*.json.*.tmp")) if folder.is_dir() else []
    for path in stale:
        path.unlink(missing_ok=True)
    return len(stale)


def _close_worker() -> None:
    env = _WORKER.pop("env", None)
    _WORKER.clear()
    if env is not None:
        env.close()


class RunningRate:
    """Episodes per second and the running intervention rate, for the progress bar."""

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.count = 0
        self.interventions = 0

    def add(self, done: EpisodeDone) -> str:
        """Count an episode; returns the progress description."""
        self.count += 1
        self.interventions += int(done.intervention)
        rate = self.count / max(time.perf_counter() - self.started, 1e-9)
        return f"eval {rate:.2f} ep/s, intervention {self.interventions / self.count:.3f}"
