"""`drivesim synth` end to end: build the world, drive through it, render, simulate the sensors, write the recording.

Output files (written as hidden temporaries and moved into place only when complete):
    <output>.mcap              the ROS2 recording (topics in `recording.py`)
    <output>.world.json        seed + resolved config: `SynthWorld.from_sidecar` rebuilds the world from it
    <output>.preview.png       contact sheet of frames (with --preview)
    <output>.map.png           bird's-eye map of the world and the drive (with --preview)
"""

from __future__ import annotations

import functools
import heapq
import json
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np
import torch

from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.stages.synth import recording as rec
from drivesim.stages.synth.config import RoadConfig, SynthConfig
from drivesim.stages.synth.drive import Trajectory, required_path_length_m
from drivesim.stages.synth.sensors import gps_series, imu_series, sample_times_s, wheel_series
from drivesim.stages.synth.world import SynthWorld

PREVIEW_FRAMES = 9
PREVIEW_WIDTH_PX = 400


@dataclass
class SynthResult:
    """What a synth run wrote and how long it took."""

    output: Path
    sidecar: Path
    previews: list[Path]
    frame_count: int
    message_counts: dict[str, int]
    triangle_count: int
    render_s: float
    total_s: float
    size_bytes: int
    path_length_m: float
    extra: dict[str, float] = field(default_factory=dict)


def sidecar_path(output: Path) -> Path:
    """`<output>.world.json` (the suffix .mcap replaced)."""
    return output.with_suffix(".world.json")


def preview_paths(output: Path) -> tuple[Path, Path]:
    """(`<output>.preview.png`, `<output>.map.png`)."""
    return output.with_suffix(".preview.png"), output.with_suffix(".map.png")


def resolve_config(cfg: SynthConfig) -> SynthConfig:
    """`cfg` with the road long enough for the drive (the recorded config: the world is rebuilt from it)."""
    # the lane is up to a few % shorter than the centreline in right-hand bends
    needed_m = required_path_length_m(cfg.drive) * 1.1 + 30.0
    if needed_m <= cfg.world.road.length_m:
        return cfg
    limit_m = RoadConfig.model_fields["length_m"].metadata[-1].le
    if needed_m > limit_m:
        raise ConfigError(
            f"a {cfg.drive.duration_s:g} s drive at {cfg.drive.speed_mps:g} m/s needs {needed_m:.0f} m of road; "
            f"the synthetic road is at most {limit_m:.0f} m: shorten drive.duration_s"
        )
    data = cfg.model_dump()
    data["world"]["road"]["length_m"] = float(np.ceil(needed_m))
    return SynthConfig.model_validate(data)


def _check_output(output: Path) -> None:
    if output.suffix != ".mcap":
        raise InputError("the output recording must end in .mcap", output)
    if output.is_dir():
        raise InputError("the output is a folder; give a file name ending in .mcap", output)


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run torch on one thread inside the block. On the shared 2-core machine a 960x600 frame took 0.30 s with one
    thread and 3.3 s with two while other jobs ran (OpenMP workers spinning against each other); one thread costs
    little when the machine is quiet, so synth renders single-threaded."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def synthesize(
    cfg: SynthConfig,
    output: Path,
    preview: bool = False,
    on_frame: Callable[[int, int], None] | None = None,
) -> SynthResult:
    """Render the drive of `cfg` and write `output` (+ sidecar, + previews). `on_frame(done, total)` reports progress.

    Nothing is left at the output paths if it fails or is interrupted.
    """
    with single_torch_thread():
        return _synthesize(cfg, output, preview, on_frame)


def _synthesize(
    cfg: SynthConfig, output: Path, preview: bool, on_frame: Callable[[int, int], None] | None
) -> SynthResult:
    started = time.perf_counter()
    output = Path(output)
    _check_output(output)
    cfg = resolve_config(cfg)
    output.parent.mkdir(parents=True, exist_ok=True)

    world = SynthWorld.from_seed(cfg.seed, cfg)
    traj = Trajectory(world.path, cfg.drive)
    duration = cfg.drive.duration_s
    gps_rng, imu_rng, wheel_rng = (np.random.default_rng(s) for s in np.random.SeedSequence([cfg.seed, 2]).spawn(3))
    gps = gps_series(traj, cfg.sensors.gps, duration, gps_rng)
    imu = imu_series(traj, cfg.sensors.imu, duration, imu_rng)
    wheel = wheel_series(traj, cfg.sensors.wheel, duration, wheel_rng)
    frame_t = sample_times_s(duration, cfg.camera.rate_hz)
    if len(frame_t) == 0:
        raise InputError(f"a {duration} s drive at {cfg.camera.rate_hz} Hz has no camera frame")

    t0_ns = int(round(cfg.drive.start_epoch_s * 1e9))

    def ns(t_s: float) -> int:
        return t0_ns + int(round(t_s * 1e9))

    events = _sensor_events(cfg, gps, imu, wheel, ns)
    pending = [p for p in (output, sidecar_path(output), *preview_paths(output))]
    tmp = {p: p.with_name(f".{p.name}.tmp-{os.getpid()}") for p in pending}
    keep_idx = set(np.unique(np.linspace(0, len(frame_t) - 1, PREVIEW_FRAMES).round().astype(int)).tolist())
    try:
        with open(tmp[output], "wb") as stream:
            counts, render_s, thumbs = _record_drive(
                stream, cfg, world, traj, frame_t, events, ns, keep_idx if preview else set(), on_frame
            )
        sidecar = {
            "seed": cfg.seed,
            "config": cfg.model_dump(mode="json"),
            "recording": output.name,
            "start_epoch_ns": t0_ns,
            "world_frame": "ENU, origin at the road start; GPS origin in config.sensors.gps",
            "triangle_count": world.triangle_count,
        }
        tmp[sidecar_path(output)].write_text(json.dumps(sidecar, indent=2) + "\n")
        if preview:
            from drivesim.stages.synth.preview import write_contact_sheet, write_map

            sheet_path, map_path = preview_paths(output)
            write_contact_sheet(thumbs, tmp[sheet_path], title=f"drivesim synth — seed {cfg.seed}")
            write_map(world, traj, duration, gps, tmp[map_path])
        for final in reversed(pending):
            if tmp[final].exists():
                os.replace(tmp[final], final)
    finally:
        for path in tmp.values():
            path.unlink(missing_ok=True)

    return SynthResult(
        output=output,
        sidecar=sidecar_path(output),
        previews=[p for p in preview_paths(output) if preview],
        frame_count=len(frame_t),
        message_counts=counts,
        triangle_count=world.triangle_count,
        render_s=render_s,
        total_s=time.perf_counter() - started,
        size_bytes=output.stat().st_size,
        path_length_m=float(traj.arc_length_m(duration) - traj.arc_length_m(0.0)),
    )


