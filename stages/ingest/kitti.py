"""Ingest of KITTI folders: raw drives (`..._sync/` with image_0X/, oxts/ and the date folder's calib_*.txt) and
odometry sequences (image_l/ or image_0/, poses.txt, calib.txt).

KITTI images are already rectified, so frames are only resized. The raw drive's vehicle frame is the OXTS IMU frame
(x forward, y left, z up) moved down to the ground (the unit sits 0.93 m above it, KITTI setup paper).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.progress import progress_bar
from drivesim.sim.geometry import camera_mount, invert, se3
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.images import CameraModel, FrameProcessor, working_size
from drivesim.stages.ingest.output import (
    FrameStore,
    IngestResult,
    OrderedPipeline,
    empty_gps_series,
    empty_imu_series,
    empty_speed_series,
    write_json,
)

IMU_HEIGHT_M = 0.93
KITTI_CAMERA_HEIGHT_M = 1.65
_OXTS_FIELDS = 30


def parse_calib_file(path: Path) -> dict[str, np.ndarray]:
    """`key: numbers` lines of a KITTI calibration file (non-numeric values such as calib_time are skipped)."""
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise InputError(f"cannot read KITTI calibration file: {e.strerror}", path) from e
    values: dict[str, np.ndarray] = {}
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:  # odometry calib.txt written without keys: line i is P<i>
            key, rest = f"P{i}", line
        try:
            values[key.strip()] = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue
    return values


def _need(calib: dict[str, np.ndarray], key: str, size: int, path: Path) -> np.ndarray:
    if key not in calib or calib[key].size != size:
        raise InputError(f"KITTI calibration has no {key} with {size} values", path)
    return calib[key]


def parse_timestamps(path: Path) -> np.ndarray:
    """KITTI raw `timestamps.txt` ("2011-09-26 13:02:25.967790592" per line) as int64 ns (clock as recorded)."""
    try:
        lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        stamps = np.array([np.datetime64(line.replace(" ", "T"), "ns") for line in lines])
    except (OSError, ValueError) as e:
        raise InputError(f"unreadable KITTI timestamps file ({e})", path) from e
    return stamps.astype(np.int64)


def _check_increasing(times_ns: np.ndarray, what: str, path: Path) -> None:
    bad = np.flatnonzero(np.diff(times_ns) <= 0)
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{what}: stamps not strictly increasing at frame {i + 1}", path)


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("unreadable image file", path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _write_frames(files: list[Path], processor: FrameProcessor, out_dir: Path, label: str, keep: bool) -> None:
    expected = (processor.camera.height_px, processor.camera.width_px)

    def work(file: Path) -> tuple[np.ndarray, np.ndarray | None]:
        rgb = _read_rgb(file)
        if rgb.shape[:2] != expected:
            raise InputError(f"image is {rgb.shape[1]}x{rgb.shape[0]}, the others {expected[1]}x{expected[0]}", file)
        return (processor.resize(rgb), rgb if keep else None)

    original_size = (processor.camera.width_px, processor.camera.height_px) if keep else None
    store = FrameStore(out_dir, len(files), (processor.out_width, processor.out_height), original_size)

    def sink(frames: tuple[np.ndarray, np.ndarray | None]) -> None:
        store.write(frames)
        progress.advance(task)

    pipeline = OrderedPipeline(work, sink)
    try:
        with progress_bar(f"ingest {label}", total=len(files)) as (progress, task):
            for file in files:
                pipeline.submit(file)
            pipeline.finish()
    finally:
        pipeline.close()
        store.close()


def _image_files(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputError("no images", folder)
    return files


def _write_camera(
    files: list[Path],
    times_ns: np.ndarray,
    P: np.ndarray,
    source_size: tuple[int, int],
    cfg: IngestConfig,
    out_dir: Path,
    label: str,
) -> FrameProcessor:
    """Write a KITTI image folder's frames (at the working resolution) and their times; returns the processor used."""
    source_w, source_h = source_size
    processor = FrameProcessor(
        _pinhole(P, source_w, source_h),
        working_size(source_w, source_h, cfg.image.width_px, cfg.image.upscale),
        cfg.image.interpolation,
    )
    _write_frames(files, processor, out_dir, label, cfg.image.keep_original)
    np.save(out_dir / "frame_times_ns.npy", times_ns)
    return processor


