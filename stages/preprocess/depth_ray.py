"""The Ray backend of `drivesim preprocess`: camera-only (mvs) depth split over the workers of a Ray cluster.

The drive is cut into chunks of consecutive frames. A Ray task (`depth_chunk`) opens the trace by its path (every
node sees the workspace at the same path, as for `drivesim eval --backend ray`), estimates its chunk's frames with the
code of the local run (`depth_mvs.mvs_frames`: a frame's depth depends only on the drive, never on the chunk) and
returns them; the driver writes each chunk into the reserved depth memmap as it arrives, so the depth is the local
run's, frame for frame. A task whose worker or node dies is run again by Ray (`TASK_RETRIES`); a chunk whose retries
are spent is submitted again by the driver (`CHUNK_RESUBMITS`); at the end every frame must have been written, or the
stage fails and leaves no artifact.
"""

from __future__ import annotations

import math
import time
import uuid
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.ray_cluster import RaySession, cluster_cpus, get_or_lost
from drivesim.stages.preprocess.config import DepthConfig

TASK_RETRIES = 3
"""Times Ray runs a chunk's task again when its worker process or node dies (not when the code raises)."""
CHUNK_RESUBMITS = 3
"""Times the driver submits a chunk again once Ray's retries of it are spent (nodes lost one after another)."""
IN_FLIGHT_PER_CPU = 2
"""Chunks submitted per CPU of the cluster at once: every worker has its next chunk queued, and the results waiting
for the driver stay bounded whatever the drive's length."""
MAX_CHUNK_FRAMES = 32
"""Largest chunk (frames): progress at least this often, and a lost worker takes at most this much work with it."""

# One estimator per worker process, kept between the chunks of one drive (its set-up and frame cache are reused).
_ESTIMATOR: dict[str, Any] = {}


@dataclass(frozen=True)
class MvsDrive:
    """What a task needs to estimate the mvs depth of any frames of a drive; small (the frames are read from the
    trace's frames by path), put in Ray's object store once.

    :param trace_dir: the trace artifact's folder, at the same path on every node.
    :param selection: (start, stop, step) of the trace frames preprocessed (`run.select_frames`).
    The other fields as `depth.estimate_depth`.
    """

    trace_dir: str
    selection: tuple[int, int, int]
    K: np.ndarray
    T_world_camera: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float | None
    cfg: DepthConfig
    drive_id: str = field(default_factory=lambda: uuid.uuid4().hex)

    def frames(self) -> np.ndarray:
        """The preprocessed frames (N, H, W, 3) uint8, memory-mapped from the trace."""
        from drivesim.stages.ingest.trace import open_trace

        return open_trace(Path(self.trace_dir)).frames[slice(*self.selection)]


@dataclass(frozen=True)
class ChunkResult:
    """What a task sends back: frames start..stop-1's depth (m), their summed fusion label counts, the matching
    resolution, the node that ran it and the seconds it took."""

    start: int
    stop: int
    depth_m: np.ndarray
    label_counts: np.ndarray
    matching_px: tuple[int, int]
    node: str
    seconds: float


@dataclass(frozen=True)
class ChunkDone:
    """What the progress callback learns of each chunk written: its frames, the node and its seconds of work."""

    start: int
    stop: int
    node: str
    seconds: float


def _one_thread() -> None:
    """One thread per task: the cluster runs one task per CPU, and more threads would only fight over the cores."""
    import cv2
    import numba
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    numba.set_num_threads(1)  # the temporal window's warps


def depth_chunk(drive: MvsDrive, start: int, stop: int) -> ChunkResult:
    """Estimate frames start..stop-1 of `drive`: the Ray task (it leaves torch, OpenCV and numba on one thread in
    the process that runs it)."""
    from drivesim.stages.preprocess.depth_mvs import MvsEstimator, mvs_frames

    began = time.perf_counter()
    _one_thread()
    estimator = _ESTIMATOR.get(drive.drive_id)
    if estimator is None:
        _ESTIMATOR.clear()
        estimator = MvsEstimator(
            drive.frames(), drive.K, drive.T_world_camera, drive.T_vehicle_camera, drive.camera_height_m, drive.cfg
        )
        _ESTIMATOR[drive.drive_id] = estimator
    h, w = estimator.frames.shape[1:3]
    depth_m = np.empty((stop - start, h, w), np.float32)
    counts = np.zeros(0, np.int64)
    for i, frame_depth_m, frame_counts in mvs_frames(estimator, drive.K, start, stop):
        depth_m[i - start] = frame_depth_m
        counts = frame_counts if counts.size == 0 else counts + frame_counts
    return ChunkResult(
        start, stop, depth_m, counts, (estimator.w, estimator.h), _node_id(), time.perf_counter() - began
    )


def _node_id() -> str:
    """The Ray node running this task ("" outside Ray)."""
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else ""
    except ImportError:
        return ""


def chunk_frames(frame_count: int, cpus: int, temporal_window: int) -> int:
    """Frames per chunk: about four chunks per CPU (balance and progress), at most `MAX_CHUNK_FRAMES`, and with a
    temporal window w at least 20 w (a chunk also estimates w frames beyond each end: 10 % more work at most)."""
    share = math.ceil(frame_count / max(1, 4 * cpus))
    return max(1, 20 * temporal_window, min(MAX_CHUNK_FRAMES, share))


