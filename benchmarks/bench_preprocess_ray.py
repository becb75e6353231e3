"""Benchmark of `drivesim preprocess --backend ray`: the camera-only (mvs) depth of one drive in one process using every
core against a 2-node Ray cluster on the loopback (a head node and a worker node of one CPU each, on this machine):
wall time and Ray's overhead, the same depth frame for frame (checked), the bytes moved per frame, and on paper the
speed-up on N machines from the measured per-frame cost and transfer sizes.

    .venv/bin/python benchmarks/bench_preprocess_ray.py                  # a synthetic 3 s drive (30 frames, 320x200)
    .venv/bin/python benchmarks/bench_preprocess_ray.py --trace WS/trace --frames 40 --out /tmp/pr.md

Both runs use the stage's code (`depth_mvs.mvs_depth` in this process; `depth_ray.mvs_depth_ray` on the cluster) with
the default mvs settings and the poses of a plane-depth preprocess of the same trace. Writes
benchmarks/results/preprocess_ray.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from _lib.paths import use_folder
from _lib.report import measured_now, write_markdown
from _lib.throughput import node_rows

from drivesim.bench.machine import usable_cores
from drivesim.pipeline.config import load_config
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess.config import DepthConfig, PreprocessConfig
from drivesim.stages.preprocess.depth_ray import ChunkDone, ChunkResult, MvsDrive, chunk_frames, mvs_depth_ray

use_folder("tests")
from ray_loopback import LOOPBACK, loopback_cluster  # noqa: E402  (the loopback cluster of the Ray tests)

RESULTS = Path(__file__).resolve().parent / "results" / "preprocess_ray.md"
NODE_COUNTS = (1, 2, 4, 8, 16)
HOUR_FRAMES = 36_000  # an hour of driving at 10 Hz


@dataclass
class Timing:
    """When each frame (local) or chunk (Ray) arrived in the driver."""

    started_s: float = 0.0
    arrivals: list[tuple[float, int]] = field(default_factory=list)  # (time, frames just written)
    ended_s: float = 0.0
    task_s: float = 0.0  # Ray: the tasks' own seconds (compute, set-up included), all tasks together

    @property
    def wall_s(self) -> float:
        """Call to return."""
        return self.ended_s - self.started_s

    @property
    def steady_fps(self) -> float:
        """Frames per second between the first and the last arrival (workers started)."""
        (t0, _), (t1, _) = self.arrivals[0], self.arrivals[-1]
        return sum(k for _, k in self.arrivals[1:]) / max(t1 - t0, 1e-9)


def make_trace(args: argparse.Namespace, tmp: Path) -> Path:
    """The trace of a synthetic drive (`drivesim synth` + `ingest` in this process), or the one given."""
    if args.trace is not None:
        return args.trace.absolute()
    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.stage import run_ingest
    from drivesim.stages.synth import synthesize as synthesize_module
    from drivesim.stages.synth.config import SynthConfig

    overrides = [f"drive.duration_s={args.duration_s}", f"camera.width_px={args.width}"]
    overrides += [f"camera.height_px={args.height}", "world.scenery.view_distance_m=60"]
    synthesize_module.synthesize(load_config(SynthConfig, overrides=overrides), tmp / "drive.mcap")
    run_ingest(Workspace(tmp / "ws"), tmp / "drive.mcap", IngestConfig())
    return tmp / "ws" / "trace"


def make_drive(trace: Path, frames: int | None, tmp: Path) -> MvsDrive:
    """The drive's mvs inputs: poses from a plane-depth preprocess of `trace` (fast), the default mvs settings."""
    from drivesim.stages.preprocess.artifact import load_preprocessed
    from drivesim.stages.preprocess.stage import run_preprocess

    ws = Workspace(tmp / "poses-ws")
    ws.root.mkdir(parents=True, exist_ok=True)
    (ws.root / "trace").symlink_to(trace, target_is_directory=True)
    stop = [f"frames.stop={frames}"] if frames else []
    cfg = load_config(PreprocessConfig, preset="preprocess", overrides=["depth.method=plane", *stop])
    pre = load_preprocessed(run_preprocess(ws, cfg).path)
    calibration = json.loads((trace / "calibration.json").read_text())
    n = len(pre.poses["T_world_camera"])
    return MvsDrive(
        str(trace), (0, n, 1), np.asarray(calibration["K"]), pre.poses["T_world_camera"],
        np.asarray(calibration["T_vehicle_camera"]), calibration.get("camera_height_m"), DepthConfig(method="mvs"),
    )  # fmt: skip


