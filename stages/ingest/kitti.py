"""Ingest of KITTI folders: raw drives (`..._sync/` with image_0X/, oxts/ and the date folder's calib_*.txt) and
odometry sequences (image_l/ or image_0/, poses.txt, calib.txt).

KITTI images are already rectified, so frames are only resized. The raw drive's vehicle frame is the OXTS IMU frame
(x forward, y left, z up) moved down to the ground (the unit sits 0.93 m above it, KITTI setup paper).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.progress import progress_bar
from drivesim.sim.geometry import camera_mount, invert, se3
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.images import (
    CameraModel,
    CorruptImageError,
    FrameProcessor,
    decode_image_bytes,
    working_size,
)
from drivesim.stages.ingest.output import FrameStore, empty_gps_series, empty_imu_series, empty_speed_series
from drivesim.stages.ingest.trace import rigid_problem
from drivesim.stages.ingest.writer import Extrinsics, FrameStream, TraceWriter, config_extrinsics

IMU_HEIGHT_M = 0.93
KITTI_CAMERA_HEIGHT_M = 1.65
_OXTS_FIELDS = 30


def _names(path: Path) -> set[str]:
    return {p.name for p in path.iterdir()} if path.is_dir() else set()


def is_kitti_raw_drive(path: Path) -> bool:
    """A KITTI raw `..._sync` drive folder (oxts/ and image_0X/)."""
    names = _names(path)
    return "oxts" in names and any(n.startswith("image_0") for n in names)


def is_kitti_odometry(path: Path) -> bool:
    """A KITTI odometry sequence folder (poses.txt or calib.txt beside the image folders)."""
    names = _names(path)
    return "poses.txt" in names or "calib.txt" in names


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
    if not np.all(np.isfinite(calib[key])):
        raise InputError(f"KITTI calibration {key} has non-finite values", path)
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


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_problem(data: bytes) -> str | None:
    """Why a PNG file is damaged (a chunk CRC that does not match, no IEND: truncated), or None.

    Hand-written (a chunk walk with zlib.crc32, ~0.3 ms for a KITTI frame) because libpng, inside cv2.imdecode,
    prints "libpng error: ..." to stderr on damaged files, which would break the CLI's one-line error.
    """
    pos = len(_PNG_MAGIC)
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        end = pos + 12 + length
        if end > len(data):
            return "truncated PNG"
        kind = data[pos + 4 : pos + 8]
        if zlib.crc32(data[pos + 4 : end - 4]) != int.from_bytes(data[end - 4 : end], "big"):
            return f"PNG chunk {kind.decode('latin1')!r} fails its CRC (damaged file)"
        if kind == b"IEND":
            return None
        pos = end
    return "truncated PNG (no IEND chunk)"


def _read_rgb(path: Path) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(f"cannot read the image: {e.strerror}", path) from e
    if data.startswith(_PNG_MAGIC) and (problem := png_problem(data)):
        raise InputError(problem, path)
    try:
        img = decode_image_bytes(data)
    except CorruptImageError as e:
        raise InputError(f"unreadable image file (damaged or not a png/jpeg): {e}", path) from e
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _write_frames(
    trace: TraceWriter, files: list[Path], processor: FrameProcessor, label: str, keep: bool, stem: str = "frames"
) -> int:
    """Resize the image files into `<stem>.imgs` in order; the rows written.

    A damaged image file refuses the folder rather than being skipped: each file is one line of poses.txt and
    times.txt, so a gap would shift every pose after it.
    """
    expected = (processor.camera.height_px, processor.camera.width_px)

    def work(file: Path) -> tuple[np.ndarray, np.ndarray | None]:
        rgb = _read_rgb(file)
        if rgb.shape[:2] != expected:
            raise InputError(f"image is {rgb.shape[1]}x{rgb.shape[0]}, the others {expected[1]}x{expected[0]}", file)
        return (processor.resize(rgb), rgb if keep else None)

    original_size = (processor.camera.width_px, processor.camera.height_px) if keep else None
    size = (processor.out_width, processor.out_height)
    store = FrameStore(trace.out_dir, len(files), size, original_size, stem, trace.frame_storage)
    stream = None
    try:
        with progress_bar(f"ingest {label}", total=len(files)) as (progress, task):
            stream = FrameStream(trace, store, work, lambda: progress.advance(task))
            for i, file in enumerate(files):
                stream.submit(file, i)
            stream.finish(label)
    finally:
        if stream is not None:
            stream.close()
        store.close()
    return store.frames.rows_written


def _image_files(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise InputError("no images", folder)
    return files


def _write_camera(
    trace: TraceWriter,
    files: list[Path],
    times_ns: np.ndarray,
    P: np.ndarray,
    cfg: IngestConfig,
    label: str,
    time_base: str,
) -> FrameProcessor:
    """Write a KITTI image folder's frames (at the working resolution) and their times; returns the processor used."""
    source_w, source_h = _image_size(files[0])
    processor = FrameProcessor(
        _pinhole(P, source_w, source_h),
        working_size(source_w, source_h, cfg.image.width_px, cfg.image.upscale),
        cfg.image.interpolation,
    )
    trace.set_camera(label, processor, (source_w, source_h))
    rows = _write_frames(trace, files, processor, label, cfg.image.keep_original)
    trace.set_times(times_ns, time_base, frame_rows=rows)
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
    try:
        T_camx_cam0 = se3(np.eye(3), np.linalg.solve(P[:, :3], P[:, 3]))
    except np.linalg.LinAlgError:
        raise InputError(f"P_rect_0{cam_index} has a singular 3x3 part (not a camera matrix)", cam_path) from None
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


