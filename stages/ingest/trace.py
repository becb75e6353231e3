"""The trace artifact (`<workspace>/trace/`): what `drivesim ingest` writes and every later stage reads.

Frames: camera optical (x right, y down, z forward); vehicle: x forward, y left, z up (REP-103), origin on the
ground below the rear axle where known (else below the IMU/GPS unit); times are int64 nanoseconds since the Unix
epoch (or since the recording's start when the source has no absolute time, see `calibration.json:time_base`).
Header stamps are used; a zero stamp falls back to the message's log time. KITTI raw stamps are the drive's clock
as logged (local time, read as if UTC).

Files (N = frame count; frames are image stacks, `sim/image_stack.py`: one JPEG (quality 97, 4:4:4) or PNG
per frame, decoded one frame at a time; other arrays are .npy):
    frames.imgs             uint8   (N, H, W, 3)  RGB, undistorted, at the working resolution (`TraceInfo.frames()`;
                            traces written as frames.npy by earlier versions load as well)
    frame_times_ns.npy      int64   (N,)          camera stamp of each frame, strictly increasing
    calibration.json        {
        "width_px": W, "height_px": H,            working resolution of the frames
        "K": [[fx,0,cx],[0,fy,cy],[0,0,1]],       pinhole intrinsics at the working resolution (pixels, pixel-centre
                                                  convention of sim.geometry.scale_intrinsics); after undistortion
                                                  this is CameraInfo P[:3,:3] scaled
        "K_source": 3x3,                          the same intrinsics at the recorded resolution
        "source_width_px", "source_height_px",    resolution of the recorded images
        "distortion_model": "plumb_bob" | "rational_polynomial" | "equidistant" | "none",  what was removed
        "T_vehicle_camera": 4x4,                  camera optical frame -> vehicle frame (metres)
        "camera_height_m": float | null,          camera optical centre above the ground (null: unknown; the
                                                  z of T_vehicle_camera is then relative to base_link, not the ground)
        "extrinsics_source": "tf_static" | "kitti_calib" | "config" | "default" | "sfm_road_plane" (video),
        "time_base": "unix" | "relative",
        "right_camera": str, "baseline_m": float  only with frames_right.imgs (below)
    }
    sources.json            {"recording": str, "format": a name of run.FORMATS ("ros1" | "rosbag2" | "mcap" |
                             "kitti_raw" | "kitti_odometry" | "kitti_odometry_stereo" | ...), "camera_topic": str,
                             "sensors": {name: {"topic", "type", "message_count"}}}
                            (the same `sensors` as the manifest summary; KITTI "topics" are folder names)
    frames_original.imgs    uint8   (N, Hs, Ws, 3) only with image.keep_original: undistorted frames at the
                            recorded resolution (intrinsics K_source)
  Stereo (a KITTI odometry stereo folder, format "kitti_odometry_stereo"):
    frames_right.imgs       uint8   (N, H, W, 3)  the right camera of the rectified pair, frame i taken with frame i
                            of frames.imgs, at the same working resolution and with the same intrinsics K; the right
                            camera's optical centre is `calibration.json:baseline_m` metres along the left camera's
                            +x axis (x_right = x_left - baseline_m in left camera coordinates), same orientation.
                            `right_camera` names its source folder (image_r). TraceInfo.baseline_m / right_frames().
  Optional series (present when the recording has them; each an .npz of equal-length arrays sorted by t_ns):
    gps.npz       t_ns int64 (M,); lat_deg, lon_deg, alt_m float64 (M,); status int8 (M,) (NavSatStatus:
                  -1 no fix, 0 fix, 1 SBAS, 2 GBAS); covariance_m2 float64 (M,3,3) ENU position covariance;
                  covariance_type uint8 (M,)
    imu.npz       t_ns (M,); angular_velocity_radps float64 (M,3) and linear_acceleration_mps2 (M,3) in the vehicle
                  frame; orientation_xyzw float64 (M,4) of the vehicle in the IMU's world frame (NaN when the
                  source has none)
    speed.npz     t_ns (M,); speed_mps float64 (M,) forward speed (TwistStamped / Odometry twist / OXTS vf)
    odometry.npz  t_ns (M,); position_m float64 (M,3); orientation_xyzw (M,4); linear_velocity_mps (M,3) and
                  angular_velocity_radps (M,3) in the child (vehicle) frame. From nav_msgs/Odometry, or else from
                  /tf poses of the vehicle frame (velocities then by forward differences)
    lidar_points.npy  float32 (P, 4): x, y, z (m, vehicle frame) and intensity (NaN when absent) of every
                  PointCloud2 scan, concatenated in log-time order (NaN/inf points dropped); open with mmap_mode="r"
    lidar_scans.npz   t_ns int64 (S,); start int64 (S,), count int64 (S,): scan s is
                  lidar_points[start[s] : start[s] + count[s]]
    poses.npz     t_ns (M,); T_world_camera float64 (M,4,4): given camera poses (KITTI odometry ground truth; a
                  video's metric SfM poses, world z up on the road or local ENU with a GPS track: video_trace.py)
    ground_truth.npz  (synthetic recordings only) t_ns (M,); T_world_vehicle float64 (M,4,4) in the synth world's
                  ENU frame; depth at the frame times is in gt_depth.npy float32 (N,H,W) metres (inf = sky),
                  resized to the working resolution by nearest neighbour, only with `ground_truth_depth: true`

`validate_trace(path)` checks all of this (without reading the frames) and returns a `TraceInfo`: shapes and dtypes,
finite intrinsics with positive focal lengths, a finite rigid T_vehicle_camera, strictly increasing frame times,
finite series values (except imu orientation, NaN when absent) sorted by time, rigid given poses.
The manifest summary (stage.IngestSummary) also counts, per sensor, the messages ingest skipped as unreadable or
non-finite (`skipped`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.json_files import read_json
from drivesim.sim.image_stack import ImageStack, ImageStackError, open_frames, read_meta, stack_path, stored_file

CALIBRATION_KEYS = (
    "width_px",
    "height_px",
    "K",
    "source_width_px",
    "source_height_px",
    "distortion_model",
    "T_vehicle_camera",
    "camera_height_m",
    "extrinsics_source",
    "time_base",
)
SERIES_COLUMNS: dict[str, dict[str, tuple[tuple[int, ...], str]]] = {
    "gps": {
        "lat_deg": ((), "f"),
        "lon_deg": ((), "f"),
        "alt_m": ((), "f"),
        "status": ((), "i"),
        "covariance_m2": ((3, 3), "f"),
        "covariance_type": ((), "u"),
    },
    "imu": {
        "angular_velocity_radps": ((3,), "f"),
        "linear_acceleration_mps2": ((3,), "f"),
        "orientation_xyzw": ((4,), "f"),
    },
    "speed": {"speed_mps": ((), "f")},
    "odometry": {
        "position_m": ((3,), "f"),
        "orientation_xyzw": ((4,), "f"),
        "linear_velocity_mps": ((3,), "f"),
        "angular_velocity_radps": ((3,), "f"),
    },
    "poses": {"T_world_camera": ((4, 4), "f")},
    "ground_truth": {"T_world_vehicle": ((4, 4), "f")},
}


# Series columns that may hold NaN: "not measured" (IMU without orientation).
NAN_ALLOWED = {("imu", "orientation_xyzw")}


def rigid_problem(T: np.ndarray) -> str | None:
    """Why `T` is not a finite rigid 4x4 transform, or None when it is."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"is {T.shape}, not 4x4"
    if not np.all(np.isfinite(T)):
        return "has non-finite values"
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        return "has a rotation part that is not a rotation (R R^T != I or det < 0)"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        return "has a last row other than 0 0 0 1"
    return None