def run_local(drive: MvsDrive, threads: int) -> tuple[np.ndarray, Timing]:
    """The local backend: `mvs_depth` in this process, torch and OpenCV on `threads` threads."""
    import cv2
    import torch

    from drivesim.stages.preprocess.depth_mvs import mvs_depth

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    frames = drive.frames()
    out = np.zeros(frames.shape[:3], np.float32)
    timing = Timing(started_s=time.perf_counter())
    mvs_depth(
        frames, drive.K, drive.T_world_camera, drive.T_vehicle_camera, drive.camera_height_m, drive.cfg, out,
        lambda k: timing.arrivals.append((time.perf_counter(), k)),
    )  # fmt: skip
    timing.ended_s = time.perf_counter()
    return out, timing


def run_ray(drive: MvsDrive, shape: tuple[int, ...]) -> tuple[np.ndarray, Timing, float, int]:
    """The Ray backend on a loopback cluster of a head and a worker node; returns its depth, timing, the cluster's
    start (s) and the nodes that returned chunks."""
    out = np.zeros(shape, np.float32)
    timing = Timing()

    def arrived(chunk: ChunkDone) -> None:
        timing.arrivals.append((time.perf_counter(), chunk.stop - chunk.start))
        timing.task_s += chunk.seconds

    start = time.perf_counter()
    with loopback_cluster() as cluster:
        cluster.add_node(num_cpus=1, node_ip_address=LOOPBACK)
        cluster.wait_for_nodes()
        cluster_s = time.perf_counter() - start
        timing.started_s = time.perf_counter()
        figures = mvs_depth_ray(drive, out, cluster.address, on_chunk=arrived)
        timing.ended_s = time.perf_counter()
    return out, timing, cluster_s, int(figures["ray_nodes"])


def transfer_per_frame(drive: MvsDrive, shape: tuple[int, ...], cpus: int) -> dict[str, float]:
    """Bytes per frame: a task's result (pickled, as Ray sends it), the drive's inputs put once, the frames each task
    reads from the shared file system (its chunk, the neighbours and the temporal window's frames beyond its ends);
    and the driver's seconds per frame to take a result and write it into the memmap."""
    n, h, w = shape
    size = chunk_frames(n, cpus, drive.cfg.mvs.temporal_window)
    result = ChunkResult(0, size, np.zeros((size, h, w), np.float32), np.zeros(6, np.int64), (w, h), "f" * 56, 1.0)
    result_bytes = len(pickle.dumps(result, protocol=5))
    window, offsets = drive.cfg.mvs.temporal_window, drive.cfg.mvs.neighbour_offsets
    read = 0
    for a in range(0, n, size):
        raw = range(max(0, a - window), min(n, a + size + window))
        read += len({min(max(i + o, 0), n - 1) for i in raw for o in [0, *offsets]})
    with tempfile.TemporaryDirectory(prefix="bench-preprocess-ray-") as tmp:
        out = np.lib.format.open_memmap(Path(tmp) / "depth.npy", mode="w+", dtype=np.float32, shape=(size * 8, h, w))
        start = time.perf_counter()
        for k in range(8):
            got = pickle.loads(pickle.dumps(result, protocol=5))
            out[k * size : (k + 1) * size] = got.depth_m
        out.flush()
        driver_s = (time.perf_counter() - start) / (8 * size)
    return {
        "frames_per_chunk": size,
        "result_bytes_per_frame": result_bytes / size,
        "inputs_bytes_per_frame": len(pickle.dumps(drive, protocol=5)) / n,
        "frames_read_bytes_per_frame": read * h * w * 3 / n,
        "frame_bytes": h * w * 3,
        "driver_s_per_frame": driver_s,
    }


