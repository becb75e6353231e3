"""The trace's sensor series (gps/imu/speed/odometry/poses/ground_truth .npz, schema in `stages/ingest/trace.py`),
loaded as small typed records of numpy arrays for the pose estimator.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivesim.pipeline.errors import InputError


@dataclass
class GpsSeries:
    """GNSS fixes: WGS84 position, NavSatStatus (-1 no fix) and ENU position covariance (m^2)."""

    t_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    status: np.ndarray
    covariance_m2: np.ndarray
    covariance_type: np.ndarray


@dataclass
class ImuSeries:
    """IMU samples in the vehicle frame; orientation_xyzw is NaN when the sensor gives none."""

    t_ns: np.ndarray
    angular_velocity_radps: np.ndarray
    linear_acceleration_mps2: np.ndarray
    orientation_xyzw: np.ndarray


@dataclass
class SpeedSeries:
    """Forward speed of the vehicle (wheel odometry, TwistStamped, OXTS vf)."""

    t_ns: np.ndarray
    speed_mps: np.ndarray


@dataclass
class OdometrySeries:
    """Odometry poses in the odometry frame; velocities in the vehicle (child) frame."""

    t_ns: np.ndarray
    position_m: np.ndarray
    orientation_xyzw: np.ndarray
    linear_velocity_mps: np.ndarray
    angular_velocity_radps: np.ndarray


@dataclass
class GivenPoses:
    """Camera poses shipped with the recording (KITTI odometry ground truth)."""

    t_ns: np.ndarray
    T_world_camera: np.ndarray


@dataclass
class GroundTruthPoses:
    """Vehicle poses of a synthetic recording, in the synth world's ENU frame."""

    t_ns: np.ndarray
    T_world_vehicle: np.ndarray


@dataclass
class SensorSeries:
    """Every pose-related series of a trace; a field is None when the recording lacks that sensor."""

    gps: GpsSeries | None = None
    imu: ImuSeries | None = None
    speed: SpeedSeries | None = None
    odometry: OdometrySeries | None = None
    given_poses: GivenPoses | None = None
    ground_truth: GroundTruthPoses | None = None


# file name -> (record class, {field: (dtype, trailing shape)})
_SCHEMA: dict[str, tuple[type, dict[str, tuple[type, tuple[int, ...]]]]] = {
    "gps": (
        GpsSeries,
        {
            "t_ns": (np.int64, ()),
            "lat_deg": (np.float64, ()),
            "lon_deg": (np.float64, ()),
            "alt_m": (np.float64, ()),
            "status": (np.int8, ()),
            "covariance_m2": (np.float64, (3, 3)),
            "covariance_type": (np.uint8, ()),
        },
    ),
    "imu": (
        ImuSeries,
        {
            "t_ns": (np.int64, ()),
            "angular_velocity_radps": (np.float64, (3,)),
            "linear_acceleration_mps2": (np.float64, (3,)),
            "orientation_xyzw": (np.float64, (4,)),
        },
    ),
    "speed": (SpeedSeries, {"t_ns": (np.int64, ()), "speed_mps": (np.float64, ())}),
    "odometry": (
        OdometrySeries,
        {
            "t_ns": (np.int64, ()),
            "position_m": (np.float64, (3,)),
            "orientation_xyzw": (np.float64, (4,)),
            "linear_velocity_mps": (np.float64, (3,)),
            "angular_velocity_radps": (np.float64, (3,)),
        },
    ),
    "poses": (GivenPoses, {"t_ns": (np.int64, ()), "T_world_camera": (np.float64, (4, 4))}),
    "ground_truth": (GroundTruthPoses, {"t_ns": (np.int64, ()), "T_world_vehicle": (np.float64, (4, 4))}),
}

_FIELD_OF_FILE = {"poses": "given_poses"}


def make_series(cls: type, path: str | Path | None = None, **arrays: np.ndarray):
    """Build one series record, checking shapes against the trace schema and sorting it by time.

    :param cls: one of GpsSeries, ImuSeries, SpeedSeries, OdometrySeries, GivenPoses, GroundTruthPoses.
    :param path: the file the arrays came from, named in errors.
    :raises InputError: a field is missing or has the wrong shape.
    """
    name = next(n for n, (c, _) in _SCHEMA.items() if c is cls)
    fields = _SCHEMA[name][1]
    where = path if path is not None else f"{name} series"
    missing = sorted(set(fields) - set(arrays))
    if missing:
        raise InputError(f"{name} series lacks {', '.join(missing)}", where)
    t_ns = np.asarray(arrays["t_ns"]).astype(np.int64).reshape(-1)
    m = len(t_ns)
    out = {}
    for field, (dtype, trailing) in fields.items():
        a = np.asarray(arrays[field]).astype(dtype, copy=False)
        if a.shape != (m, *trailing):
            raise InputError(f"{name}.{field} has shape {a.shape}, expected {(m, *trailing)}", where)
        out[field] = a
    order = np.argsort(t_ns, kind="stable")
    if np.any(order != np.arange(m)):
        out = {k: v[order] for k, v in out.items()}
    return cls(**out)


def load_series(trace_dir: Path) -> SensorSeries:
    """Read whichever of gps/imu/speed/odometry/poses/ground_truth .npz the trace folder holds.

    :raises InputError: a series file is unreadable or does not match the trace schema.
    """
    trace_dir = Path(trace_dir)
    found = {}
    for name, (cls, _) in _SCHEMA.items():
        path = trace_dir / f"{name}.npz"
        if not path.is_file():
            continue
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read series: {e}", path) from e
        record = make_series(cls, path, **arrays)
        if len(record.t_ns) > 0:
            found[_FIELD_OF_FILE.get(name, name)] = record
    return SensorSeries(**found)
