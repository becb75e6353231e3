"""The Ray backend of `drivesim eval`: the episodes of `run_episodes`, sharded over the workers of a Ray cluster.

Each Ray actor (`EpisodeWorker`) builds the env and loads the policy once, then runs the seeds it is fed, at most
`IN_FLIGHT_PER_ACTOR` at a time (every actor stays busy, and a dead one takes little work with it). The driver writes
each `episodes/<seed>.json` atomically the moment its record arrives, as the local workers do, so resuming, the
metrics and the report are those of the local backend; an episode depends only on its seed, so the same seeds give
the same files on both. A seed whose actor (or node) dies is put back at the head of the queue for the other actors,
and a replacement actor is started, used once Ray can place it. A seed is written once: its result either arrived
(written, never resubmitted) or was lost (resubmitted, written when it arrives).
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.ray_cluster import (
    RaySession,
    cluster_cpus,
    cpus_per_actor,
    get_or_lost,
    is_lost_worker,
    kill_actors,
)
from drivesim.stages.evaluate.metrics import EpisodeRecord, evaluate_episode
from drivesim.stages.evaluate.rollout import (
    EnvFactory,
    EpisodeDone,
    PolicySpec,
    env_limits,
    limit_worker_threads,
    run_episode,
    seeds_to_run,
    write_episode,
)

IN_FLIGHT_PER_ACTOR = 2
ACTOR_START_TIMEOUT_S = 600.0
"""How long to wait for an actor to start when no episode is running (a cluster without room for one)."""


@dataclass(frozen=True)
class RayEvalOutcome:
    """What an evaluation on Ray did.

    :param episodes_run: episodes run and written now (the ones already on disk not counted).
    :param actors: actors started at first (the evaluation's workers).
    :param resubmitted: episodes run again because their actor or its node died.
    :param nodes: distinct nodes whose actors returned episodes.
    """

    episodes_run: int
    actors: int
    resubmitted: int
    nodes: int


@dataclass(frozen=True)
class RayEpisodeDone(EpisodeDone):
    """What the progress display learns of each finished episode, and the Ray node that ran it."""

    node: str = ""


class EpisodeWorker:
    """One env and one policy, built once in a Ray actor; runs the seeds it is given (`ray.remote` makes it an actor
    at run time, so importing this module needs no Ray).

    :param env_factory: builds the env. :param policy_spec: the policy. :param task: recorded with each episode.
    """

    def __init__(self, env_factory: EnvFactory, policy_spec: PolicySpec, task: str) -> None:
        limit_worker_threads()
        self.env = env_factory()
        self.policy = policy_spec.load(self.env)
        self.task = task
        self.limits = env_limits(self.env)

    def node_id(self) -> str:
        """The Ray node this actor runs on (also: the actor is ready)."""
        import ray

        return ray.get_runtime_context().get_node_id()

    def run(self, seed: int) -> tuple[EpisodeRecord, str]:
        """One episode from `seed`, and the node that ran it."""
        return run_episode(self.env, self.policy, seed, self.task, self.limits), self.node_id()


class _Actors:
    """The evaluation's actors: starting (their first call in flight), ready, and replacements for the dead ones."""

    def __init__(self, ray: ModuleType, actor_class: Any, args: tuple[Any, ...], count: int) -> None:
        self.ray, self.actor_class, self.args = ray, actor_class, args
        self.starting: dict[Any, Any] = {}  # first call's ObjectRef -> actor
        self.ready: list[Any] = []
        self.every: list[Any] = []
        self.gone: set[int] = set()
        self.max_starts = 2 * count + 2  # a node lost or two, not an env that cannot start anywhere
        self.last_error = ""
        for _ in range(count):
            self.start()

    def start(self) -> None:
        """Start one actor (unless too many have died already)."""
        if len(self.every) >= self.max_starts:
            return
        actor = self.actor_class.remote(*self.args)
        self.every.append(actor)
        self.starting[actor.node_id.remote()] = actor

    def on_started(self, ref: Any) -> None:
        """An actor's first call returned: it is ready, or it failed to start (then it is replaced)."""
        actor = self.starting.pop(ref)
        try:
            self.ray.get(ref)
        except Exception as e:
            if not is_lost_worker(e):
                raise
            self.last_error = str(e).strip().splitlines()[-1][:200] if str(e).strip() else type(e).__name__
            self.replace(actor)
            return
        self.ready.append(actor)

    def replace(self, actor: Any) -> None:
        """Stop a dead actor and start another (once per actor, however many of its calls failed)."""
        if id(actor) in self.gone:
            return
        self.gone.add(id(actor))
        if actor in self.ready:
            self.ready.remove(actor)
        kill_actors(self.ray, [actor])
        self.start()

    def close(self) -> None:
        """Stop every actor, the ones still waiting for room included."""
        kill_actors(self.ray, self.every)


def run_episodes_ray(
    env_factory: EnvFactory,
    policy_spec: PolicySpec,
    task: str,
    seeds: list[int],
    folder: Path,
    address: str | None = None,
    workers: int | None = None,
    on_episode: Callable[[EpisodeDone], None] | None = None,
) -> RayEvalOutcome:
    """Run every seed whose episode file is not in `folder` yet on Ray actors; the driver writes each file.

    The other arguments as `rollout.run_episodes`, an actor in a worker's place (it builds the env and loads the
    policy once).
    :param address: the Ray cluster ("auto", host:port); None starts Ray on this machine.
    :param workers: actors to start; None = one per CPU of the cluster.
    :param on_episode: called in this process after each episode is written (progress display).
    """
    todo = seeds_to_run(folder, seeds)
    if not todo:
        return RayEvalOutcome(0, 0, 0, 0)
    with RaySession(address) as ray:
        count = max(1, min(workers or int(cluster_cpus(ray)), len(todo)))
        actor_class = ray.remote(num_cpus=cpus_per_actor(ray, count), scheduling_strategy="SPREAD")(EpisodeWorker)
        actors = _Actors(ray, actor_class, (env_factory, policy_spec, task), count)
        try:
            run, resubmitted, nodes = _drive(ray, actors, todo, folder, on_episode)
        finally:
            actors.close()
    return RayEvalOutcome(run, count, resubmitted, nodes)


def _drive(
    ray: ModuleType,
    actors: _Actors,
    todo: list[int],
    folder: Path,
    on_episode: Callable[[EpisodeDone], None] | None,
) -> tuple[int, int, int]:
    """Feed seeds to the ready actors and write results as they come; returns (episodes, resubmitted, nodes)."""
    queue = deque(todo)
    in_flight: dict[Any, tuple[Any, int]] = {}
    load: Counter[int] = Counter()
    written: set[int] = set()
    nodes: set[str] = set()
    resubmitted = 0
    while queue or in_flight:
        for actor in list(actors.ready):
            while queue and load[id(actor)] < IN_FLIGHT_PER_ACTOR:
                seed = queue.popleft()
                in_flight[actor.run.remote(seed)] = (actor, seed)
                load[id(actor)] += 1
        pending = [*in_flight, *actors.starting]
        if not pending:
            raise DrivesimError(
                f"no Ray worker is left to run the last {len(queue)} episodes: {len(actors.every)} started and died "
                f"(last error: {actors.last_error or 'none'}); the finished episodes are kept, the same command resumes"
            )
        started = time.monotonic()
        done, _ = ray.wait(pending, num_returns=1, timeout=None if in_flight else ACTOR_START_TIMEOUT_S)
        if not done:
            raise DrivesimError(
                f"no Ray worker could start in {time.monotonic() - started:.0f} s (is there a free CPU on the "
                "cluster?); run the same command again to finish"
            )
        for ref in done:
            if ref in actors.starting:
                actors.on_started(ref)
                continue
            actor, seed = in_flight.pop(ref)
            load[id(actor)] -= 1
            result, lost_error = get_or_lost(ray, ref)
            if lost_error is not None:
                queue.appendleft(seed)
                resubmitted += 1
                actors.replace(actor)
                continue
            record, node = result
            if seed in written:
                continue
            write_episode(folder, record)
            written.add(seed)
            nodes.add(node)
            if on_episode:
                on_episode(RayEpisodeDone(seed, evaluate_episode(record).metrics.intervention, record.steps, node))
    return len(written), resubmitted, len(nodes)