def main() -> None:
    """Run the benchmark and write its markdown and JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trace", type=Path, default=None, help="a trace folder (default: a synthetic drive)")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames of the trace (default: all)")
    parser.add_argument("--duration-s", type=float, default=3.0, help="synthetic drive's length")
    parser.add_argument("--width", type=int, default=320, help="synthetic drive's frame width (px)")
    parser.add_argument("--height", type=int, default=200, help="synthetic drive's frame height (px)")
    parser.add_argument("--cores-per-node", type=int, default=usable_cores(), help="for the projection")
    parser.add_argument("--bandwidth-gbps", type=float, default=1.0, help="the head's link, for the projection")
    parser.add_argument("--out", type=Path, default=RESULTS, help="markdown report")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-preprocess-ray-") as tmp:
        trace = make_trace(args, Path(tmp))
        drive = make_drive(trace, args.frames, Path(tmp))
        cores = usable_cores()
        load_start = measured_now()
        local_depth, local = run_local(drive, cores)
        print(f"local: {len(local_depth)} frames in {local.wall_s:.1f} s on {cores} threads", flush=True)
        one_depth, one_thread = run_local(drive, 1)
        print(f"local: {len(one_depth)} frames in {one_thread.wall_s:.1f} s on 1 thread", flush=True)
        ray_depth, on_ray, cluster_s, nodes = run_ray(drive, local_depth.shape)
        print(f"ray: {len(ray_depth)} frames in {on_ray.wall_s:.1f} s on {nodes} nodes", flush=True)
        load_end = measured_now()
        same = all(np.array_equal(a, b) for a, b in zip(local_depth, ray_depth, strict=True))
        same &= all(np.array_equal(a, b) for a, b in zip(local_depth, one_depth, strict=True))
        transfer = transfer_per_frame(drive, local_depth.shape, 2)
    raw = {
        "measured": load_start,
        "measured_end": load_end,
        "trace": str(args.trace) if args.trace else f"synthetic {args.duration_s:g} s, {args.width}x{args.height}",
        "frames": len(local_depth),
        "cores": cores,
        "local": {"wall_s": local.wall_s, "steady_frames_per_s": local.steady_fps, "threads": cores},
        "local_one_thread": {"wall_s": one_thread.wall_s, "steady_frames_per_s": one_thread.steady_fps},
        "ray": {
            "wall_s": on_ray.wall_s,
            "steady_frames_per_s": on_ray.steady_fps,
            "cluster_start_s": cluster_s,
            "nodes": nodes,
            "task_s_total": on_ray.task_s,
        },  # fmt: skip
        "same_depth_frame_for_frame": same,
        **transfer,
        "cores_per_node": args.cores_per_node,
        "bandwidth_gbps": args.bandwidth_gbps,
    }
    write_markdown(args.out, report(args, raw), raw)


def report(args: argparse.Namespace, raw: dict) -> list[str]:
    """The markdown lines."""
    local, on_ray, n = raw["local"], raw["ray"], raw["frames"]
    start, end = raw["measured"], raw["measured_end"]
    cmd = "python benchmarks/bench_preprocess_ray.py"
    cmd += f" --trace {args.trace}" if args.trace else f" --duration-s {args.duration_s:g}"
    cmd += f" --frames {args.frames}" if args.frames else ""
    one = raw["local_one_thread"]

    def overhead(base: dict, factor: float = 1.0) -> str:
        wall = on_ray["wall_s"] / (base["wall_s"] / factor) - 1
        steady = factor * base["steady_frames_per_s"] / on_ray["steady_frames_per_s"] - 1
        return f"{100 * wall:+.0f} % wall, {100 * steady:+.0f} % steady"

    rows = [
        (f"one process, torch and OpenCV on {local['threads']} threads", local, overhead(local)),
        ("one process, one thread", one, f"against twice its speed: {overhead(one, 2.0)}"),
        (f"Ray: {on_ray['nodes']} nodes on the loopback, 1 CPU each", on_ray, "-"),
    ]
    lines = [
        "# preprocess_ray: camera-only depth on Ray (`drivesim preprocess --backend ray`)",
        "",
        f"- date: {start['date_utc']} UTC; machine: {start['machine']}; 1-min load average "
        f"{start['load_average_1_5_15_min'][0]} at the start, {end['load_average_1_5_15_min'][0]} at the end "
        "(the benchmark's own runs count in it)",
        f"- drive: {raw['trace']}, {n} frames; depth: mvs at its default settings; reproduce: `{cmd}`",
        "",
        "| run | wall (s) | s per frame | frames / s, steady state | Ray's overhead against it |",
        "|---|---|---|---|---|",
        *(
            f"| {name} | {r['wall_s']:.1f} | {r['wall_s'] / n:.2f} | {r['steady_frames_per_s']:.2f} | {text} |"
            for name, r, text in rows
        ),
        "",
        f"- The depth was {'identical, frame for frame' if raw['same_depth_frame_for_frame'] else 'DIFFERENT'} "
        "in the three runs (compared bit for bit). The Ray wall time counts the workers' start (each imports torch "
        f"and opens the trace), not the cluster's start ({on_ray['cluster_start_s']:.1f} s for the two nodes). "
        "Ray's tasks run one thread each; the one-thread row times twice is what two cores can do at best.",
        f"- Per frame, chunks of {raw['frames_per_chunk']} frames: a task sends back "
        f"{raw['result_bytes_per_frame'] / 1e3:.0f} kB (the float32 depth); the drive's inputs (poses, settings) are "
        f"put once, {raw['inputs_bytes_per_frame']:.0f} B per frame; a task reads "
        f"{raw['frames_read_bytes_per_frame'] / 1e3:.0f} kB of frames from the shared file system (its frames and "
        f"their neighbours; one frame is {raw['frame_bytes'] / 1e3:.0f} kB); the driver spends "
        f"{1e3 * raw['driver_s_per_frame']:.2f} ms taking a result and writing it into the memmap.",
        "",
    ]
    return lines + projection(raw)


def projection(raw: dict) -> list[str]:
    """On paper: expected frames per second on 1-16 nodes, the least of compute, the driver and the network."""
    core_s = raw["ray"]["task_s_total"] / raw["frames"]  # one core's seconds per frame, set-up included
    cores = raw["cores_per_node"]
    moved = raw["result_bytes_per_frame"] + raw["frames_read_bytes_per_frame"]
    driver_limit = 1 / raw["driver_s_per_frame"]
    network_limit = raw["bandwidth_gbps"] * 1e9 / 8 / moved
    lines = [
        f"## On paper: {cores} cores per node, up to {NODE_COUNTS[-1]} nodes",
        "",
        f"Expected frames per second = the least of compute (nodes x {cores} cores / {core_s:.2f} core-s per frame, "
        f"the Ray tasks' own time above), the driver (1 / {1e3 * raw['driver_s_per_frame']:.2f} ms = "
        f"{driver_limit:,.0f}) and the head's {raw['bandwidth_gbps']:g} Gbit/s link carrying each frame's result and "
        f"frames read ({moved / 1e3:.0f} kB: {network_limit:,.0f}). An hour of driving is {HOUR_FRAMES:,} frames "
        "at 10 Hz at this resolution.",
        "",
        "| nodes | cores | compute bound (frames / s) | expected (frames / s) | limited by | an hour of driving |",
        "|---|---|---|---|---|---|",
    ]
    limits = (driver_limit, network_limit)
    hours = lambda rate: f"{HOUR_FRAMES / rate / 3600:.2f} h"  # noqa: E731
    return [*lines, *node_rows(NODE_COUNTS, cores, 1 / core_s, limits, ".2f", hours), ""]


if __name__ == "__main__":
    os.environ.setdefault("DRIVESIM_PROGRESS_S", "30")
    main()
