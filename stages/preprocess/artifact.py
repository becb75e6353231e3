"""The preprocessed artifact (`<workspace>/preprocessed/`): what `drivesim preprocess` writes and build-world reads.

Frames as in `sim/geometry.py` (world = local ENU with its origin at the first GPS fix, or the first pose when there
is no GPS; vehicle x forward / y left / z up; camera optical x right / y down / z forward). N = the number of frames
selected from the trace (`frames.start:stop:step` of the config), H x W = the trace's working resolution.

Files:
    poses.npz          one row per selected frame:
                       frame_index int64 (N,)      index of the frame in the trace's frames
                       t_ns int64 (N,)             the frame's camera stamp
                       x_m, y_m, z_m float64 (N,)  vehicle origin in the world frame
                       yaw_rad float64 (N,)        heading of vehicle x, counter-clockwise from east
                       speed_mps float64 (N,)      forward speed
                       curvature_1pm float64 (N,)  path curvature, + = turning left
                       arc_length_m float64 (N,)   distance driven since the first frame
                       T_world_vehicle float64 (N,4,4); T_world_camera float64 (N,4,4) (= T_world_vehicle @
                       T_vehicle_camera of the trace's calibration)
    depth.imgs         float16 (N, H, W): optical-axis depth in metres; no estimate (sky) = depth.max_depth_m.
                       An image stack (`sim/image_stack.py`): each frame's float16 bits in a 16-bit PNG, lossless,
                       read one frame at a time. float16 keeps 11 significant bits (under 0.05 % relative error); the
                       world's depth is float16 too and min-pooled from it, which rounding commutes with: the world is
                       the same as from float32. Artifacts written as depth.npy (float16 or float32) load as well
    origin.json        {"pose_source": str ("gps_imu", "odometry", "sfm", ...), "origin_lat_deg", "origin_lon_deg",
                        "origin_alt_m" (null without GPS), "residual_m": float | null (RMS distance between the fused
                        path and the raw position fixes), "depth_method": str, "max_depth_m": float,
                        "width_px": W, "height_px": H}
    depth_preview.png  a few frames above their colour-mapped depth, for people
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.json_files import read_json
from drivesim.sim.image_stack import ImageStack, open_frames, stored_file
from drivesim.sim.world import PATH_ARRAYS, PATH_ARRAYS_FLOAT

# poses.npz holds the same per-frame arrays as the world's path.npz: one schema, defined by the simulator's loader.
POSE_ARRAYS_FLOAT = PATH_ARRAYS_FLOAT
POSE_ARRAYS = PATH_ARRAYS
# The dtype preprocess stores depth in, and every dtype the loader accepts.
DEPTH_DTYPE = np.float16
DEPTH_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))
ORIGIN_KEYS = ("pose_source", "origin_lat_deg", "origin_lon_deg", "origin_alt_m", "residual_m", "depth_method")


@dataclass
class Preprocessed:
    """A loaded preprocessed artifact.

    :param root: the artifact folder.
    :param poses: the arrays of poses.npz (see the module docstring).
    :param depth_m: (N, H, W) float16 (or float32) depth, read one frame at a time (`depth_m[i]`).
    :param origin: the contents of origin.json.
    """

    root: Path
    poses: dict[str, np.ndarray]
    depth_m: np.ndarray | ImageStack
    origin: dict[str, Any]

    @property
    def frame_count(self) -> int:
        """Number of frames N."""
        return int(self.poses["t_ns"].shape[0])


def load_preprocessed(root: Path) -> Preprocessed:
    """Open and validate a preprocessed artifact; InputError naming the file for anything malformed."""
    root = Path(root)
    depth_file = stored_file(root, "depth")
    for name in ("poses.npz", "origin.json"):
        if not (root / name).is_file():
            raise InputError(f"missing {name}; run `drivesim preprocess --force` to rebuild it", root)
    if depth_file is None:
        raise InputError("missing depth.imgs; run `drivesim preprocess --force` to rebuild it", root)
    try:
        with np.load(root / "poses.npz") as data:
            poses = {k: np.asarray(data[k]) for k in data.files}
        depth = open_frames(depth_file)
        origin = read_json(root / "origin.json")
    except (OSError, ValueError) as e:
        raise InputError(f"unreadable preprocessed artifact: {e}", root) from e
    validate_preprocessed(root, poses, depth, origin)
    return Preprocessed(root=root, poses=poses, depth_m=depth, origin=origin)


def validate_preprocessed(
    root: Path, poses: dict[str, np.ndarray], depth_m: np.ndarray | ImageStack, origin: dict[str, Any]
) -> None:
    """Check the arrays of a preprocessed artifact against the schema above; InputError naming the file if not."""
    missing = [k for k in POSE_ARRAYS if k not in poses]
    if missing:
        raise InputError(f"poses.npz lacks {', '.join(missing)}", root)
    n = poses["t_ns"].shape[0]
    if n < 2:
        raise InputError(f"poses.npz has {n} frame(s); a drive needs at least 2", root)
    for key in POSE_ARRAYS_FLOAT:
        if poses[key].shape != (n,):
            raise InputError(f"poses.npz: {key} has shape {poses[key].shape}, expected ({n},)", root)
        if not np.all(np.isfinite(poses[key])):
            raise InputError(f"poses.npz: {key} has non-finite values", root)
    for key in ("T_world_vehicle", "T_world_camera"):
        if poses[key].shape != (n, 4, 4) or not np.all(np.isfinite(poses[key])):
            raise InputError(f"poses.npz: {key} must be finite ({n}, 4, 4), got {poses[key].shape}", root)
    if poses["frame_index"].shape != (n,) or np.any(np.diff(poses["frame_index"]) <= 0):
        raise InputError("poses.npz: frame_index must be strictly increasing", root)
    if np.any(np.diff(poses["t_ns"]) <= 0):
        raise InputError("poses.npz: t_ns must be strictly increasing", root)
    if depth_m.dtype not in DEPTH_DTYPES or depth_m.ndim != 3 or depth_m.shape[0] != n:
        raise InputError(f"depth must be float16 ({n}, H, W), got {depth_m.dtype} {depth_m.shape}", root)
    if not isinstance(origin, dict):
        raise InputError("origin.json must hold a JSON object; run `drivesim preprocess --force`", root)
    absent = [k for k in ORIGIN_KEYS if k not in origin]
    if absent:
        raise InputError(f"origin.json lacks {', '.join(absent)}", root)
