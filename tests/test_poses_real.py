"""Pose fusion on real recordings: the KITTI raw drive's OXTS (RTK GPS/INS) and a Husky robot's GPS+IMU+odometry bag."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import REAL_DATA
from scipy.spatial.transform import Rotation

from drivesim.stages.preprocess.poses import PoseConfig, enu_transformer, estimate_poses, fuse_gps_imu
from drivesim.stages.preprocess.series import GpsSeries, ImuSeries, OdometrySeries, SensorSeries, SpeedSeries

REAL = REAL_DATA
KITTI_DRIVE = REAL / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
HUSKY_BAG = REAL / "husky_gps_imu_odom.bag"

# oxts/dataformat.txt, in file order
OXTS_FIELDS = [
    *("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az", "af", "al", "au"),
    *("wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode"),
    "orimode",
]


def _kitti_time_ns(line: str) -> int:
    day, clock = line.strip().split(" ")
    whole, frac = clock.split(".")
    base = datetime.fromisoformat(f"{day}T{whole}+00:00")
    return int(base.timestamp()) * 1_000_000_000 + int(frac.ljust(9, "0")[:9])


def read_oxts(drive: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """KITTI raw OXTS packets: (t_ns, {field: values})."""
    t_ns = np.array([_kitti_time_ns(s) for s in (drive / "oxts" / "timestamps.txt").read_text().splitlines() if s])
    rows = [np.loadtxt(p) for p in sorted((drive / "oxts" / "data").glob("*.txt"))]
    data = np.vstack(rows)
    return t_ns, {name: data[:, i] for i, name in enumerate(OXTS_FIELDS)}


def oxts_series(t_ns: np.ndarray, o: dict[str, np.ndarray]) -> SensorSeries:
    """OXTS as the trace's series: fixes with pos_accuracy, vehicle-frame rates (f/l/u axes), orientation, vf."""
    m = len(t_ns)
    cov = np.zeros((m, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = cov[:, 2, 2] = o["pos_accuracy"] ** 2
    # OXTS yaw is the heading from east, counter-clockwise: the ENU yaw of the vehicle.
    q = Rotation.from_euler("ZYX", np.column_stack([o["yaw"], o["pitch"], o["roll"]])).as_quat()
    return SensorSeries(
        gps=GpsSeries(t_ns, o["lat"], o["lon"], o["alt"], np.zeros(m, np.int8), cov, np.full(m, 2, np.uint8)),
        imu=ImuSeries(
            t_ns,
            np.column_stack([o["wf"], o["wl"], o["wu"]]),
            np.column_stack([o["af"], o["al"], o["au"]]),
            q,
        ),
        speed=SpeedSeries(t_ns, o["vf"]),
    )


@pytest.fixture(scope="module")
def kitti():
    if not (KITTI_DRIVE / "oxts").is_dir():
        pytest.skip(f"KITTI raw drive not found at {KITTI_DRIVE}")
    return read_oxts(KITTI_DRIVE)


def test_kitti_oxts_fusion_follows_the_rtk_track(kitti):
    t_ns, o = kitti
    series = oxts_series(t_ns, o)
    fused = fuse_gps_imu(series, t_ns, PoseConfig())
    e, n, _ = enu_transformer(o["lat"][0], o["lon"][0], o["alt"][0]).transform(o["lon"], o["lat"], o["alt"])
    err = np.hypot(fused.x_m - e, fused.y_m - n)
    # OXTS is RTK-grade (pos_accuracy ~3 cm here): the fused track must stay on it
    assert err.max() < 0.1, f"max distance to the OXTS track {err.max():.3f} m"
    assert fused.fixes_rejected == 0
    length = fused.arc_length_m[-1]
    assert length == pytest.approx(107.0, abs=3.0)
    oxts_length = np.hypot(np.diff(e), np.diff(n)).sum()
    assert length == pytest.approx(oxts_length, rel=0.01)
    # a gentle RIGHT bend: the heading falls by ~8 degrees (from -150 to -157 deg, i.e. clockwise seen from above;
    # both the OXTS heading and the direction of the ENU track itself say so)
    turn_deg = np.degrees(np.unwrap(fused.yaw_rad)[-1] - fused.yaw_rad[0])
    oxts_turn_deg = np.degrees(np.unwrap(o["yaw"])[-1] - o["yaw"][0])
    assert -30.0 < turn_deg < -3.0
    assert turn_deg == pytest.approx(oxts_turn_deg, abs=1.0)
    yaw_err_deg = np.degrees(np.abs((fused.yaw_rad - o["yaw"] + np.pi) % (2 * np.pi) - np.pi))
    assert yaw_err_deg.max() < 1.5
    assert np.abs(fused.speed_mps - o["vf"]).max() < 0.2
    assert np.all(fused.curvature_1pm < 0.002)  # it never turns left noticeably
    assert fused.curvature_1pm.min() < -0.001
    assert fused.z_m == pytest.approx(o["alt"] - o["alt"][0], abs=0.3)
    # full 3D attitude: the fused heading with the IMU's roll and pitch
    R_oxts = Rotation.from_euler("ZYX", np.column_stack([o["yaw"], o["pitch"], o["roll"]]))
    angle_deg = np.degrees((R_oxts.inv() * Rotation.from_matrix(fused.T_world_vehicle[:, :3, :3])).magnitude())
    assert angle_deg.max() < 1.0  # measured 0.54 deg (the heading); level poses would be 2.8 deg off
    level = fuse_gps_imu(series, t_ns, PoseConfig(use_imu_tilt=False))
    assert np.allclose(level.T_world_vehicle[:, 2, :3], [0, 0, 1])


def read_husky(bag: Path) -> SensorSeries:
    """GPS, IMU and wheel odometry of the Husky bag as the trace's series (header stamps)."""
    from rosbags.highlevel import AnyReader

    fix, imu, odo = [], [], []
    with AnyReader([bag]) as reader:
        for con, _, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if con.msgtype == "sensor_msgs/msg/NavSatFix":
                cov = np.asarray(msg.position_covariance, dtype=float).reshape(3, 3)
                fix.append(
                    (t, msg.latitude, msg.longitude, msg.altitude, msg.status.status, cov, msg.position_covariance_type)
                )
            elif con.msgtype == "sensor_msgs/msg/Imu":
                a, w, q = msg.linear_acceleration, msg.angular_velocity, msg.orientation
                imu.append((t, (w.x, w.y, w.z), (a.x, a.y, a.z), (q.x, q.y, q.z, q.w)))
            elif con.msgtype == "nav_msgs/msg/Odometry":
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                v, w = msg.twist.twist.linear, msg.twist.twist.angular
                odo.append((t, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), (v.x, v.y, v.z), (w.x, w.y, w.z)))

    def col(rows, i, dtype=float):
        return np.array([r[i] for r in rows], dtype=dtype)

    return SensorSeries(
        gps=GpsSeries(
            col(fix, 0, np.int64),
            col(fix, 1),
            col(fix, 2),
            col(fix, 3),
            col(fix, 4, np.int8),
            col(fix, 5),
            col(fix, 6, np.uint8),
        ),
        # imu_link is mounted with its y axis up and the bag has no tf: the IMU's own gravity-aligned orientation is
        # what lets the fusion take the yaw rate about the vertical
        imu=ImuSeries(col(imu, 0, np.int64), col(imu, 1), col(imu, 2), col(imu, 3)),
        odometry=OdometrySeries(col(odo, 0, np.int64), col(odo, 1), col(odo, 2), col(odo, 3), col(odo, 4)),
    )


def rigid_align_2d(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """src (N,2) rotated and shifted to best fit dst (least squares, Kabsch)."""
    ms, md = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - ms).T @ (dst - md))
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = (U @ D @ Vt).T
    return (src - ms) @ R.T + md


