"""Benchmark of `drivesim eval --backend ray`: episodes per minute on this machine with local worker processes and with
Ray actors (Ray's overhead), the time to start Ray and its actors, and on paper the scaling to 16 nodes from the
measured per-episode cost, the driver's cost per episode and the bytes sent back per episode.

    .venv/bin/python benchmarks/bench_ray.py --world WS/world --episodes 200       # expert, 200 episodes per backend
    .venv/bin/python benchmarks/bench_ray.py --episodes 4 --world WS/world --out /tmp/ray.md   # a quick check

Both backends run the same seeds through the same episode loop as `drivesim eval` (stages/evaluate: `run_episodes`,
`run_episodes_ray`); the files must be identical (checked). Without --world it builds the demo world as `make demo`
does (benchmarks/bench_eval.py). Writes benchmarks/results/ray.md.
"""

from __future__ import annotations

import argparse
import os
import pickle
import tempfile
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from _lib.report import write_markdown
from _lib.throughput import node_rows
from bench_eval import build_demo_world

from drivesim.bench.machine import machine_line, usable_cores
from drivesim.pipeline.ray_cluster import RaySession
from drivesim.sim.envs.registry import task_spec
from drivesim.stages.evaluate.metrics import evaluate_episode
from drivesim.stages.evaluate.ray_backend import run_episodes_ray
from drivesim.stages.evaluate.rollout import (
    EnvFactory,
    PolicySpec,
    read_episode,
    run_episodes,
    write_episode,
)

RESULTS = Path(__file__).resolve().parent / "results" / "ray.md"
NODE_COUNTS = (1, 2, 4, 8, 16)


@dataclass
class LoopTiming:
    """When each episode of one backend's run arrived in the driver."""

    backend: str
    workers: int
    started_s: float = 0.0
    arrivals_s: list[float] = field(default_factory=list)
    ended_s: float = 0.0

    def record(self, _done: object) -> None:
        """The progress callback: note the arrival time."""
        self.arrivals_s.append(time.perf_counter())

    @property
    def wall_s(self) -> float:
        """Call to return: worker start (world and policy loaded once each) and every episode."""
        return self.ended_s - self.started_s

    @property
    def first_episode_s(self) -> float:
        """Call to the first episode back: worker start plus one episode."""
        return self.arrivals_s[0] - self.started_s

    @property
    def per_min_end_to_end(self) -> float:
        """Episodes per minute, worker start included."""
        return 60 * len(self.arrivals_s) / self.wall_s

    @property
    def per_min_steady(self) -> float | None:
        """Episodes per minute between the first and the last episode (workers running), None for < 3 episodes."""
        if len(self.arrivals_s) < 3:
            return None
        return 60 * (len(self.arrivals_s) - 1) / (self.arrivals_s[-1] - self.arrivals_s[0])


def run_local(factory: EnvFactory, seeds: list[int], folder: Path, workers: int) -> LoopTiming:
    """The local backend's episode loop (spawned worker processes)."""
    timing = LoopTiming("local", workers, started_s=time.perf_counter())
    run_episodes(factory, PolicySpec("expert"), "overtake", seeds, folder, workers=workers, on_episode=timing.record)
    timing.ended_s = time.perf_counter()
    return timing


def run_ray(factory: EnvFactory, seeds: list[int], folder: Path, workers: int, address: str | None) -> LoopTiming:
    """The Ray backend's episode loop (Ray already connected: its start is measured apart)."""
    timing = LoopTiming("ray", workers, started_s=time.perf_counter())
    run_episodes_ray(factory, PolicySpec("expert"), "overtake", seeds, folder, address, workers, timing.record)
    timing.ended_s = time.perf_counter()
    return timing


def transfer_and_driver_cost(folder: Path) -> tuple[float, float, float, float]:
    """Per episode: bytes an actor sends back (the pickled record), bytes of its JSON file, driver seconds to write
    the file and compute its metrics (the serial part of the Ray backend), and mean steps."""
    records = [read_episode(p) for p in sorted(folder.glob("*.json"))]
    records = [r for r in records if r is not None]
    sent = [len(pickle.dumps((r, "f" * 56), protocol=5)) for r in records]  # the record and the node id
    on_disk = [p.stat().st_size for p in folder.glob("*.json")]
    with tempfile.TemporaryDirectory(prefix="bench-ray-driver-") as tmp:
        start = time.perf_counter()
        for r in records:
            write_episode(Path(tmp), r)
            evaluate_episode(r)
        driver_s = (time.perf_counter() - start) / len(records)
    steps = sum(r.steps for r in records) / len(records)
    return sum(sent) / len(sent), sum(on_disk) / len(on_disk), driver_s, steps