@dataclass(frozen=True)
class TraceInfo:
    """What a valid trace holds, for later stages (arrays are opened lazily from `path`)."""

    path: Path
    frame_count: int
    width_px: int
    height_px: int
    K: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float | None
    duration_s: float
    time_base: str
    calibration: dict[str, Any]
    sources: dict[str, Any]
    series: tuple[str, ...]
    has_gt_depth: bool
    baseline_m: float | None = None
    """Stereo traces: the right camera's offset along the left camera's +x (m); None without frames_right.imgs."""

    def frames(self) -> np.ndarray | ImageStack:
        """The frames, uint8 (N, H, W, 3), read one at a time (`frames()[i]`; an older trace's .npy memory-mapped)."""
        return _open_stored(self.path, "frames")

    def frame_times_ns(self) -> np.ndarray:
        """int64 (N,) frame stamps."""
        return np.load(self.path / "frame_times_ns.npy")

    def load_series(self, name: str) -> dict[str, np.ndarray] | None:
        """The arrays of series `name` (gps, imu, speed, odometry, poses, ground_truth, lidar_scans), or None."""
        if name not in self.series:
            return None
        with np.load(self.path / f"{name}.npz") as data:
            return {k: data[k] for k in data.files}

    def lidar_points(self) -> np.ndarray | None:
        """lidar_points.npy memory-mapped read-only, float32 (P, 4), or None (scan rows: load_series("lidar_scans"))."""
        return np.load(self.path / "lidar_points.npy", mmap_mode="r") if "lidar_scans" in self.series else None

    def right_frames(self) -> np.ndarray | ImageStack | None:
        """The right camera's frames as `frames()`, uint8 (N, H, W, 3), or None for a one-camera trace."""
        return _open_stored(self.path, "frames_right") if self.baseline_m is not None else None

    def gt_depth(self) -> np.ndarray | None:
        """gt_depth.npy memory-mapped read-only, float32 (N, H, W) metres, or None."""
        return np.load(self.path / "gt_depth.npy", mmap_mode="r") if self.has_gt_depth else None


