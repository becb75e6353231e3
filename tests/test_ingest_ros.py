"""ROS recordings through ingest: every container format, topic choice, extrinsics, series, ground truth, bad input."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from recordings import (
    DEFAULT_K,
    FORMATS,
    START_NS,
    T_FOOTPRINT_LINK,
    T_LINK_CAMERA,
    Msg,
    camera_info_values,
    drive_messages,
    image_values,
    imu_values,
    navsat_values,
    odometry_values,
    patch_image,
    recording_path,
    tf_static_values,
    write_recording,
)

from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.run import ingest_recording
from drivesim.stages.ingest.trace import validate_trace

LOSSLESS = IngestConfig.model_validate({"image": {"codec": "png"}})  # frames compared pixel for pixel


def _ingest(tmp_path: Path, msgs: list[Msg], fmt: str = "mcap", cfg: IngestConfig | None = None):
    """Write the messages as a recording in a fresh folder under tmp_path and ingest it."""
    run = Path(tempfile.mkdtemp(dir=tmp_path))
    rec = write_recording(recording_path(run, fmt), fmt, msgs)
    out = run / "trace"
    out.mkdir()
    result = ingest_recording(rec, cfg or IngestConfig(), out)
    return result, validate_trace(out)


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_container_format_gives_the_same_trace(tmp_path: Path, fmt: str) -> None:
    n = 6
    msgs = drive_messages(n_frames=n, encoding="bgr8", with_ground_truth=True)
    lossless = {"ground_truth_depth": True, "image": {"codec": "png"}}  # frames compared pixel for pixel below
    result, info = _ingest(tmp_path, msgs, fmt, IngestConfig.model_validate(lossless))
    assert info.sources["format"] == {"rosbag2_sqlite3": "rosbag2", "rosbag2_mcap": "rosbag2"}.get(fmt, fmt)
    assert (info.frame_count, info.width_px, info.height_px) == (n, 64, 40)
    np.testing.assert_array_equal(info.frame_times_ns(), START_NS + 1 + np.arange(n) * 100_000_000)
    assert info.duration_s == pytest.approx(0.5)
    np.testing.assert_array_equal(info.frames()[2], patch_image(64, 40, frame=2))
    np.testing.assert_allclose(info.K, DEFAULT_K)

    # T_vehicle_camera = base_footprint -> base_link -> camera_optical, so the camera is 1.5 m above the ground.
    np.testing.assert_allclose(info.T_vehicle_camera, T_FOOTPRINT_LINK @ T_LINK_CAMERA, atol=1e-9)
    assert info.camera_height_m == pytest.approx(1.5)
    assert info.calibration["extrinsics_source"] == "tf_static"

    gps = info.load_series("gps")
    assert len(gps["t_ns"]) == n and gps["lat_deg"][0] == pytest.approx(49.0) and gps["lon_deg"][0] == 8.4
    np.testing.assert_allclose(gps["covariance_m2"][0], np.diag([4.0, 4.0, 16.0]))
    assert gps["status"][0] == 0 and gps["covariance_type"][0] == 2
    imu = info.load_series("imu")
    assert len(imu["t_ns"]) == n * 5
    np.testing.assert_allclose(imu["angular_velocity_radps"][3], [0, 0, 0.1], atol=1e-12)
    np.testing.assert_allclose(imu["linear_acceleration_mps2"][3], [0.5, 0, 9.81], atol=1e-12)
    speed = info.load_series("speed")
    assert len(speed["t_ns"]) == n * 2 and np.all(speed["speed_mps"] == 10.0)

    depth = np.asarray(info.gt_depth())
    assert depth.shape == (n, 40, 64) and depth.dtype == np.float32
    assert depth[3, 30, 10] == 8.0 and np.isinf(depth[3, 0, 0])
    gt = info.load_series("ground_truth")
    np.testing.assert_allclose(gt["T_world_vehicle"][4][:3, 3], [6.0, 0, 0], atol=1e-9)

    summary = result.summary
    assert summary["frame_count"] == n and summary["width_px"] == 64 and summary["height_px"] == 40
    assert summary["sensors"]["camera"] == {
        "topic": "/camera/image_raw",
        "type": "sensor_msgs/msg/Image",
        "message_count": n,
    }
    assert summary["sensors"]["imu"]["message_count"] == n * 5
    assert "gt_depth" in summary["sensors"]


def test_working_resolution_scales_frames_and_intrinsics(tmp_path: Path) -> None:
    w, h = 200, 120
    K = np.array([[100.0, 0, 99.5], [0, 100.0, 59.5], [0, 0, 1]])
    msgs = drive_messages(n_frames=3, width=w, height=h, K=K, image_fn=lambda i: patch_image(w, h, frame=i))
    _, info = _ingest(tmp_path, msgs, cfg=IngestConfig.model_validate({"image": {"width_px": 100}}))
    assert (info.width_px, info.height_px) == (100, 60)
    np.testing.assert_allclose(info.K, [[50.0, 0, 49.5], [0, 50.0, 29.5], [0, 0, 1]])
    assert info.calibration["source_width_px"] == 200


def test_imu_in_a_rotated_frame_is_expressed_in_the_vehicle_frame(tmp_path: Path) -> None:
    # An IMU mounted yawed by +90 deg: its x axis points along the vehicle's y axis.
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T_link_imu = np.eye(4)
    T_link_imu[:3, :3] = R
    msgs = [m for m in drive_messages(n_frames=3) if m.topic not in ("/imu/data", "/tf_static")]
    edges = [
        ("base_footprint", "base_link", T_FOOTPRINT_LINK),
        ("base_link", "camera_optical", T_LINK_CAMERA),
        ("base_link", "imu_link", T_link_imu),
    ]
    msgs.append(Msg("/tf_static", "tf2_msgs/msg/TFMessage", START_NS, tf_static_values(START_NS, edges)))
    values = imu_values(START_NS + 5, frame_id="imu_link")
    values["linear_acceleration"] = {"x": 1.0, "y": 0.0, "z": 9.81}
    msgs.append(Msg("/imu/data", "sensor_msgs/msg/Imu", START_NS + 5, values))
    _, info = _ingest(tmp_path, sorted(msgs, key=lambda m: m.t_ns))
    imu = info.load_series("imu")
    # acceleration along the IMU's x is along the vehicle's y; the yaw rate about z is unchanged
    np.testing.assert_allclose(imu["linear_acceleration_mps2"][0], [0.0, 1.0, 9.81], atol=1e-9)
    np.testing.assert_allclose(imu["angular_velocity_radps"][0], [0.0, 0.0, 0.1], atol=1e-9)


def test_without_base_footprint_the_height_comes_from_config(tmp_path: Path) -> None:
    msgs = [m for m in drive_messages(n_frames=3) if m.topic != "/tf_static"]
    edges = [("base_link", "camera_optical", T_LINK_CAMERA)]
    msgs.insert(0, Msg("/tf_static", "tf2_msgs/msg/TFMessage", START_NS, tf_static_values(START_NS, edges)))
    _, info = _ingest(tmp_path, msgs)
    np.testing.assert_allclose(info.T_vehicle_camera, T_LINK_CAMERA, atol=1e-9)
    assert info.camera_height_m is None
    cfg = IngestConfig.model_validate({"extrinsics": {"camera_height_m": 1.3}})
    _, info = _ingest(tmp_path, msgs, cfg=cfg)
    assert info.camera_height_m == 1.3


def test_config_extrinsics_override_tf_static(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, :3] = T_LINK_CAMERA[:3, :3]
    T[:3, 3] = [2.0, 0.0, 1.4]
    cfg = IngestConfig.model_validate({"extrinsics": {"T_vehicle_camera": T.tolist(), "camera_height_m": 1.4}})
    _, info = _ingest(tmp_path, drive_messages(n_frames=2), cfg=cfg)
    np.testing.assert_allclose(info.T_vehicle_camera, T)
    assert info.calibration["extrinsics_source"] == "config" and info.camera_height_m == 1.4


def test_odometry_gives_speed_and_poses_without_twist(tmp_path: Path) -> None:
    msgs = drive_messages(n_frames=4, with_gps=False, with_twist=False)
    for i in range(8):
        t = START_NS + i * 50_000_000 + 7
        msgs.append(Msg("/odom", "nav_msgs/msg/Odometry", t, odometry_values(t, 0.4 * i, 8.0)))
    result, info = _ingest(tmp_path, sorted(msgs, key=lambda m: m.t_ns), fmt="ros1")
    odom = info.load_series("odometry")
    np.testing.assert_allclose(odom["position_m"][5], [2.0, 0, 0])
    np.testing.assert_allclose(odom["orientation_xyzw"][5], [0, 0, 0, 1])
    assert np.all(info.load_series("speed")["speed_mps"] == 8.0)
    assert "gps" not in info.series and result.summary["sensors"]["odometry"]["message_count"] == 8


def _two_cameras(with_info_on: str) -> list[Msg]:
    msgs = drive_messages(n_frames=3, with_camera_info=False)
    for m in list(msgs):
        if m.topic == "/camera/image_raw":
            t = m.t_ns
            msgs.append(
                Msg("/a/image_raw", "sensor_msgs/msg/Image", t, image_values(t, patch_image(64, 40, (0, 0, 255))))
            )
            info = camera_info_values(t, 64, 40, DEFAULT_K)
            msgs.append(Msg(f"{with_info_on}/camera_info", "sensor_msgs/msg/CameraInfo", t, info))
    return sorted(msgs, key=lambda m: m.t_ns)


def test_several_cameras_pick_the_one_with_camera_info_and_say_so(tmp_path: Path) -> None:
    result, info = _ingest(tmp_path, _two_cameras("/camera"), cfg=LOSSLESS)
    assert info.sources["camera_topic"] == "/camera/image_raw"
    assert any("with a CameraInfo" in note for note in result.notes)
    result, info = _ingest(tmp_path, _two_cameras("/a"), cfg=LOSSLESS)
    assert info.sources["camera_topic"] == "/a/image_raw"
    assert tuple(np.asarray(info.frames()[0])[20, 32]) == (0, 0, 255)


def test_topic_option_picks_the_camera(tmp_path: Path) -> None:
    cfg = IngestConfig.model_validate({"topics": {"camera": "/a/image_raw"}, "image": {"codec": "png"}})
    result, info = _ingest(tmp_path, _two_cameras("/camera"), cfg=cfg)
    assert info.sources["camera_topic"] == "/a/image_raw"
    assert tuple(np.asarray(info.frames()[0])[20, 32]) == (0, 0, 255)
    assert "--topic camera" in result.notes[0]


def test_unknown_topic_choice_lists_the_topics(tmp_path: Path) -> None:
    cfg = IngestConfig.model_validate({"topics": {"camera": "/nope"}})
    with pytest.raises(ConfigError, match=r"--topic camera=/nope: no such topic .*found: .*/camera/image_raw Image"):
        _ingest(tmp_path, drive_messages(n_frames=2), cfg=cfg)
    cfg = IngestConfig.model_validate({"topics": {"camera": "/gps/fix"}})
    with pytest.raises(ConfigError, match=r"carries NavSatFix, expected Image or CompressedImage"):
        _ingest(tmp_path, drive_messages(n_frames=2), cfg=cfg)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_no_camera_is_refused_naming_what_was_found(tmp_path: Path, fmt: str) -> None:
    msgs = [
        Msg("/fix", "sensor_msgs/msg/NavSatFix", START_NS + i, navsat_values(START_NS + i, 49.0, 8.4)) for i in range(3)
    ]
    with pytest.raises(
        InputError, match=r"no camera topic \(sensor_msgs/Image or CompressedImage\).*found: /fix NavSatFix"
    ):
        _ingest(tmp_path, msgs, fmt)


def test_camera_without_pose_source_is_refused_unless_allowed(tmp_path: Path) -> None:
    msgs = drive_messages(n_frames=2, with_gps=False)
    with pytest.raises(InputError, match=r"no pose source: no NavSatFix, Odometry or /tf topic"):
        _ingest(tmp_path, msgs)
    _, info = _ingest(tmp_path, msgs, cfg=IngestConfig(require_pose_source=False))
    assert info.frame_count == 2


def test_camera_without_camera_info_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"no CameraInfo for camera /camera/image_raw"):
        _ingest(tmp_path, drive_messages(n_frames=2, with_camera_info=False))


@pytest.mark.parametrize("fmt", ["ros1", "mcap", "rosbag2_sqlite3"])
def test_non_monotonic_camera_stamps_are_refused(tmp_path: Path, fmt: str) -> None:
    stamps = [0, 100_000_000, 200_000_000, 150_000_000, 400_000_000]
    msgs = drive_messages(n_frames=5, stamps_ns=stamps)
    with pytest.raises(InputError, match=r"stamps not strictly increasing at frame 3"):
        _ingest(tmp_path, msgs, fmt)


def test_zero_header_stamps_fall_back_to_log_time(tmp_path: Path) -> None:
    msgs = drive_messages(n_frames=3)
    for m in msgs:
        if m.topic == "/camera/image_raw":
            m.values["header"]["stamp"] = {"sec": 0, "nanosec": 0}
    _, info = _ingest(tmp_path, msgs)
    np.testing.assert_array_equal(info.frame_times_ns(), START_NS + 1 + np.arange(3) * 100_000_000)


def _truncate(path: Path, fraction: float) -> None:
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(int(size * fraction))


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("fraction", [0.5, 0.97])
def test_truncated_recordings_are_one_clear_error(tmp_path: Path, fmt: str, fraction: float) -> None:
    rec = write_recording(recording_path(tmp_path, fmt), fmt, drive_messages(n_frames=8))
    data_file = rec if rec.is_file() else next(p for p in rec.iterdir() if p.suffix in (".db3", ".mcap"))
    _truncate(data_file, fraction)
    out = tmp_path / "trace"
    out.mkdir()
    with pytest.raises(InputError) as err:
        ingest_recording(rec, IngestConfig(), out)
    line = err.value.one_line()
    assert "\n" not in line and str(rec) in line
    assert "truncated" in line or "unreadable" in line or "malformed" in line


def test_garbage_and_missing_paths(tmp_path: Path) -> None:
    junk = tmp_path / "junk.bag"
    junk.write_bytes(os.urandom(2000))
    with pytest.raises(InputError, match=r"not a recording drivesim can read"):
        ingest_recording(junk, IngestConfig(), tmp_path)
    with pytest.raises(InputError, match=r"no such file or folder"):
        ingest_recording(tmp_path / "absent.mcap", IngestConfig(), tmp_path)
    (tmp_path / "empty").mkdir()
    accepted = (
        r"folder is not a recording drivesim can read; .*rosbag2 folder.*folder of PNG/JPEG images only \(with --fps\)"
    )
    with pytest.raises(InputError, match=accepted):
        ingest_recording(tmp_path / "empty", IngestConfig(), tmp_path)


def _tf_drive(moving_frame: str = "base_link") -> list[Msg]:
    """A drive without GPS or odometry whose /tf moves `moving_frame` along x at 5 m/s turning at 0.2 rad/s."""
    msgs = drive_messages(n_frames=5, with_gps=False, with_twist=False)
    for i in range(25):
        t = START_NS + i * 20_000_000 + 9
        yaw = 0.2 * i * 0.02
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[0, 3] = 5.0 * i * 0.02
        msgs.append(Msg("/tf", "tf2_msgs/msg/TFMessage", t, tf_static_values(t, [("odom", moving_frame, T)])))
    return sorted(msgs, key=lambda m: m.t_ns)


def test_dynamic_tf_is_a_pose_source(tmp_path: Path) -> None:
    result, info = _ingest(tmp_path, _tf_drive(), fmt="ros1")
    odom = info.load_series("odometry")
    assert len(odom["t_ns"]) == 25
    # /tf moves base_link; the trace's vehicle frame is base_footprint, 0.4 m below it
    np.testing.assert_allclose(odom["position_m"][10], [1.0, 0.0, -0.4], atol=1e-9)
    # velocities are in the vehicle frame: 5 m/s along world x seen from a vehicle yawed by yaw
    yaw = 0.2 * np.arange(25) * 0.02
    v = odom["linear_velocity_mps"]
    np.testing.assert_allclose(v[:-1, 0], 5.0 * np.cos(yaw[:-1]), atol=0.01)
    np.testing.assert_allclose(v[:-1, 1], -5.0 * np.sin(yaw[:-1]), atol=0.01)
    np.testing.assert_allclose(odom["angular_velocity_radps"][:, 2], 0.2, atol=1e-6)
    assert result.summary["sensors"]["tf"]["topic"] == "/tf"


def test_tf_that_never_moves_the_vehicle_is_no_pose_source(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"/tf never moves base_footprint or base_link"):
        _ingest(tmp_path, _tf_drive(moving_frame="some_other_frame"))


def test_camera_size_change_midway_is_refused(tmp_path: Path) -> None:
    msgs = drive_messages(n_frames=4)
    camera_msgs = [m for m in msgs if m.topic == "/camera/image_raw"]
    camera_msgs[2].values.update(image_values(camera_msgs[2].t_ns, patch_image(32, 20)))
    with pytest.raises(InputError, match=r"camera image size changed from 64x40 to 32x20"):
        _ingest(tmp_path, msgs)


def test_pointcloud_scans_are_stored_in_the_vehicle_frame(tmp_path: Path) -> None:
    from recordings import pointcloud_values

    T_link_lidar = np.eye(4)
    T_link_lidar[:3, 3] = [0.5, 0.0, 1.8]  # lidar on the roof, axes as the vehicle's
    msgs = [m for m in drive_messages(n_frames=3) if m.topic != "/tf_static"]
    edges = [
        ("base_footprint", "base_link", T_FOOTPRINT_LINK),
        ("base_link", "camera_optical", T_LINK_CAMERA),
        ("base_link", "lidar", T_link_lidar),
    ]
    msgs.append(Msg("/tf_static", "tf2_msgs/msg/TFMessage", START_NS, tf_static_values(START_NS, edges)))
    for i in range(3):
        t = START_NS + i * 100_000_000 + 6
        pts = np.array([[10.0, 1.0, -2.2, 5.0], [np.nan, 0, 0, 1.0], [3.0 + i, -1.0, 0.0, 7.0]], np.float32)
        msgs.append(Msg("/velodyne_points", "sensor_msgs/msg/PointCloud2", t, pointcloud_values(t, pts)))
    result, info = _ingest(tmp_path, sorted(msgs, key=lambda m: m.t_ns), fmt="ros1")
    scans = info.load_series("lidar_scans")
    np.testing.assert_array_equal(scans["count"], [2, 2, 2])  # the NaN point is dropped
    np.testing.assert_array_equal(scans["start"], [0, 2, 4])
    points = np.asarray(info.lidar_points())
    # lidar (10, 1, -2.2) -> base_link (10.5, 1, -0.4) -> base_footprint (10.5, 1, 0): a point on the ground
    np.testing.assert_allclose(points[0], [10.5, 1.0, 0.0, 5.0], atol=1e-5)
    np.testing.assert_allclose(points[5], [5.5, -1.0, 2.2, 7.0], atol=1e-5)
    assert result.summary["sensors"]["lidar"]["message_count"] == 3