def _fmt(value: float | None, pattern: str = "{:.1f}") -> str:
    return "n/a" if value is None else pattern.format(value)


@dataclass
class Measured:
    """Everything the report shows."""

    world: Path
    local: LoopTiming
    on_ray: LoopTiming
    ray_start_s: float
    nodes: int
    same_files: bool
    load_start: float
    load_end: float
    bytes_sent: float
    bytes_file: float
    driver_s: float
    steps: float


def main() -> None:
    """Run the benchmark and write its markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per backend (the same seeds)")
    parser.add_argument("--workers", type=int, default=usable_cores(), help="worker processes / Ray actors")
    parser.add_argument("--world", type=Path, default=None, help="world folder (default: build the demo world)")
    parser.add_argument("--meshes", type=Path, default=None, help="mesh library (default: the procedural one)")
    parser.add_argument("--address", default=None, help="a running Ray cluster (default: start Ray here)")
    parser.add_argument("--cores-per-node", type=int, default=usable_cores(), help="for the projection")
    parser.add_argument("--bandwidth-gbps", type=float, default=1.0, help="the head's link, for the projection")
    parser.add_argument("--out", type=Path, default=RESULTS, help="markdown report")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-ray-") as tmp:
        world = args.world.absolute() if args.world else build_demo_world(Path(tmp) / "ws")
        measured = measure(args, world, Path(tmp))
    write_markdown(args.out, report(args, measured), raw_figures(args, measured))


def raw_figures(args: argparse.Namespace, m: Measured) -> dict:
    """The figures the report shows, unrounded, for the JSON beside it."""
    backends = [
        {
            "backend": t.backend,
            "workers": t.workers,
            "episodes": len(t.arrivals_s),
            "first_episode_s": t.first_episode_s,
            "wall_s": t.wall_s,
            "episodes_per_min_end_to_end": t.per_min_end_to_end,
            "episodes_per_min_steady": t.per_min_steady,
        }
        for t in (m.local, m.on_ray)
    ]
    return {
        "world": str(m.world),
        "address": args.address,
        "nodes": m.nodes,
        "load_average_start_end": [m.load_start, m.load_end],
        "backends": backends,
        "ray_start_s": m.ray_start_s,
        "same_episode_files": m.same_files,
        "bytes_sent_per_episode": m.bytes_sent,
        "bytes_file_per_episode": m.bytes_file,
        "driver_s_per_episode": m.driver_s,
        "steps_per_episode": m.steps,
        "cores_per_node": args.cores_per_node,
        "bandwidth_gbps": args.bandwidth_gbps,
    }


def measure(args: argparse.Namespace, world: Path, tmp: Path) -> Measured:
    """Both backends on the same seeds, Ray's start, and the per-episode transfer and driver cost."""
    seeds = list(range(args.episodes))
    meshes = None if args.meshes is None else str(args.meshes.absolute())
    factory = EnvFactory(task_spec("overtake").env_id, {"world": str(world), "meshes": meshes, "mode": "eval"})
    load_start = os.getloadavg()[0]
    local = run_local(factory, seeds, tmp / "local", args.workers)
    print(f"local: {args.episodes} episodes in {local.wall_s:.1f} s", flush=True)
    start = time.perf_counter()
    session = RaySession(args.address)
    ray = session.open()
    ray_start_s = time.perf_counter() - start
    try:
        nodes = len([n for n in ray.nodes() if n.get("Alive")])
        on_ray = run_ray(factory, seeds, tmp / "ray", args.workers, args.address)
    finally:
        session.close()
    print(f"ray: started in {ray_start_s:.1f} s, {args.episodes} episodes in {on_ray.wall_s:.1f} s", flush=True)
    load_end = os.getloadavg()[0]
    bytes_sent, bytes_file, driver_s, steps = transfer_and_driver_cost(tmp / "ray")
    same = _same_files(tmp / "local", tmp / "ray")
    return Measured(world, local, on_ray, ray_start_s, nodes, same, load_start, load_end, bytes_sent, bytes_file,
                    driver_s, steps)  # fmt: skip


def _same_files(a: Path, b: Path) -> bool:
    names = sorted(p.name for p in a.glob("*.json"))
    return names == sorted(p.name for p in b.glob("*.json")) and all(
        (a / n).read_bytes() == (b / n).read_bytes() for n in names
    )