@pytest.fixture(scope="module")
def husky():
    if not HUSKY_BAG.is_file():
        pytest.skip(f"Husky bag not found at {HUSKY_BAG}")
    return read_husky(HUSKY_BAG)


def test_husky_fusion_follows_the_odometry_shape(husky):
    series = husky
    frame_t = np.arange(series.odometry.t_ns[0], series.odometry.t_ns[-1], 100_000_000)  # a 10 Hz "camera"
    fused = estimate_poses(series, frame_t, PoseConfig())
    assert fused.source == "gps_imu"
    odo = estimate_poses(series, frame_t, PoseConfig(source="odometry"))
    fused_xy = np.column_stack([fused.x_m, fused.y_m])
    odo_xy = np.column_stack([odo.x_m, odo.y_m])
    aligned = rigid_align_2d(odo_xy, fused_xy)
    rms = float(np.sqrt(np.mean(np.sum((aligned - fused_xy) ** 2, axis=1))))
    length = fused.arc_length_m[-1]
    # wheel odometry of a skid-steer robot drifts in heading and scale (measured: RMS 2.0 % of the 348 m path after
    # alignment, lengths 3 % apart); the shapes still agree to a few % of the path
    assert rms < 0.03 * length, f"RMS {rms:.2f} m over a {length:.0f} m path"
    assert length == pytest.approx(odo.arc_length_m[-1], rel=0.05)
    # the fused track sits on the fixes to about their noise (0.8-1.7 m std reported; measured residual 0.92 m), and
    # the gate drops only the few fixes that jump (measured 39 of 989)
    assert fused.residual_m < 1.2
    assert fused.fixes_rejected < 0.06 * len(series.gps.t_ns)
    # IMU yaw rate about the vertical, taken through the IMU's tilt (its y axis is up), turns like the odometry does
    assert np.unwrap(fused.yaw_rad)[-1] - fused.yaw_rad[0] == pytest.approx(
        np.unwrap(odo.yaw_rad)[-1] - odo.yaw_rad[0], abs=0.35
    )