def _pinhole(P: np.ndarray, width: int, height: int) -> CameraModel:
    K = P.reshape(3, 4)[:, :3].copy()
    return CameraModel(K=K, D=np.zeros(5), model="none", P=K, R=np.eye(3), width_px=width, height_px=height)


def _image_size(path: Path) -> tuple[int, int]:
    img = _read_rgb(path)
    return img.shape[1], img.shape[0]


def _choose_camera(drive: Path, wanted: str | None, prefix: str = "image_0") -> Path:
    cams = sorted(p for p in drive.iterdir() if p.is_dir() and p.name.startswith(prefix))
    if wanted is not None:
        match = [c for c in cams if c.name == wanted.strip("/")]
        if not match:
            names = ", ".join(c.name for c in cams)
            raise InputError(f"--topic camera={wanted}: no such camera folder (found: {names})", drive)
        return match[0]
    colour = [c for c in cams if c.name == "image_02"]
    return (colour or cams)[0]


def kitti_raw_extrinsics(calib_dir: Path, cam_index: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(T_vehicle_camera, P_rect 3x4, rectified size) of camera `cam_index` from the date folder's calib files."""
    cam_path = calib_dir / "calib_cam_to_cam.txt"
    velo_path = calib_dir / "calib_velo_to_cam.txt"
    imu_path = calib_dir / "calib_imu_to_velo.txt"
    for p in (cam_path, velo_path, imu_path):
        if not p.is_file():
            raise InputError(f"KITTI raw drive without {p.name} in its date folder", p.parent)
    cam = parse_calib_file(cam_path)
    velo = parse_calib_file(velo_path)
    imu = parse_calib_file(imu_path)
    P = _need(cam, f"P_rect_0{cam_index}", 12, cam_path).reshape(3, 4)
    size = _need(cam, f"S_rect_0{cam_index}", 2, cam_path)
    R_rect = se3(_need(cam, "R_rect_00", 9, cam_path).reshape(3, 3), np.zeros(3))
    T_cam0_velo = se3(_need(velo, "R", 9, velo_path).reshape(3, 3), _need(velo, "T", 3, velo_path))
    T_velo_imu = se3(_need(imu, "R", 9, imu_path).reshape(3, 3), _need(imu, "T", 3, imu_path))
    # Rectified camera X sits at K^-1 P[:, 3] from rectified camera 0 (the stereo baseline).
    T_camx_cam0 = se3(np.eye(3), np.linalg.solve(P[:, :3], P[:, 3]))
    T_cam_imu = T_camx_cam0 @ R_rect @ T_cam0_velo @ T_velo_imu
    T_vehicle_imu = se3(np.eye(3), np.array([0.0, 0.0, IMU_HEIGHT_M]))
    return T_vehicle_imu @ invert(T_cam_imu), P, (int(size[0]), int(size[1]))


def _oxts_status(posmode: np.ndarray) -> np.ndarray:
    """OXTS position mode to NavSatStatus: <3 no fix, 3 standalone fix, >=4 differential/RTK (ground-based)."""
    status = np.where(posmode >= 4, 2, np.where(posmode >= 3, 0, -1))
    return status.astype(np.int8)


def read_oxts(drive: Path, step_ns: int, use_timestamps: bool) -> tuple[np.ndarray, np.ndarray]:
    """(times ns, (M, 30) values) of the drive's OXTS packets (times every `step_ns` without timestamps)."""
    files = sorted((drive / "oxts" / "data").glob("*.txt"))
    if not files:
        raise InputError("KITTI raw drive without oxts/data/*.txt", drive)
    rows = []
    for f in files:
        try:
            values = np.array([float(v) for v in f.read_text().split()])
        except (OSError, ValueError) as e:
            raise InputError(f"unreadable OXTS packet ({e})", f) from e
        if values.size != _OXTS_FIELDS:
            raise InputError(f"OXTS packet has {values.size} values, expected {_OXTS_FIELDS}", f)
        rows.append(values)
    stamps_path = drive / "oxts" / "timestamps.txt"
    if use_timestamps and stamps_path.is_file():
        times = parse_timestamps(stamps_path)
    else:
        times = np.arange(len(files), dtype=np.int64) * step_ns
    if len(times) != len(files):
        raise InputError(f"{len(times)} OXTS timestamps for {len(files)} packets", stamps_path)
    return times, np.stack(rows)


def _save_oxts(out_dir: Path, times: np.ndarray, oxts: np.ndarray) -> dict[str, int]:
    gps, imu, speed = empty_gps_series(), empty_imu_series(), empty_speed_series()
    quats = Rotation.from_euler("ZYX", oxts[:, [5, 4, 3]]).as_quat()  # yaw, pitch, roll -> R_enu_imu
    for t, row, q in zip(times, oxts, quats, strict=True):
        acc_m = row[23]
        gps.append(
            t_ns=t,
            lat_deg=row[0],
            lon_deg=row[1],
            alt_m=row[2],
            status=_oxts_status(np.array([row[27]]))[0],
            covariance_m2=np.diag([acc_m**2] * 3),
            covariance_type=1,  # approximated from the unit's reported position accuracy
        )
        imu.append(t_ns=t, angular_velocity_radps=row[17:20], linear_acceleration_mps2=row[11:14], orientation_xyzw=q)
        speed.append(t_ns=t, speed_mps=row[8])
    return {
        "gps": gps.save(out_dir / "gps.npz"),
        "imu": imu.save(out_dir / "imu.npz"),
        "speed": speed.save(out_dir / "speed.npz"),
    }


def ingest_kitti_raw(drive: Path, cfg: IngestConfig, out_dir: Path) -> IngestResult:
    """Read a KITTI raw `..._sync` drive folder into the trace folder `out_dir`."""
    cam_dir = _choose_camera(drive, cfg.topics.camera)
    cam_index = int(cam_dir.name[-1])
    notes = [f"camera: {cam_dir.name} ({'chosen with --topic camera' if cfg.topics.camera else 'default choice'})"]
    files = _image_files(cam_dir / "data")
    T_vehicle_camera, P, rect_size = kitti_raw_extrinsics(drive.parent, cam_index)
    source_w, source_h = _image_size(files[0])
    if (source_w, source_h) != rect_size:
        raise InputError(
            f"images are {source_w}x{source_h} but S_rect_0{cam_index} says {rect_size[0]}x{rect_size[1]} "
            "(only rectified _sync drives are supported)",
            cam_dir,
        )
    step_ns = round(cfg.kitti_time_step_s * 1e9)
    stamps_path = cam_dir / "timestamps.txt"
    if stamps_path.is_file():
        times = parse_timestamps(stamps_path)
        time_base = "unix"
        if len(times) != len(files):
            raise InputError(f"{len(times)} timestamps for {len(files)} images", stamps_path)
    else:
        times = np.arange(len(files), dtype=np.int64) * step_ns
        time_base = "relative"
    _check_increasing(times, f"camera {cam_dir.name}", stamps_path)

    oxts_times, oxts = read_oxts(drive, step_ns, use_timestamps=time_base == "unix")

    extrinsics_source = "kitti_calib"
    height_m: float | None = float(T_vehicle_camera[2, 3])
    if cfg.extrinsics.T_vehicle_camera is not None:
        T_vehicle_camera = np.asarray(cfg.extrinsics.T_vehicle_camera, dtype=float)
        extrinsics_source = "config"
        height_m = cfg.extrinsics.camera_height_m
    processor = _write_camera(files, times, P, (source_w, source_h), cfg, out_dir, cam_dir.name)
    counts = _save_oxts(out_dir, oxts_times, oxts)
    sensors = {
        "camera": {"topic": cam_dir.name, "type": "png", "message_count": len(files)},
        **{name: {"topic": "oxts", "type": "oxts", "message_count": n} for name, n in counts.items()},
    }
    return _finish(
        out_dir, drive, "kitti_raw", cam_dir.name, processor, (source_w, source_h), T_vehicle_camera, height_m,
        extrinsics_source, time_base, times, sensors, notes,
    )  # fmt: skip


def ingest_kitti_odometry(folder: Path, cfg: IngestConfig, out_dir: Path) -> IngestResult:
    """Read a KITTI odometry sequence folder (image_l/ or image_0X/, poses.txt, calib.txt) into `out_dir`."""
    names = {p.name for p in folder.iterdir()}
    wanted = cfg.topics.camera
    if wanted is None:
        wanted = next((n for n in ("image_l", "image_0", "image_2") if n in names), None)
    if wanted is None or wanted.strip("/") not in names:
        raise InputError("KITTI odometry folder without an image folder (image_l/, image_0/ or image_2/)", folder)
    cam_dir = folder / wanted.strip("/")
    files = _image_files(cam_dir)
    calib_path = folder / "calib.txt"
    if not calib_path.is_file():
        raise InputError("KITTI odometry folder without calib.txt (needed for the intrinsics)", folder)
    calib = parse_calib_file(calib_path)
    p_key = {"image_r": "P1", "image_1": "P1", "image_2": "P2", "image_3": "P3"}.get(cam_dir.name, "P0")
    P = _need(calib, p_key, 12, calib_path).reshape(3, 4)

    poses_path = folder / "poses.txt"
    poses = None
    if poses_path.is_file():
        try:
            rows = np.loadtxt(poses_path, ndmin=2)
        except ValueError as e:
            raise InputError(f"unreadable poses ({e})", poses_path) from e
        if rows.shape[1] != 12 or len(rows) != len(files):
            raise InputError(f"{len(rows)} poses of {rows.shape[1]} values for {len(files)} images", poses_path)
        poses = np.tile(np.eye(4), (len(rows), 1, 1))
        poses[:, :3, :] = rows.reshape(-1, 3, 4)
    elif cfg.require_pose_source:
        raise InputError("KITTI odometry folder without poses.txt: no pose source", folder)

    times_path = folder / "times.txt"
    if times_path.is_file():
        times = np.round(np.loadtxt(times_path, ndmin=1) * 1e9).astype(np.int64)
        if len(times) != len(files):
            raise InputError(f"{len(times)} times for {len(files)} images", times_path)
    else:
        times = np.arange(len(files), dtype=np.int64) * round(cfg.kitti_time_step_s * 1e9)
    _check_increasing(times, f"camera {cam_dir.name}", times_path)

    source_w, source_h = _image_size(files[0])
    processor = _write_camera(files, times, P, (source_w, source_h), cfg, out_dir, cam_dir.name)
    sensors = {"camera": {"topic": cam_dir.name, "type": "png", "message_count": len(files)}}
    if poses is not None:
        np.savez(out_dir / "poses.npz", t_ns=times, T_world_camera=poses)
        sensors["poses"] = {"topic": "poses.txt", "type": "kitti_poses", "message_count": len(poses)}

    if cfg.extrinsics.T_vehicle_camera is not None:
        T_vehicle_camera = np.asarray(cfg.extrinsics.T_vehicle_camera, dtype=float)
        height_m, extrinsics_source = cfg.extrinsics.camera_height_m, "config"
    else:
        height_m = cfg.extrinsics.camera_height_m or KITTI_CAMERA_HEIGHT_M
        T_vehicle_camera, extrinsics_source = camera_mount(0.0, 0.0, height_m), "default"
    notes = [f"camera: {cam_dir.name}; no timestamps, frames at {cfg.kitti_time_step_s:g} s"]
    return _finish(
        out_dir, folder, "kitti_odometry", cam_dir.name, processor, (source_w, source_h), T_vehicle_camera, height_m,
        extrinsics_source, "relative", times, sensors, notes,
    )  # fmt: skip


def _finish(
    out_dir: Path,
    recording: Path,
    fmt: str,
    camera: str,
    processor: FrameProcessor,
    source_size: tuple[int, int],
    T_vehicle_camera: np.ndarray,
    height_m: float | None,
    extrinsics_source: str,
    time_base: str,
    times: np.ndarray,
    sensors: dict,
    notes: list[str],
) -> IngestResult:
    write_json(
        out_dir / "calibration.json",
        {
            "width_px": processor.out_width,
            "height_px": processor.out_height,
            "K": processor.K_out,
            "K_source": processor.K_source,
            "source_width_px": source_size[0],
            "source_height_px": source_size[1],
            "distortion_model": "none",
            "T_vehicle_camera": T_vehicle_camera,
            "camera_height_m": height_m,
            "extrinsics_source": extrinsics_source,
            "time_base": time_base,
        },
    )
    write_json(
        out_dir / "sources.json",
        {"recording": str(recording), "format": fmt, "camera_topic": camera, "sensors": sensors},
    )
    summary = {
        "frame_count": len(times),
        "duration_s": round(float(times[-1] - times[0]) / 1e9, 3) if len(times) > 1 else 0.0,
        "width_px": processor.out_width,
        "height_px": processor.out_height,
        "sensors": sensors,
    }
    return IngestResult(summary=summary, notes=notes)