def _save_oxts(trace: TraceWriter, times: np.ndarray, oxts: np.ndarray) -> dict[str, int]:
    """gps.npz, imu.npz and speed.npz from the OXTS packets; packets with non-finite values are skipped and counted."""
    used = list(range(0, 9)) + list(range(11, 14)) + list(range(17, 20)) + [23]
    finite = np.all(np.isfinite(oxts[:, used]), axis=1)
    for role in ("gps", "imu", "speed"):
        trace.skip(role, int(np.count_nonzero(~finite)))
    times, oxts = times[finite], oxts[finite]
    gps, imu, speed = empty_gps_series(), empty_imu_series(), empty_speed_series()
    quats = Rotation.from_euler("ZYX", oxts[:, [5, 4, 3]]).as_quat() if len(oxts) else np.zeros((0, 4))
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
    out = trace.out_dir
    return {"gps": gps.save(out / "gps.npz"), "imu": imu.save(out / "imu.npz"), "speed": speed.save(out / "speed.npz")}


def _camera_times(stamps_path: Path, n_files: int, step_ns: int) -> tuple[np.ndarray, str]:
    """(frame times ns, time base) from a raw drive camera's timestamps.txt, or every `step_ns` without one."""
    if not stamps_path.is_file():
        return np.arange(n_files, dtype=np.int64) * step_ns, "relative"
    times = parse_timestamps(stamps_path)
    if len(times) != n_files:
        raise InputError(f"{len(times)} timestamps for {n_files} images", stamps_path)
    return times, "unix"


