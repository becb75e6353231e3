"""Recorders for the trace's time series: one per topic role, each fed decoded ROS messages and saved as an .npz.

Every recorder is called as `recorder(msg, log_time_ns)` during the single pass over the recording and keeps its
samples in growable numpy columns (output.Series), never in lists of message objects. A message with a non-finite
value the trace needs (NaN latitude, NaN pose, ...) is left out and counted in `skipped`: one bad sample among
thousands is noise a driver can emit, and the later stages interpolate over the gap; writing it would poison every
fused pose around it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from drivesim.stages.ingest.extrinsics import StaticTfTree, pose_from_msg, transform_from_msg
from drivesim.stages.ingest.output import (
    Series,
    empty_gps_series,
    empty_imu_series,
    empty_odometry_series,
    empty_speed_series,
)
from drivesim.stages.ingest.stamps import ordered_series

_NAN4 = np.full(4, np.nan)


def _finite(*values: Any) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(v, dtype=float)))) for v in values)


def field_of(msg: Any, *names: str) -> Any:
    """A message field under its ROS2 or ROS1 name (CameraInfo `k` vs `K`)."""
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(names[0])


def stamp_ns(msg: Any, log_time_ns: int) -> int:
    """The header stamp in ns, or the log time when the stamp is zero (drivers that do not fill it)."""
    stamp = msg.header.stamp
    t = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return t if t > 0 else int(log_time_ns)


class GpsRecorder:
    """sensor_msgs/NavSatFix -> gps.npz (position, status, ENU covariance)."""

    def __init__(self) -> None:
        self.series = empty_gps_series()
        self.skipped = 0

    def __call__(self, msg: Any, log_ns: int) -> None:
        covariance = np.asarray(msg.position_covariance, dtype=float).reshape(3, 3)
        if not _finite(msg.latitude, msg.longitude, msg.altitude, covariance):
            self.skipped += 1
            return
        self.series.append(
            t_ns=stamp_ns(msg, log_ns),
            lat_deg=msg.latitude,
            lon_deg=msg.longitude,
            alt_m=msg.altitude,
            status=msg.status.status,
            covariance_m2=covariance,
            covariance_type=msg.position_covariance_type,
        )

    def save(self, out_dir: Path) -> None:
        """Write gps.npz when there were fixes."""
        if len(self.series):
            self.series.save(out_dir / "gps.npz")


class ImuRecorder:
    """sensor_msgs/Imu -> imu.npz, rotated into the vehicle frame when /tf_static relates the IMU frame to it.

    :param tf: the static transforms.
    :param vehicle_frame: the trace's vehicle frame in that tree (None: the IMU data is used as is).
    """

    def __init__(self, tf: StaticTfTree, vehicle_frame: str | None) -> None:
        self.series = empty_imu_series()
        self._tf = tf
        self._vehicle_frame = vehicle_frame
        self._rotations: dict[str, tuple[np.ndarray, Rotation] | None] = {}
        self.skipped = 0

    def _rotation(self, frame_id: str) -> tuple[np.ndarray, Rotation] | None:
        """(R_vehicle_imu, its inverse as a Rotation), or None when no rotation is needed or known."""
        if frame_id not in self._rotations:
            T = self._tf.lookup(self._vehicle_frame, frame_id) if self._vehicle_frame and frame_id else None
            if T is None or np.allclose(T[:3, :3], np.eye(3), atol=1e-9):
                self._rotations[frame_id] = None
            else:
                self._rotations[frame_id] = (T[:3, :3], Rotation.from_matrix(T[:3, :3].T))
        return self._rotations[frame_id]

    def __call__(self, msg: Any, log_ns: int) -> None:
        rotation = self._rotation(msg.header.frame_id.lstrip("/"))
        w = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        a = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        q = msg.orientation
        has_orientation = float(field_of(msg, "orientation_covariance")[0]) != -1.0
        quat = np.array([q.x, q.y, q.z, q.w]) if has_orientation else _NAN4
        if not _finite(quat):
            quat = _NAN4  # the documented "no orientation"
        if rotation is not None:
            R, rot_imu_vehicle = rotation
            w, a = R @ w, R @ a
            if has_orientation and np.linalg.norm(quat) > 1e-9:
                # orientation of the vehicle = orientation of the IMU composed with R_imu_vehicle
                quat = (Rotation.from_quat(quat) * rot_imu_vehicle).as_quat()
        if not _finite(w, a):
            self.skipped += 1
            return
        self.series.append(
            t_ns=stamp_ns(msg, log_ns), angular_velocity_radps=w, linear_acceleration_mps2=a, orientation_xyzw=quat
        )

    def save(self, out_dir: Path) -> None:
        """Write imu.npz when there were samples."""
        if len(self.series):
            self.series.save(out_dir / "imu.npz")


class SpeedRecorder:
    """geometry_msgs/TwistStamped (or TwistWithCovarianceStamped) forward speed -> speed.npz."""

    def __init__(self) -> None:
        self.series = empty_speed_series()
        self.skipped = 0

    def __call__(self, msg: Any, log_ns: int) -> None:
        twist = msg.twist.twist if hasattr(msg.twist, "twist") else msg.twist
        self.add(stamp_ns(msg, log_ns), twist.linear.x)

    def add(self, t_ns: int, speed_mps: float) -> None:
        """One speed sample from another source (odometry)."""
        if not _finite(speed_mps):
            self.skipped += 1
            return
        self.series.append(t_ns=t_ns, speed_mps=speed_mps)

    def save(self, out_dir: Path) -> None:
        """Write speed.npz when there were samples."""
        if len(self.series):
            self.series.save(out_dir / "speed.npz")


class OdometryRecorder:
    """nav_msgs/Odometry -> odometry.npz; also feeds `speed` when the recording has no TwistStamped.

    :param speed: the speed recorder to feed with the odometry's forward velocity, or None.
    """

    def __init__(self, speed: SpeedRecorder | None) -> None:
        self.series = empty_odometry_series()
        self._speed = speed
        self.skipped = 0

    def __call__(self, msg: Any, log_ns: int) -> None:
        t = stamp_ns(msg, log_ns)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        v, w = msg.twist.twist.linear, msg.twist.twist.angular
        if not _finite((p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z, w.x, w.y, w.z)):
            self.skipped += 1
            return
        self.series.append(
            t_ns=t,
            position_m=(p.x, p.y, p.z),
            orientation_xyzw=(q.x, q.y, q.z, q.w),
            linear_velocity_mps=(v.x, v.y, v.z),
            angular_velocity_radps=(w.x, w.y, w.z),
        )
        if self._speed is not None:
            self._speed.add(t, v.x)

    def save(self, out_dir: Path) -> None:
        """Write odometry.npz when there were messages."""
        if len(self.series):
            self.series.save(out_dir / "odometry.npz")


class TfPoseRecorder:
    """Vehicle poses from dynamic /tf (e.g. odom -> base_link) -> odometry.npz, for recordings without Odometry.

    :param vehicle_frames: frame names that are the vehicle; the first one /tf moves is recorded.
    """

    def __init__(self, vehicle_frames: list[str]) -> None:
        self.series = Series({"T_parent_vehicle": ((4, 4), np.float64)})
        self._vehicle_frames = set(vehicle_frames)
        self.child: str | None = None
        self.skipped = 0

    def __call__(self, msg: Any, log_ns: int) -> None:
        for transform in msg.transforms:
            child = transform.child_frame_id.lstrip("/")
            if child not in self._vehicle_frames or transform.header.frame_id.lstrip("/") in self._vehicle_frames:
                continue
            if self.child is None:
                self.child = child
            if child == self.child:
                T = transform_from_msg(transform.transform.translation, transform.transform.rotation)
                if not _finite(T):
                    self.skipped += 1
                    continue
                self.series.append(t_ns=stamp_ns(transform, log_ns), T_parent_vehicle=T)

    def has_poses(self) -> bool:
        """True when /tf moved the vehicle at least twice (enough for velocities)."""
        return len(self.series) >= 2

    def save(self, out_dir: Path, tf: StaticTfTree, vehicle_frame: str | None) -> None:
        """odometry.npz of the trace's vehicle frame: velocities by forward differences in the vehicle frame."""
        raw = {"t_ns": self.series.columns["t_ns"].array(), "T": self.series.columns["T_parent_vehicle"].array()}
        ordered = ordered_series(raw, "/tf vehicle poses")  # sorted, one pose per stamp
        t_ns, T = ordered["t_ns"], ordered["T"]
        T_child_vehicle = tf.lookup(self.child, vehicle_frame) if vehicle_frame and self.child else None
        if T_child_vehicle is not None:
            T = T @ T_child_vehicle
        R = T[:, :3, :3]
        dt_s = np.diff(t_ns) / 1e9
        v_world = np.diff(T[:, :3, 3], axis=0) / dt_s[:, None]
        v_body = np.einsum("nji,nj->ni", R[:-1], v_world)
        w_body = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec() / dt_s[:, None]
        np.savez(
            out_dir / "odometry.npz",
            t_ns=t_ns,
            position_m=T[:, :3, 3],
            orientation_xyzw=Rotation.from_matrix(R).as_quat(),
            linear_velocity_mps=np.vstack([v_body, v_body[-1:]]),
            angular_velocity_radps=np.vstack([w_body, w_body[-1:]]),
        )


class GroundTruthPoseRecorder:
    """geometry_msgs/PoseStamped ground truth of synthetic recordings -> ground_truth.npz (T_world_vehicle)."""

    def __init__(self) -> None:
        self.series = Series({"T_world_vehicle": ((4, 4), np.float64)})
        self.skipped = 0

    def __call__(self, msg: Any, log_ns: int) -> None:
        T = pose_from_msg(msg.pose.position, msg.pose.orientation)
        if not _finite(T):
            self.skipped += 1
            return
        self.series.append(t_ns=stamp_ns(msg, log_ns), T_world_vehicle=T)

    def save(self, out_dir: Path) -> None:
        """Write ground_truth.npz when there were poses."""
        if len(self.series):
            self.series.save(out_dir / "ground_truth.npz")