def _rate_ratio(local: LoopTiming, on_ray: LoopTiming) -> float | None:
    """Ray's steady-state episodes per minute over the local workers' (below 1: Ray's overhead)."""
    if local.per_min_steady is None or on_ray.per_min_steady is None:
        return None
    return on_ray.per_min_steady / local.per_min_steady


def report(args: argparse.Namespace, m: Measured) -> list[str]:
    """The markdown lines."""
    cmd = f"python benchmarks/bench_ray.py --episodes {args.episodes} --workers {args.workers}"
    cmd += f" --world {args.world}" if args.world else ""
    cmd += f" --meshes {args.meshes}" if args.meshes else ""
    cmd += f" --address {args.address}" if args.address else ""
    local, on_ray = m.local, m.on_ray
    core_s = 60 * local.workers / (local.per_min_steady or local.per_min_end_to_end)  # one core's s per episode
    where = "started on this machine" if args.address is None else args.address
    lines = [
        "# ray: evaluation on Ray (`drivesim eval --backend ray`)",
        "",
        f"Machine: {machine_line()} (load average {m.load_start:.1f} at start, {m.load_end:.1f} at the end). "
        f"Date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}. World: {m.world}. Task: overtake, the expert. "
        f"Ray: {where}, {m.nodes} node(s). Reproduce: `{cmd}`.",
        "",
        "| backend | workers | episodes | first episode back | wall (workers started, every episode) | "
        "episodes / min, end to end | episodes / min, steady state |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in (local, on_ray):
        lines.append(
            f"| {t.backend} | {t.workers} | {len(t.arrivals_s)} | {t.first_episode_s:.1f} s | {t.wall_s:.1f} s | "
            f"{t.per_min_end_to_end:.1f} | {_fmt(t.per_min_steady)} |"
        )
    lines += [
        "",
        f"- Starting Ray on this machine (`ray.init`, one head node, no dashboard): {m.ray_start_s:.1f} s. Then the "
        "actors start (each imports drivesim and torch and loads the world and the policy once): the Ray row's "
        f"first episode came back {on_ray.first_episode_s:.1f} s after the call, the local row's "
        f"{local.first_episode_s:.1f} s.",
        f"- Ray's steady-state rate is {_fmt(_rate_ratio(local, on_ray), '{:.2f}')}x the local worker processes' "
        "on this machine (same cores, same seeds; below 1 is Ray's overhead).",
        f"- The same seeds gave {'identical' if m.same_files else 'DIFFERENT'} episode files on both backends.",
        f"- Per episode ({m.steps:.0f} steps on average): one core works {core_s:.2f} s (local steady state x "
        f"workers); an actor sends back {m.bytes_sent / 1e3:.1f} kB (the pickled record; the request is a seed); the "
        f"driver writes a {m.bytes_file / 1e3:.1f} kB JSON file and spends {1e3 * m.driver_s:.1f} ms writing it and "
        "computing its metrics (the driver's serial share).",
        "",
    ]
    return lines + projection(args, m, core_s)


def projection(args: argparse.Namespace, m: Measured, core_s: float) -> list[str]:
    """On paper: expected episodes per minute on 1-16 nodes, the least of compute, the driver and the network."""
    driver_limit = 60 / m.driver_s
    network_limit = 60 * args.bandwidth_gbps * 1e9 / 8 / m.bytes_sent
    startup_min = (m.ray_start_s + m.on_ray.first_episode_s) / 60
    lines = [
        f"## On paper: {args.cores_per_node} cores per node, up to {NODE_COUNTS[-1]} nodes",
        "",
        f"Expected episodes per minute = the least of compute (nodes x {args.cores_per_node} cores / {core_s:.2f} "
        f"core-s per episode), the driver (1 / {1e3 * m.driver_s:.1f} ms = {driver_limit:,.0f}) and the head's "
        f"{args.bandwidth_gbps:g} Gbit/s link ({network_limit:,.0f}); Ray's overhead measured above is not "
        "counted. Every node must hold the world (memory-mapped; a shared file system or a copy). 1000 episodes "
        "take the expected rate plus the measured start (Ray and the first episode back; nodes join in parallel); "
        "the paper evaluated 1000 episodes per environment.",
        "",
        "| nodes | cores | compute bound (episodes / min) | expected (episodes / min) | limited by | "
        "1000 episodes take |",
        "|---|---|---|---|---|---|",
    ]
    limits = (driver_limit, network_limit)
    minutes = lambda rate: f"{1000 / rate + startup_min:.1f} min"  # noqa: E731
    return [*lines, *node_rows(NODE_COUNTS, args.cores_per_node, 60 / core_s, limits, ",.0f", minutes), ""]


if __name__ == "__main__":
    main()