def _record_drive(
    stream: BinaryIO,
    cfg: SynthConfig,
    world: SynthWorld,
    traj: Trajectory,
    frame_t: np.ndarray,
    events: Iterator[tuple[int, str, Callable[[], Any]]],
    ns: Callable[[float], int],
    thumb_frames: set[int],
    on_frame: Callable[[int, int], None] | None,
) -> tuple[dict[str, int], float, list[tuple[float, np.ndarray]]]:
    """Write the drive's recording into `stream`: each camera frame rendered, with its camera info, ground-truth
    depth and pose, and the sensor `events` in time order; returns (messages per topic, render seconds, the
    thumbnails of the frames `thumb_frames` with their times)."""
    cam = world.camera
    render_s = 0.0
    thumbs: list[tuple[float, np.ndarray]] = []
    writer = rec.RecordingWriter(stream)
    writer.add_metadata("drivesim_synth", {"seed": str(cfg.seed), "config": json.dumps(cfg.model_dump())})
    writer.write("/tf_static", rec.tf_static_msg(cam.T_vehicle_camera, ns(0.0)), ns(0.0))
    pending = next(events, None)
    for k, t in enumerate(frame_t):
        t_ns = ns(float(t))
        while pending is not None and pending[0] <= t_ns:
            writer.write(pending[1], pending[2](), pending[0])
            pending = next(events, None)
        T_world_vehicle = traj.vehicle_pose(float(t))
        tic = time.perf_counter()
        rgb, depth = world.render(T_world_vehicle @ cam.T_vehicle_camera, cam.K, cam.width_px, cam.height_px)
        render_s += time.perf_counter() - tic
        writer.write("/camera/camera_info", rec.camera_info_msg(cam.K, cam.width_px, cam.height_px, t_ns), t_ns)
        writer.write("/camera/image_raw", rec.image_msg(rgb, t_ns), t_ns)
        writer.write("/ground_truth/depth", rec.depth_msg(depth, t_ns), t_ns)
        writer.write("/ground_truth/pose", rec.pose_stamped_msg(T_world_vehicle, t_ns), t_ns)
        if k in thumb_frames:
            scale = PREVIEW_WIDTH_PX / cam.width_px
            thumbs.append((float(t), cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)))
        if on_frame is not None:
            on_frame(k + 1, len(frame_t))
    while pending is not None:
        writer.write(pending[1], pending[2](), pending[0])
        pending = next(events, None)
    writer.finish()
    return dict(writer.counts), render_s, thumbs


def _timed_events(
    t_s: Any, ns: Callable[[float], int], topic: str, message: Callable[[int, int], Any]
) -> Iterator[tuple[int, str, Callable[[], Any]]]:
    """(log time ns, topic, message factory) of one sensor's messages in time order; `message(i, t_ns)` builds
    message i."""
    for i, t in enumerate(t_s):
        t_ns = ns(float(t))
        yield t_ns, topic, functools.partial(message, i, t_ns)


def _sensor_events(
    cfg: SynthConfig, gps: dict, imu: dict, wheel: dict, ns: Callable[[float], int]
) -> Iterator[tuple[int, str, Callable[[], Any]]]:
    """(log time ns, topic, message factory) of every GPS, IMU and wheel message, in time order, made as they are
    consumed (a long drive has hundreds of thousands)."""
    gyro_var = cfg.sensors.imu.gyro_noise_radps**2
    accel_var = cfg.sensors.imu.accel_noise_mps2**2
    # merged by time; equal stamps keep the GPS, IMU, wheel order (heapq.merge takes ties from the first iterable)
    return heapq.merge(
        _timed_events(
            gps["t_s"],
            ns,
            "/gps/fix",
            lambda i, t_ns: rec.navsat_msg(
                gps["lat_deg"][i], gps["lon_deg"][i], gps["alt_m"][i], gps["covariance_m2"][i], t_ns
            ),
        ),
        _timed_events(
            imu["t_s"],
            ns,
            "/imu/data",
            lambda i, t_ns: rec.imu_msg(
                imu["angular_velocity_radps"][i], imu["linear_acceleration_mps2"][i], gyro_var, accel_var, t_ns
            ),
        ),
        _timed_events(wheel["t_s"], ns, "/vehicle/twist", lambda i, t_ns: rec.twist_msg(wheel["speed_mps"][i], t_ns)),
        key=lambda ev: ev[0],
    )
