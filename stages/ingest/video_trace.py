"""A plain video (or image folder + frame rate) into a trace: frames and times, intrinsics, camera poses by SfM,
metric scale from a GPS track (a sidecar file, or the GPS a GoPro records inside its videos) or the camera height
above the fitted road plane.

The trace looks like a KITTI odometry trace to `preprocess`: `poses.npz` holds metric T_world_camera of the frames
SfM registered (world z up along the road's normal), so the pose source "given" interpolates them for every frame.
Only the frames inside the kept SfM piece's time span are written. T_vehicle_camera comes from the road plane too
(vehicle z along its normal, x the optical axis on the road, the camera `camera_height_m` above it).

Two passes over the file: SfM images first (nothing is written to the trace before the poses and the scale are
known), then the trace frames of the kept span.
"""

from __future__ import annotations

import datetime as dt
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.progress import progress_bar
from drivesim.stages.ingest.camera_file import camera_from_hfov, read_camera_file
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.gopro_gps import read_gopro_gps
from drivesim.stages.ingest.gps_sidecar import GpsTrack, check_overlap, find_sidecar, read_sidecar
from drivesim.stages.ingest.images import CameraModel, FrameProcessor, working_size
from drivesim.stages.ingest.output import FrameStore, empty_gps_series
from drivesim.stages.ingest.scale import fit_road, gps_alignment, level_world, scale_poses, vehicle_mount
from drivesim.stages.ingest.sfm import MIN_SFM_FRAMES, SfmOptions, SfmResult, reconstruct
from drivesim.stages.ingest.video import (
    FrameSource,
    image_files,
    is_video_file,
    iter_frames,
    probe_image_folder,
    probe_video,
    select_frames,
    thin_to_rate,
)
from drivesim.stages.ingest.writer import Extrinsics, TraceWriter, image_size_problem

SCALE_HINT = (
    "a video needs a metric scale: give --camera-height-m (the camera's height above the road, e.g. 1.4) "
    "or a GPS track (--gps drive.gpx, .nmea or .csv, with --video-start-utc; a GoPro's own GPS is read from its video)"
)
# Mean absolute difference (grey levels, on 32 px wide area-averaged thumbnails) below which the first and every
# later SfM frame are taken as the same view: a parked camera. Measured: a still MP4 of a noise texture 0.4 (mp4v
# artefacts), the rendered test drive 41 and the KITTI drive 44 at most.
_STILL_GREY_LEVELS = 2.0


# Horizontal fields of view an estimated focal length may give (deg): narrower or wider means SfM's refinement
# diverged (forward motion hardly constrains the focal length; on KITTI it once ran off to a 3 degree lens).
_HFOV_RANGE_DEG = (30.0, 150.0)


def is_video(path: Path) -> bool:
    """A video file, or a folder holding only images (a frame sequence)."""
    if is_video_file(path):
        return True
    if not path.is_dir():
        return False
    entries = [p for p in path.iterdir() if not p.name.startswith(".")]
    return bool(entries) and len(image_files(path)) == len(entries)


@dataclass
class _Metric:
    """SfM poses made metric: per registered frame T_world_camera, the mount and how the scale was found."""

    T_world_camera: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float
    note: str


def _camera(source: FrameSource, cfg: IngestConfig) -> CameraModel | None:
    video = cfg.video
    size = (source.width_px, source.height_px)
    if video.calibration_file:
        return read_camera_file(Path(video.calibration_file), size)
    if video.hfov_deg is not None:
        return camera_from_hfov(video.hfov_deg, size)
    return None


def _gps(path: Path, source: FrameSource, cfg: IngestConfig) -> GpsTrack | None:
    """The GPS track that scales the poses: --gps, else a sidecar with the video's name, else the GPS a GoPro
    recorded inside the video; None with `--gps none` or when there is none."""
    given = cfg.video.gps_file
    if given is not None and given.lower() == "none":
        return None
    gps_path = Path(given) if given else (find_sidecar(path) if source.kind == "video" else None)
    if gps_path is None:
        return read_gopro_gps(path) if source.kind == "video" else None
    track = read_sidecar(gps_path)
    if cfg.video.start_time_utc is None:
        raise InputError(
            "the video's start time is unknown, so its frames cannot be matched with the GPS track's times: "
            "give --video-start-utc (UTC time of the first frame, e.g. 2024-05-01T09:30:00Z)",
            gps_path,
        )
    return track