@dataclass
class _DriveState:
    """The driver's account of a run: frames written, nodes that returned chunks, chunks resubmitted, label counts."""

    written: np.ndarray
    nodes: set[str] = field(default_factory=set)
    resubmitted: int = 0
    label_counts: np.ndarray | None = None
    matching_px: tuple[int, int] = (0, 0)


def mvs_depth_ray(
    drive: MvsDrive,
    out: np.ndarray,
    address: str | None = None,
    frames_per_chunk: int | None = None,
    on_chunk: Callable[[ChunkDone], None] | None = None,
) -> dict[str, Any]:
    """Fill `out` (N, H, W) with the mvs depth of `drive` estimated by Ray tasks; returns the figures of the local
    run (fusion fractions) and the Ray run's (nodes, chunks, resubmitted).

    :param address: the Ray cluster ("auto", host:port); None starts Ray on this machine for the call.
    :param frames_per_chunk: frames per task; None = `chunk_frames`.
    :param on_chunk: called in this process after each chunk is written (progress).
    :raises DrivesimError: a chunk lost more often than the retries allow, or a frame never written.
    """
    from drivesim.stages.preprocess.depth_mvs import fusion_fractions

    n = out.shape[0]
    with RaySession(address) as ray:
        cpus = int(cluster_cpus(ray))
        size = frames_per_chunk or chunk_frames(n, cpus, drive.cfg.mvs.temporal_window)
        chunks = [(a, min(a + size, n)) for a in range(0, n, size)]
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES, scheduling_strategy="SPREAD")(depth_chunk)
        outcome = _drive(ray, task, ray.put(drive), chunks, out, IN_FLIGHT_PER_CPU * cpus, on_chunk)
    missing = int(np.count_nonzero(~outcome.written))
    if missing:
        raise DrivesimError(f"Ray returned no depth for {missing} of {n} frames; run the same command again")
    counts = outcome.label_counts if outcome.label_counts is not None else np.zeros(0, np.int64)
    return {
        **fusion_fractions(counts, n, *outcome.matching_px),
        "ray_chunks": len(chunks),
        "ray_frames_per_chunk": size,
        "ray_nodes": len(outcome.nodes),
        "ray_resubmitted": outcome.resubmitted,
    }


def _drive(
    ray: ModuleType,
    task: Any,
    drive_ref: Any,
    chunks: list[tuple[int, int]],
    out: np.ndarray,
    in_flight_max: int,
    on_chunk: Callable[[ChunkDone], None] | None,
) -> _DriveState:
    """Keep `in_flight_max` chunks submitted, write each result into `out` as it arrives, resubmit lost chunks."""
    queue = deque(chunks)
    in_flight: dict[Any, tuple[int, int]] = {}
    lost: Counter[tuple[int, int]] = Counter()
    state = _DriveState(written=np.zeros(out.shape[0], bool))
    while queue or in_flight:
        while queue and len(in_flight) < in_flight_max:
            start, stop = queue.popleft()
            in_flight[task.remote(drive_ref, start, stop)] = (start, stop)
        done, _ = ray.wait(list(in_flight), num_returns=1)
        for ref in done:
            chunk = in_flight.pop(ref)
            result, lost_error = get_or_lost(ray, ref)
            if lost_error is not None:
                lost[chunk] += 1
                if lost[chunk] > CHUNK_RESUBMITS:
                    raise DrivesimError(
                        f"Ray lost the workers of frames {chunk[0]}-{chunk[1] - 1} {lost[chunk]} times "
                        f"({type(lost_error).__name__}); run the same command again"
                    ) from lost_error
                queue.appendleft(chunk)
                state.resubmitted += 1
                continue
            _write(state, result, out)
            if on_chunk is not None:
                on_chunk(ChunkDone(result.start, result.stop, result.node, result.seconds))
    return state


def _write(state: _DriveState, result: ChunkResult, out: np.ndarray) -> None:
    """Write a chunk's frames into `out` (once: a chunk that came back twice is written the first time)."""
    if state.written[result.start : result.stop].all():
        return
    out[result.start : result.stop] = result.depth_m
    state.written[result.start : result.stop] = True
    state.label_counts = result.label_counts if state.label_counts is None else state.label_counts + result.label_counts
    state.matching_px = result.matching_px
    state.nodes.add(result.node)


def ray_depth_method(trace_dir: Path, selection: tuple[int, int, int], address: str | None) -> Callable[..., dict]:
    """A `depth.DepthMethod` that runs mvs on Ray: the frames given to it are those of `trace_dir`'s frames at
    `selection` (start, stop, step), which each task reads itself."""

    def run(inputs: Any, cfg: DepthConfig, out: np.ndarray, progress: Callable[[int], None] | None) -> dict:
        drive = MvsDrive(
            str(Path(trace_dir).absolute()), selection, np.asarray(inputs.K), np.asarray(inputs.T_world_camera),
            np.asarray(inputs.T_vehicle_camera), inputs.camera_height_m, cfg,
        )  # fmt: skip
        on_chunk = None if progress is None else (lambda done: progress(done.stop - done.start))
        return mvs_depth_ray(drive, out, address, on_chunk=on_chunk)

    return run