def ingest_kitti_raw(drive: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    """Read a KITTI raw `..._sync` drive folder into `trace`."""
    cam_dir = _choose_camera(drive, cfg.topics.camera)
    cam_index = int(cam_dir.name[-1])
    how = "chosen with --topic camera" if cfg.topics.camera else "default choice"
    trace.notes.append(f"camera: {cam_dir.name} ({how})")
    files = _image_files(cam_dir / "data")
    T_vehicle_camera, P, rect_size = kitti_raw_extrinsics(drive.parent, cam_index)
    source_size = _image_size(files[0])
    if source_size != rect_size:
        raise InputError(
            f"images are {source_size[0]}x{source_size[1]} but S_rect_0{cam_index} says {rect_size[0]}x{rect_size[1]} "
            "(only rectified _sync drives are supported)",
            cam_dir,
        )
    step_ns = round(cfg.kitti_time_step_s * 1e9)
    times, time_base = _camera_times(cam_dir / "timestamps.txt", len(files), step_ns)
    _check_increasing(times, f"camera {cam_dir.name}", cam_dir / "timestamps.txt")
    oxts_times, oxts = read_oxts(drive, step_ns, use_timestamps=time_base == "unix")
    trace.set_extrinsics(
        config_extrinsics(cfg) or Extrinsics(T_vehicle_camera, float(T_vehicle_camera[2, 3]), "kitti_calib")
    )
    _write_camera(trace, files, times, P, cfg, cam_dir.name, time_base)
    trace.add_sensor("camera", cam_dir.name, "png", len(files))
    for name, n in _save_oxts(trace, oxts_times, oxts).items():
        trace.add_sensor(name, "oxts", "oxts", n)


def _odometry_camera(folder: Path, cfg: IngestConfig) -> Path:
    names = {p.name for p in folder.iterdir()}
    wanted = cfg.topics.camera
    if wanted is None:
        wanted = next((n for n in ("image_l", "image_0", "image_2") if n in names), None)
    if wanted is None or wanted.strip("/") not in names:
        raise InputError("KITTI odometry folder without an image folder (image_l/, image_0/ or image_2/)", folder)
    return folder / wanted.strip("/")


def _odometry_poses(folder: Path, n_images: int, cfg: IngestConfig) -> np.ndarray | None:
    """(N, 4, 4) T_world_camera from poses.txt, or None when there is none (and none is required)."""
    poses_path = folder / "poses.txt"
    if not poses_path.is_file():
        if cfg.require_pose_source:
            raise InputError("KITTI odometry folder without poses.txt: no pose source", folder)
        return None
    try:
        rows = np.loadtxt(poses_path, ndmin=2)
    except ValueError as e:
        raise InputError(f"unreadable poses ({str(e).splitlines()[0]})", poses_path) from None
    if rows.shape[1] != 12 or len(rows) != n_images:
        raise InputError(f"{len(rows)} poses of {rows.shape[1]} values for {n_images} images", poses_path)
    bad = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
    if bad.size:
        raise InputError(f"pose on line {int(bad[0]) + 1} has non-finite values", poses_path)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    for i, T in enumerate(poses):
        problem = rigid_problem(T)
        if problem:
            raise InputError(f"pose on line {i + 1} {problem}", poses_path)
    return poses


def _odometry_times(folder: Path, n_images: int, cfg: IngestConfig) -> tuple[np.ndarray, str]:
    """Frame times from times.txt (seconds), else every kitti_time_step_s (10 Hz by default)."""
    times_path = folder / "times.txt"
    if not times_path.is_file():
        return np.arange(n_images, dtype=np.int64) * round(cfg.kitti_time_step_s * 1e9), "no times.txt"
    try:
        seconds = np.loadtxt(times_path, ndmin=1)
    except ValueError as e:
        raise InputError(f"unreadable times ({str(e).splitlines()[0]})", times_path) from None
    if seconds.ndim != 1 or len(seconds) != n_images:
        raise InputError(f"{len(seconds)} times for {n_images} images", times_path)
    if not np.all(np.isfinite(seconds)) or np.any(np.abs(seconds) > 1e9):
        raise InputError("times must be finite seconds since the sequence start", times_path)
    times = np.round(seconds * 1e9).astype(np.int64)
    _check_increasing(times, "times.txt", times_path)
    return times, "times.txt"


def ingest_kitti_odometry(folder: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    """Read a KITTI odometry sequence folder (image_l/ or image_0X/, poses.txt, calib.txt) into `trace`."""
    _odometry(folder, cfg, trace)


def _odometry(folder: Path, cfg: IngestConfig, trace: TraceWriter) -> tuple[Path, dict[str, np.ndarray], np.ndarray]:
    """The odometry ingest; (camera folder, calib.txt values, frame times) for the stereo reader."""
    cam_dir = _odometry_camera(folder, cfg)
    files = _image_files(cam_dir)
    calib_path = folder / "calib.txt"
    if not calib_path.is_file():
        raise InputError("KITTI odometry folder without calib.txt (needed for the intrinsics)", folder)
    calib = parse_calib_file(calib_path)
    P = _need(calib, _P_KEYS.get(cam_dir.name, "P0"), 12, calib_path).reshape(3, 4)
    poses = _odometry_poses(folder, len(files), cfg)
    times, times_from = _odometry_times(folder, len(files), cfg)
    height_m = cfg.extrinsics.camera_height_m or KITTI_CAMERA_HEIGHT_M
    trace.set_extrinsics(config_extrinsics(cfg) or Extrinsics(camera_mount(0.0, 0.0, height_m), height_m, "default"))
    _write_camera(trace, files, times, P, cfg, cam_dir.name, "relative")
    trace.add_sensor("camera", cam_dir.name, "png", len(files))
    if poses is not None:
        np.savez(trace.out_dir / "poses.npz", t_ns=times, T_world_camera=poses)
        trace.add_sensor("poses", "poses.txt", "kitti_poses", len(poses))
    step = f"frames at {cfg.kitti_time_step_s:g} s" if times_from == "no times.txt" else "times from times.txt"
    trace.notes.append(f"camera: {cam_dir.name}; {step}")
    return cam_dir, calib, times


_P_KEYS = {"image_l": "P0", "image_0": "P0", "image_r": "P1", "image_1": "P1", "image_2": "P2", "image_3": "P3"}
_STEREO_PAIRS = {"image_l": "image_r", "image_0": "image_1", "image_2": "image_3"}
_MAX_STEREO_OFFSET_M = 0.01  # off-axis offset of the right camera a rectified pair may have (KITTI P2/P3: ~1 mm)


def is_kitti_stereo(path: Path) -> bool:
    """A KITTI odometry folder with a stereo pair: image_l/ + image_r/, image_0/ + image_1/ or image_2/ + image_3/."""
    names = _names(path)
    return is_kitti_odometry(path) and any(left in names and right in names for left, right in _STEREO_PAIRS.items())


def stereo_baseline_m(P_left: np.ndarray, P_right: np.ndarray, path: Path) -> float:
    """How far (m) the right camera sits along the left camera's +x, from the two rectified 3x4 projections.

    Rectified cameras share K and differ by a translation t: P = K [I | t], so the right camera's centre in the
    left camera's frame is t_left - t_right. Refused when the pair is not rectified (different K, an off-axis offset).
    """
    K = P_left[:, :3]
    if not np.allclose(K, P_right[:, :3], rtol=1e-6, atol=1e-6):
        raise InputError("not a rectified stereo pair: the two cameras' P have different intrinsics", path)
    try:
        offset = np.linalg.solve(K, P_left[:, 3]) - np.linalg.solve(K, P_right[:, 3])
    except np.linalg.LinAlgError:
        raise InputError("stereo calibration has a singular camera matrix", path) from None
    if np.any(np.abs(offset[1:]) > _MAX_STEREO_OFFSET_M) or not offset[0] > 0:
        raise InputError(f"not a rectified stereo pair: the right camera sits at {offset.round(4).tolist()} m", path)
    return float(offset[0])


def ingest_kitti_stereo(folder: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    """A KITTI odometry stereo folder: the left camera as the trace's camera (as `ingest_kitti_odometry`), plus the
    right camera's frames in frames_right.imgs and the baseline in calibration.json (trace.py)."""
    cam_dir, calib, times = _odometry(folder, cfg, trace)
    right = _STEREO_PAIRS.get(cam_dir.name)
    if right is None or not (folder / right).is_dir():
        trace.notes.append(f"{cam_dir.name} is not the left camera of a stereo pair: the trace has one camera")
        return
    calib_path = folder / "calib.txt"
    P_left = _need(calib, _P_KEYS[cam_dir.name], 12, calib_path).reshape(3, 4)
    P_right = _need(calib, _P_KEYS[right], 12, calib_path).reshape(3, 4)
    baseline_m = stereo_baseline_m(P_left, P_right, calib_path)
    files = _image_files(folder / right)
    if len(files) != len(times):
        raise InputError(f"{len(files)} right images for {len(times)} left images", folder / right)
    left_size = _image_size(_image_files(cam_dir)[0])
    if _image_size(files[0]) != left_size:
        raise InputError(f"right images are not {left_size[0]}x{left_size[1]} as the left ones", folder / right)
    processor = FrameProcessor(
        _pinhole(P_right, *left_size),
        working_size(*left_size, cfg.image.width_px, cfg.image.upscale),
        cfg.image.interpolation,
    )
    _write_frames(trace, files, processor, right, keep=False, stem="frames_right")
    trace.add_calibration(right_camera=right, baseline_m=round(baseline_m, 6))
    trace.add_sensor("camera_right", right, "png", len(files))
    trace.notes.append(f"stereo: {right} stored as frames_right.imgs, baseline {baseline_m:.3f} m")