def _start_ns(cfg: IngestConfig, gps: GpsTrack | None) -> int | None:
    """UTC ns of the video's first frame: --video-start-utc, else what a GoPro's GPS says of it, else None."""
    start = cfg.video.start_time_utc
    if start is None:
        return gps.video_start_ns if gps is not None else None
    if start.tzinfo is None:
        start = start.replace(tzinfo=dt.UTC)
    return round(start.timestamp() * 1e9)


def _write_sfm_images(
    source: FrameSource, indices: np.ndarray, camera: CameraModel | None, width_px: int, folder: Path
) -> tuple[list[str], tuple[int, int]]:
    """The SfM frames as PNGs `width_px` wide (undistorted); (names, size).

    :raises InputError: every frame shows the same view as the first (a parked camera).
    """
    size = working_size(source.width_px, source.height_px, width_px, False)
    w, h = source.width_px, source.height_px
    model = camera or CameraModel(np.eye(3), np.zeros(5), "none", np.eye(3), np.eye(3), w, h)  # resizing only
    processor = FrameProcessor(model, size, "area")
    thumb_size = (32, max(1, 32 * size[1] // size[0]))
    names, first, motion = [], None, 0.0
    with progress_bar("ingest: SfM frames", total=len(indices)) as (progress, task):
        for _, rgb in iter_frames(source, indices):
            image = processor.process(rgb)
            name = f"{len(names):06d}.png"
            cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            names.append(name)
            grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
            thumb = cv2.resize(grey, thumb_size, interpolation=cv2.INTER_AREA).astype(np.float32)
            first = thumb if first is None else first
            motion = max(motion, float(np.mean(np.abs(thumb - first))))
            progress.advance(task)
        if motion < _STILL_GREY_LEVELS:
            raise InputError(
                "the camera does not move in this video (every frame shows the same view); "
                "SfM needs a video filmed from a moving vehicle",
                source.path,
            )
    return names, size


def _sfm(source: FrameSource, sfm_idx: np.ndarray, camera: CameraModel | None, cfg: IngestConfig) -> SfmResult:
    video = cfg.video
    with tempfile.TemporaryDirectory(prefix="drivesim-video-sfm-") as tmp:
        work = Path(tmp)
        (work / "images").mkdir()
        names, size = _write_sfm_images(source, sfm_idx, camera, video.sfm_width_px, work / "images")
        K = None
        if camera is not None:
            K = FrameProcessor(camera, size, "area").K_out
        opts = SfmOptions(
            window=video.sfm_window,
            loop_keyframes=video.sfm_loop_keyframes,
            max_features=video.sfm_max_features,
            threads=video.sfm_threads,
        )
        result = reconstruct(work / "images", names, K, size, opts, work)
    if result.focal_estimated:
        hfov_deg = float(np.degrees(2 * np.arctan(0.5 * size[0] / result.K[0, 0])))
        if not _HFOV_RANGE_DEG[0] <= hfov_deg <= _HFOV_RANGE_DEG[1]:
            raise InputError(
                f"SfM could not estimate the camera's focal length (it found a {hfov_deg:.0f} degree field of view); "
                "give --hfov-deg or --calibration",
                source.path,
            )
    registered = len(result.image_index)
    if registered < video.min_registered_fraction * len(sfm_idx):
        raise InputError(
            f"SfM registered only {registered} of {len(sfm_idx)} frames in one piece (pieces: "
            f"{result.piece_sizes}); the poses would be guesses. Too little texture or motion, or a wrong "
            "--hfov-deg / calibration file",
            source.path,
        )
    return result


def _metric(result: SfmResult, times_ns: np.ndarray, gps: GpsTrack | None, cfg: IngestConfig) -> _Metric:
    """Level the SfM poses on the road plane and scale them (GPS track first, else the camera height)."""
    road = fit_road(result.T_sfm_camera, result.points_sfm)
    height_m = cfg.extrinsics.camera_height_m
    if road is None:
        if gps is None:
            raise InputError(
                "the road plane could not be found in the SfM cloud below the camera (no textured road ahead?), "
                "so --camera-height-m cannot give the scale; give a GPS track (--gps) instead"
            )
        normal_sfm = -np.median(result.T_sfm_camera[:, :3, 1], axis=0)  # image up, for a level camera
        normal_sfm /= np.linalg.norm(normal_sfm)
        normal_camera, height_sfm = np.array([0.0, -1.0, 0.0]), 0.0
    else:
        normal_sfm, normal_camera, height_sfm = road.normal_sfm, road.normal_camera, road.height_sfm
    T_level_sfm = level_world(result.T_sfm_camera[0], normal_sfm, height_sfm)
    T_level_camera = T_level_sfm @ result.T_sfm_camera
    if gps is not None:
        t_rel = (times_ns - times_ns[0]) * 1e-9
        inside = (times_ns >= gps.t_ns[0]) & (times_ns <= gps.t_ns[-1])
        enu = gps.enu_m()
        t_gps = (gps.t_ns - times_ns[0]) * 1e-9
        enu_at = np.column_stack([np.interp(t_rel[inside], t_gps, enu[:, k]) for k in range(3)])
        T_enu_level = gps_alignment(T_level_camera[inside, :3, 3], enu_at)
        scale = float(T_enu_level[2, 2])
        T_world_camera = T_enu_level @ T_level_camera
        T_world_camera[:, :3, :3] /= scale  # the similarity's scale belongs to the positions only
        measured = height_sfm * scale if road is not None else None
        height_m = height_m or measured or 1.5
        track = f"the GoPro GPS recorded in {gps.path.name}" if gps.kind == "gpmf" else f"the GPS track {gps.path.name}"
        note = f"scale from {track} ({int(inside.sum())} frames matched)"
        if measured is not None:
            note += f"; camera {measured:.2f} m above the fitted road"
    else:
        if height_m is None:
            raise InputError(SCALE_HINT)
        scale = height_m / height_sfm
        T_world_camera = scale_poses(T_level_camera, scale)
        fitted = len(road.frame_rows)
        note = f"scale from --camera-height-m {height_m:g} over the road plane fitted below {fitted} frames"
        if result.focal_estimated:
            note += (
                " (it inherits the error of the focal length SfM estimated, which forward driving constrains weakly: "
                "a focal length 5 % short makes the path about 5 % short; give --hfov-deg or --calibration if known)"
            )
    return _Metric(T_world_camera, vehicle_mount(normal_camera, height_m), float(height_m), note)


def _write_trace_frames(
    trace: TraceWriter, source: FrameSource, indices: np.ndarray, camera: CameraModel, cfg: IngestConfig
) -> FrameProcessor:
    """The trace's frames (working resolution, undistorted) of the given frame indices."""
    size = working_size(source.width_px, source.height_px, cfg.image.width_px, cfg.image.upscale)
    processor = FrameProcessor(camera, size, cfg.image.interpolation)
    original = (source.width_px, source.height_px) if cfg.image.keep_original else None
    store = FrameStore(trace.out_dir, len(indices), size, original, storage=trace.frame_storage)
    try:
        with progress_bar("ingest: frames", total=len(indices)) as (progress, task):
            for _, rgb in iter_frames(source, indices):
                full = processor.undistort(rgb)
                store.write((processor.resize(full), full if original else None))
                progress.advance(task)
    finally:
        store.close()
    return processor


def _camera_after_sfm(
    source: FrameSource, camera: CameraModel | None, result: SfmResult, sfm_width: int
) -> CameraModel:
    """The given camera, or the one SfM estimated (its K scaled from the SfM images to the video's size)."""
    if camera is not None:
        return camera
    sfm_w, sfm_h = working_size(source.width_px, source.height_px, sfm_width, False)
    K = result.K.copy()
    K[0, 0] = K[1, 1] = K[0, 0] * source.width_px / sfm_w
    K[0, 2], K[1, 2] = (source.width_px - 1) / 2, (source.height_px - 1) / 2
    return CameraModel(K, np.zeros(5), "none", K.copy(), np.eye(3), source.width_px, source.height_px)


def _save_gps(trace: TraceWriter, gps: GpsTrack, t0_ns: int, t1_ns: int) -> None:
    series = empty_gps_series()
    keep = (gps.t_ns >= t0_ns - 1_000_000_000) & (gps.t_ns <= t1_ns + 1_000_000_000)
    for t, lat, lon, alt in zip(gps.t_ns[keep], gps.lat_deg[keep], gps.lon_deg[keep], gps.alt_m[keep], strict=True):
        series.append(
            t_ns=t, lat_deg=lat, lon_deg=lon, alt_m=alt, status=0, covariance_m2=np.zeros((3, 3)), covariance_type=0
        )
    count = series.save(trace.out_dir / "gps.npz")
    trace.add_sensor("gps", gps.path.name, gps.kind or gps.path.suffix.lstrip(".").lower(), count)


# A video that decodes to fewer than this share of the frames its container announces is cut short (an interrupted
# copy, download or recording); it is refused unless --end-s says to take only the part that decodes.
MIN_DECODED_FRACTION = 0.9


def _probe(path: Path, cfg: IngestConfig) -> FrameSource:
    source = probe_video(path) if path.is_file() else probe_image_folder(path, cfg.video.fps)
    problem = image_size_problem(source.width_px, source.height_px)
    if problem:
        raise InputError(problem, path)
    decoded, announced = len(source.times_ns), source.announced_frames
    if decoded < MIN_DECODED_FRACTION * announced and cfg.video.end_s is None:
        raise InputError(
            f"the video announces {announced} frames but only {decoded} decode ({source.duration_s:.1f} s): the file "
            f"is cut short; copy it again, or ingest the part that decodes with --end-s {source.duration_s:.1f}",
            path,
        )
    window = select_frames(source.times_ns, cfg.video.start_s, cfg.video.end_s)
    if len(window) < MIN_SFM_FRAMES:
        raise InputError(
            f"too short: {len(window)} frame(s) ({source.duration_s:.1f} s in the file) where SfM needs at least "
            f"{MIN_SFM_FRAMES}; give a longer video (or a wider --start-s/--end-s window)",
            path,
        )
    return source


def ingest_video(path: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    """Read a video file or an image folder into `trace`: frames, SfM poses (poses.npz), metric scale."""
    started = time.perf_counter()
    source = _probe(path, cfg)
    if 0 < len(source.times_ns) < source.announced_frames:
        trace.notes.append(f"the video announces {source.announced_frames} frames; {len(source.times_ns)} decode")
    camera = _camera(source, cfg)
    gps = _gps(path, source, cfg)
    if gps is None and cfg.extrinsics.camera_height_m is None:
        raise InputError(SCALE_HINT, path)
    start_ns = _start_ns(cfg, gps)
    window = select_frames(source.times_ns, cfg.video.start_s, cfg.video.end_s)
    if gps is not None and start_ns is not None:
        times = start_ns + source.times_ns[window]
        check_overlap(gps, int(times[0]), int(times[-1]))
    sfm_idx = window[thin_to_rate(source.times_ns[window], cfg.video.sfm_rate_hz)]
    if len(sfm_idx) < MIN_SFM_FRAMES:
        raise InputError(f"too short for SfM: {len(sfm_idx)} frames at {cfg.video.sfm_rate_hz:g} Hz", path)
    result = _sfm(source, sfm_idx, camera, cfg)
    registered = sfm_idx[result.image_index]
    abs_times = source.times_ns + (start_ns or 0)
    metric = _metric(result, abs_times[registered], gps, cfg)
    camera = _camera_after_sfm(source, camera, result, cfg.video.sfm_width_px)
    span = window[(window >= registered[0]) & (window <= registered[-1])]
    processor = _write_trace_frames(trace, source, span, camera, cfg)
    label = "video" if source.kind == "video" else source.path.name
    trace.set_camera(label, processor, (source.width_px, source.height_px), camera.model)
    trace.set_extrinsics(Extrinsics(metric.T_vehicle_camera, metric.camera_height_m, "sfm_road_plane"))
    trace.set_times(abs_times[span], "unix" if start_ns is not None else "relative", frame_rows=len(span))
    trace.add_sensor("camera", path.name, source.kind, len(span))
    np.savez(trace.out_dir / "poses.npz", t_ns=abs_times[registered], T_world_camera=metric.T_world_camera)
    trace.add_sensor("poses", "sfm", "sfm_poses", len(registered))
    if gps is not None:
        _save_gps(trace, gps, int(abs_times[span[0]]), int(abs_times[span[-1]]))
    trace.notes.extend(_notes(source, camera, result, sfm_idx, registered, metric, time.perf_counter() - started))


def _notes(
    source: FrameSource,
    camera: CameraModel,
    result: SfmResult,
    sfm_idx: np.ndarray,
    registered: np.ndarray,
    metric: _Metric,
    seconds: float,
) -> list[str]:
    hfov = np.degrees(2 * np.arctan(0.5 * camera.width_px / camera.K[0, 0]))
    how = "estimated by SfM" if result.focal_estimated else "given"
    missing = np.setdiff1d(sfm_idx, registered)
    notes = [
        source.note,
        f"intrinsics {how}: fx {camera.K[0, 0]:.1f} px at {camera.width_px} px wide (horizontal FOV {hfov:.1f} deg)",
        f"SfM registered {len(registered)} of {len(sfm_idx)} frames "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in result.seconds.items())})",
        metric.note,
        f"video ingest took {seconds:.0f} s",
    ]
    if len(result.piece_sizes) > 1:
        notes.append(
            f"SfM broke the drive into {len(result.piece_sizes)} pieces {result.piece_sizes}; kept the largest"
        )
    if len(missing):
        shown = ", ".join(str(int(i)) for i in missing[:10]) + (" ..." if len(missing) > 10 else "")
        notes.append(f"{len(missing)} SfM frame(s) not registered (video frames {shown}); their poses are interpolated")
    return notes