def _fail(path: Path, problem: str) -> InputError:
    return InputError(f"invalid trace: {problem}", path)


def _npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype, int]:
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read_header(f)  # the header only: frames are never read here
            data_offset = f.tell()
    except (OSError, ValueError) as e:
        raise _fail(path, f"unreadable .npy ({e})") from e
    size = path.stat().st_size - data_offset
    if size < int(np.prod(shape)) * dtype.itemsize:
        raise _fail(path, "file shorter than its header says (truncated)")
    return shape, dtype, data_offset


def _open_stored(folder: Path, stem: str) -> np.ndarray | ImageStack:
    """The per-frame array `stem` of a trace (its image stack, or the .npy of an older trace); InputError if absent
    or unreadable."""
    path = stored_file(folder, stem)
    if path is None:
        raise _fail(stack_path(folder, stem), "missing file")
    try:
        return open_frames(path)
    except (OSError, ValueError) as e:
        raise _fail(path, f"unreadable ({e}); run `{TRACE_HINT} --force`") from e


def _stored_layout(folder: Path, stem: str) -> tuple[Path, tuple[int, ...], np.dtype] | None:
    """(file, shape, dtype) of the per-frame array `stem` (image stack or .npy), reading only its header; None when
    absent."""
    path = stored_file(folder, stem)
    if path is None:
        return None
    if path.suffix == ".npy":
        shape, dtype, _ = _npy_header(path)
        return path, shape, dtype
    try:
        meta, _ = read_meta(path)
    except (OSError, ImageStackError) as e:
        raise _fail(path, f"unreadable image stack ({e})") from e
    return path, tuple(int(s) for s in meta["shape"]), np.dtype(meta["dtype"])


def _check_calibration(path: Path, calibration: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(K, T_vehicle_camera) after checking the keys, finite intrinsics and a rigid transform."""
    file = path / "calibration.json"
    missing = [k for k in CALIBRATION_KEYS if k not in calibration]
    if missing:
        raise _fail(file, f"missing keys {missing}")
    try:
        K = np.asarray(calibration["K"], dtype=float)
        T = np.asarray(calibration["T_vehicle_camera"], dtype=float)
    except (TypeError, ValueError) as e:
        raise _fail(file, f"K and T_vehicle_camera must be numeric matrices ({e})") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise _fail(file, f"K must be 3x3, finite, with positive focal lengths, got {K.tolist()}")
    if rigid_problem(T) is not None:
        raise _fail(file, f"T_vehicle_camera must be a 4x4 rigid transform (it {rigid_problem(T)})")
    height = calibration["camera_height_m"]
    if height is not None and not (isinstance(height, int | float) and np.isfinite(height)):
        raise _fail(file, f"camera_height_m must be a finite number or null, got {height!r}")
    return K, T


def _check_frames(path: Path, width: int, height: int) -> tuple[int, np.ndarray]:
    """(frame count, frame times) after checking the frames' header and the times."""
    layout = _stored_layout(path, "frames")
    if layout is None:
        raise _fail(stack_path(path, "frames"), "missing file")
    file, shape, dtype = layout
    if dtype != np.uint8 or len(shape) != 4 or shape[1:] != (height, width, 3) or shape[0] < 1:
        raise _fail(file, f"expected uint8 (N >= 1, {height}, {width}, 3), got {dtype} {shape}")
    n = shape[0]
    times = np.load(path / "frame_times_ns.npy")
    if times.dtype != np.int64 or times.shape != (n,):
        raise _fail(path / "frame_times_ns.npy", f"expected int64 ({n},), got {times.dtype} {times.shape}")
    if n > 1 and np.any(np.diff(times) <= 0):
        raise _fail(path / "frame_times_ns.npy", "frame times are not strictly increasing")
    return n, times


def _check_series(path: Path) -> list[str]:
    """The series present, after checking their columns' shapes, kinds, finiteness and time order."""
    series = []
    for name, columns in SERIES_COLUMNS.items():
        file = path / f"{name}.npz"
        if not file.is_file():
            continue
        with np.load(file) as data:
            if "t_ns" not in data.files:
                raise _fail(file, "no t_ns array")
            m = len(data["t_ns"])
            if m > 1 and np.any(np.diff(data["t_ns"]) < 0):
                raise _fail(file, "t_ns is not sorted")
            for col, (row_shape, kind) in columns.items():
                if col not in data.files:
                    raise _fail(file, f"no {col} array")
                arr = data[col]
                if arr.shape != (m, *row_shape) or arr.dtype.kind != kind:
                    raise _fail(file, f"{col} is {arr.dtype} {arr.shape}, expected ({m}, {row_shape}) of kind {kind}")
                if kind == "f" and (name, col) not in NAN_ALLOWED and not np.all(np.isfinite(arr)):
                    raise _fail(file, f"{col} has non-finite values")
        series.append(name)
    return series


def _check_extra_arrays(path: Path, calibration: dict[str, Any], n: int) -> tuple[list[str], bool, float | None]:
    """Check the optional arrays (originals, lidar, ground-truth depth, right camera); (extra series, gt depth?,
    stereo baseline or None)."""
    width, height = int(calibration["width_px"]), int(calibration["height_px"])
    originals = _stored_layout(path, "frames_original")
    if originals is not None:
        file, o_shape, o_dtype = originals
        source = (int(calibration["source_height_px"]), int(calibration["source_width_px"]), 3)
        if o_dtype != np.uint8 or o_shape != (n, *source):
            raise _fail(file, f"expected uint8 ({n}, {source}), got {o_dtype} {o_shape}")
    series = []
    if (path / "lidar_points.npy").is_file() or (path / "lidar_scans.npz").is_file():
        if not (path / "lidar_scans.npz").is_file():
            raise _fail(path / "lidar_scans.npz", "missing file (lidar_points.npy needs it)")
        p_shape, p_dtype, _ = _npy_header(path / "lidar_points.npy")
        with np.load(path / "lidar_scans.npz") as scans:
            end = int((scans["start"] + scans["count"]).max()) if len(scans["t_ns"]) else 0
        if p_dtype != np.float32 or len(p_shape) != 2 or p_shape[1] != 4 or end > p_shape[0]:
            raise _fail(path / "lidar_points.npy", f"expected float32 (>= {end}, 4), got {p_dtype} {p_shape}")
        series.append("lidar_scans")
    has_gt_depth = (path / "gt_depth.npy").is_file()
    if has_gt_depth:
        d_shape, d_dtype, _ = _npy_header(path / "gt_depth.npy")
        if d_dtype != np.float32 or d_shape != (n, height, width):
            raise _fail(path / "gt_depth.npy", f"expected float32 ({n}, {height}, {width}), got {d_dtype} {d_shape}")
    return series, has_gt_depth, _check_right(path, calibration, n, width, height)


def _check_right(path: Path, calibration: dict[str, Any], n: int, width: int, height: int) -> float | None:
    right = _stored_layout(path, "frames_right")
    if right is None and "baseline_m" not in calibration:
        return None
    if right is None:
        raise _fail(stack_path(path, "frames_right"), "missing file (calibration.json gives a stereo baseline_m)")
    file, r_shape, r_dtype = right
    if r_dtype != np.uint8 or r_shape != (n, height, width, 3):
        raise _fail(file, f"expected uint8 ({n}, {height}, {width}, 3), got {r_dtype} {r_shape}")
    baseline = calibration.get("baseline_m")
    if not isinstance(baseline, int | float) or not np.isfinite(baseline) or baseline <= 0:
        raise _fail(path / "calibration.json", f"baseline_m must be a positive number of metres, got {baseline!r}")
    return float(baseline)


def validate_trace(path: Path | str) -> TraceInfo:
    """Check a trace folder against the schema above (files, shapes, dtypes, finite values, increasing times);
    return its TraceInfo.

    Raises InputError naming the file and the problem. Only headers and small arrays are read, never frames.
    """
    path = Path(path)
    if stored_file(path, "frames") is None:
        raise _fail(stack_path(path, "frames"), "missing file")
    for name in ("frame_times_ns.npy", "calibration.json", "sources.json"):
        if not (path / name).is_file():
            raise _fail(path / name, "missing file")
    try:
        calibration = read_json(path / "calibration.json")
        sources = read_json(path / "sources.json")
    except ValueError as e:  # not JSON, not UTF-8, nested too deeply, NaN
        raise _fail(path, f"unreadable JSON ({e})") from e
    if not isinstance(calibration, dict) or not isinstance(sources, dict):
        raise _fail(path, "calibration.json and sources.json must hold JSON objects")
    K, T = _check_calibration(path, calibration)
    n, times = _check_frames(path, int(calibration["width_px"]), int(calibration["height_px"]))
    series = _check_series(path)
    if "poses" in series:
        with np.load(path / "poses.npz") as data:
            problems = [rigid_problem(P) for P in data["T_world_camera"]]
        if any(problems):
            raise _fail(path / "poses.npz", f"T_world_camera {next(p for p in problems if p)}")
    extra_series, has_gt_depth, baseline_m = _check_extra_arrays(path, calibration, n)
    return TraceInfo(
        path=path,
        frame_count=n,
        width_px=int(calibration["width_px"]),
        height_px=int(calibration["height_px"]),
        K=K,
        T_vehicle_camera=T,
        camera_height_m=calibration["camera_height_m"],
        duration_s=float(times[-1] - times[0]) / 1e9 if n > 1 else 0.0,
        time_base=calibration["time_base"],
        calibration=calibration,
        sources=sources,
        series=tuple(series + extra_series),
        has_gt_depth=has_gt_depth,
        baseline_m=baseline_m,
    )


TRACE_HINT = "drivesim ingest PATH"


@dataclass
class TraceView:
    """The parts of a trace artifact that preprocess and build-world read.

    :param root: the trace folder.
    :param frames: (N, H, W, 3) uint8 RGB, decoded one frame at a time (`frames[i]`; slices stay lazy).
    :param frame_times_ns: (N,) int64 camera stamps.
    :param calibration: the contents of calibration.json.
    :param K: 3x3 intrinsics at the working resolution.
    :param T_vehicle_camera: 4x4 camera optical frame -> vehicle frame.
    """

    root: Path
    frames: np.ndarray | ImageStack
    frame_times_ns: np.ndarray
    calibration: dict[str, Any]
    K: np.ndarray
    T_vehicle_camera: np.ndarray
    info: TraceInfo


def open_trace(trace_dir: Path) -> TraceView:
    """Open the trace's frames (read one at a time), stamps and calibration; InputError naming the file when
    malformed."""
    info = validate_trace(trace_dir)
    frames = info.frames()
    try:
        calibration = read_json(trace_dir / "calibration.json")
        frame_times_ns = np.load(trace_dir / "frame_times_ns.npy")
    except FileNotFoundError as e:
        raise InputError(f"the trace lacks {Path(e.filename).name}; run `{TRACE_HINT}` again", trace_dir) from e
    except (OSError, ValueError) as e:
        raise InputError(f"unreadable trace: {e}; run `{TRACE_HINT}` again", trace_dir) from e
    for key in ("K", "T_vehicle_camera", "width_px", "height_px"):
        if key not in calibration:
            raise InputError(f"calibration.json lacks {key!r}", trace_dir)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise InputError(f"the frames must be uint8 (N, H, W, 3), got {frames.dtype} {frames.shape}", trace_dir)
    if frame_times_ns.shape != (frames.shape[0],) or np.any(np.diff(frame_times_ns) <= 0):
        raise InputError("frame_times_ns.npy must hold one strictly increasing stamp per frame", trace_dir)
    K = np.asarray(calibration["K"], dtype=float)
    T_vehicle_camera = np.asarray(calibration["T_vehicle_camera"], dtype=float)
    if K.shape != (3, 3) or T_vehicle_camera.shape != (4, 4):
        raise InputError("calibration.json: K must be 3x3 and T_vehicle_camera 4x4", trace_dir)
    return TraceView(trace_dir, frames, frame_times_ns, calibration, K, T_vehicle_camera, info)
