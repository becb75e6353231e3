"""`drivesim synth` end to end: the MCAP recording reads back with standard ROS2 decoding and agrees with the
world; the CLI writes the recording and previews, and leaves nothing behind when it fails."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2.reader import read_ros2_messages
from PIL import Image
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from drivesim.stages.synth.config import SynthConfig
from drivesim.stages.synth.drive import Trajectory
from drivesim.stages.synth.road import build_centreline
from drivesim.stages.synth.synthesize import preview_paths, sidecar_path, synthesize
from drivesim.stages.synth.world import SynthWorld

W, H = 320, 200
DURATION_S = 1.5


@pytest.fixture(scope="module")
def small_cfg() -> SynthConfig:
    return SynthConfig.model_validate(
        {"seed": 4, "camera": {"width_px": W, "height_px": H}, "drive": {"duration_s": DURATION_S}}
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory, small_cfg) -> tuple[Path, list]:
    out = tmp_path_factory.mktemp("synth") / "drive.mcap"
    result = synthesize(small_cfg, out, preview=True)
    assert result.frame_count == 15
    messages = list(read_ros2_messages(str(out)))
    return out, messages


def by_topic(messages: list, topic: str) -> list:
    return [m for m in messages if m.channel.topic == topic]


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_topics_types_and_counts(recording):
    _, messages = recording
    counts = {}
    types = {}
    for m in messages:
        counts[m.channel.topic] = counts.get(m.channel.topic, 0) + 1
        types[m.channel.topic] = m.schema.name
    assert counts == {
        "/tf_static": 1,
        "/camera/image_raw": 15,
        "/camera/camera_info": 15,
        "/gps/fix": 15,
        "/imu/data": 150,
        "/vehicle/twist": 75,
        "/ground_truth/depth": 15,
        "/ground_truth/pose": 15,
    }
    assert types["/camera/image_raw"] == "sensor_msgs/msg/Image"
    assert types["/gps/fix"] == "sensor_msgs/msg/NavSatFix"
    assert types["/imu/data"] == "sensor_msgs/msg/Imu"
    assert types["/vehicle/twist"] == "geometry_msgs/msg/TwistStamped"
    assert types["/tf_static"] == "tf2_msgs/msg/TFMessage"
    assert types["/ground_truth/pose"] == "geometry_msgs/msg/PoseStamped"
    assert all(m.channel.message_encoding == "cdr" for m in messages)


def test_stamps_are_real_monotonic_and_equal_to_log_time(recording, small_cfg):
    _, messages = recording
    log = np.array([m.log_time_ns for m in messages])
    assert np.all(np.diff(log) >= 0)
    assert log[0] == int(small_cfg.drive.start_epoch_s * 1e9)  # 2026-01-01, non-zero
    for m in messages:
        if m.channel.topic != "/tf_static":
            assert stamp_ns(m.ros_msg) == m.log_time_ns
    for topic, rate in (("/gps/fix", 10.0), ("/imu/data", 100.0), ("/camera/image_raw", 10.0)):
        t = np.array([stamp_ns(m.ros_msg) for m in by_topic(messages, topic)])
        assert np.allclose(np.diff(t), 1e9 / rate, atol=1)
    # depth, pose and camera_info share each image's stamp
    cam = [stamp_ns(m.ros_msg) for m in by_topic(messages, "/camera/image_raw")]
    for topic in ("/ground_truth/depth", "/ground_truth/pose", "/camera/camera_info"):
        assert [stamp_ns(m.ros_msg) for m in by_topic(messages, topic)] == cam


def test_images_camera_info_and_tf_static(recording, small_cfg):
    _, messages = recording
    img = by_topic(messages, "/camera/image_raw")[0].ros_msg
    assert (img.encoding, img.width, img.height, img.step) == ("rgb8", W, H, 3 * W)
    assert len(img.data) == W * H * 3
    depth = by_topic(messages, "/ground_truth/depth")[0].ros_msg
    assert (depth.encoding, depth.step, depth.is_bigendian) == ("32FC1", 4 * W, 0)
    info = by_topic(messages, "/camera/camera_info")[0].ros_msg
    assert info.distortion_model == "plumb_bob" and list(info.d) == [0.0] * 5
    K = np.array(info.k).reshape(3, 3)
    assert K[0, 0] == pytest.approx(0.5 * W / np.tan(np.deg2rad(40.0)))
    assert (K[0, 2], K[1, 2]) == (W / 2, H / 2)
    tf = by_topic(messages, "/tf_static")[0].ros_msg.transforms
    pairs = {(t.header.frame_id, t.child_frame_id): t.transform for t in tf}
    assert set(pairs) == {("base_footprint", "base_link"), ("base_link", "camera_optical")}
    assert pairs[("base_footprint", "base_link")].translation.z == 0.0
    cam_tf = pairs[("base_link", "camera_optical")]
    assert cam_tf.translation.z == pytest.approx(small_cfg.camera.height_m)
    q = cam_tf.rotation
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    # the optical axis (z) points forward and 3 degrees down; image x points right (-y of the vehicle)
    assert R[:, 2] == pytest.approx([np.cos(np.deg2rad(3)), 0.0, -np.sin(np.deg2rad(3))], abs=1e-9)
    assert R[:, 0] == pytest.approx([0.0, -1.0, 0.0], abs=1e-9)


def test_gps_imu_and_twist_messages(recording, small_cfg):
    _, messages = recording
    fix = by_topic(messages, "/gps/fix")[0].ros_msg
    assert fix.latitude == pytest.approx(49.0, abs=1e-3) and fix.longitude == pytest.approx(8.4, abs=1e-3)
    assert fix.position_covariance_type == 2 and fix.status.status == 0
    assert fix.position_covariance[0] == pytest.approx(0.7**2 + 0.15**2)
    imu = by_topic(messages, "/imu/data")[0].ros_msg
    assert imu.header.frame_id == "base_link" and imu.orientation_covariance[0] == -1.0
    assert imu.linear_acceleration.z == pytest.approx(9.81, abs=0.5)
    speeds = [m.ros_msg.twist.linear.x for m in by_topic(messages, "/vehicle/twist")]
    assert 8.0 < np.mean(speeds) < 12.0


def test_ground_truth_pose_and_depth_agree_with_the_world(recording, small_cfg):
    out, messages = recording
    sidecar = json.loads(sidecar_path(out).read_text())
    assert sidecar["seed"] == small_cfg.seed
    world = SynthWorld.from_sidecar(sidecar_path(out))
    traj = Trajectory(world.path, SynthConfig.model_validate(sidecar["config"]).drive)
    poses = by_topic(messages, "/ground_truth/pose")
    p = poses[5].ros_msg.pose
    T = traj.vehicle_pose(0.5)
    assert (p.position.x, p.position.y, p.position.z) == pytest.approx(tuple(T[:3, 3]), abs=1e-6)
    yaw = Rotation.from_quat([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]).as_euler("xyz")[2]
    assert yaw == pytest.approx(np.arctan2(T[1, 0], T[0, 0]), abs=1e-9)
    # the recorded frame and depth are what the world renders from that pose
    msg = by_topic(messages, "/ground_truth/depth")[5].ros_msg
    depth = np.frombuffer(bytes(msg.data), "<f4").reshape(H, W)
    img = by_topic(messages, "/camera/image_raw")[5].ros_msg
    rgb = np.frombuffer(bytes(img.data), np.uint8).reshape(H, W, 3)
    rgb_w, depth_w = world.render(T @ world.camera.T_vehicle_camera, world.camera.K, W, H)
    assert np.array_equal(depth, depth_w)
    assert np.array_equal(rgb, rgb_w)
    assert np.isinf(depth).any() and np.isfinite(depth[-1]).all()


def test_previews_are_pictures(recording):
    out, _ = recording
    sheet, map_png = preview_paths(out)
    for path, min_w in ((sheet, 800), (map_png, 600)):
        with Image.open(path) as im:
            assert im.format == "PNG" and im.width >= min_w
            # not a blank canvas
            assert np.asarray(im.convert("L")).std() > 10


def test_interrupted_run_leaves_nothing(tmp_path, small_cfg):
    out = tmp_path / "cut.mcap"

    def stop(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        synthesize(small_cfg, out, preview=True, on_frame=stop)
    assert list(tmp_path.iterdir()) == []


def test_cli_writes_the_default_output_and_previews(tmp_path):
    from drivesim.cli.main import app

    ws = tmp_path / "ws"
    args = ["--workspace", str(ws), "synth", "--seed", "3", "--duration-s", "0.3", "--rate-hz", "10", "--preview"]
    args += ["--set", "camera.width_px=160", "--set", "camera.height_px=100"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    out = ws / "recordings" / "synth-seed3.mcap"
    assert out.is_file() and sidecar_path(out).is_file()
    assert all(p.is_file() for p in preview_paths(out))
    assert sum(1 for _ in read_ros2_messages(str(out), topics=["/camera/image_raw"])) == 3
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(
        [out.name, sidecar_path(out).name, *(p.name for p in preview_paths(out))]
    )


def test_cli_bad_output_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "drive.txt"
    proc = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "synth", "--output", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and ".mcap" in proc.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_default_resolution_drive(tmp_path):
    """One second at the default 960x600: frames and depth at full size, road depth at the bottom as geometry says."""
    cfg = SynthConfig.model_validate({"drive": {"duration_s": 1.0}})
    out = tmp_path / "full.mcap"
    result = synthesize(cfg, out)
    assert result.frame_count == 10
    msgs = list(read_ros2_messages(str(out), topics=["/ground_truth/depth", "/camera/image_raw"]))
    depth = np.frombuffer(bytes(msgs[-1].ros_msg.data), "<f4").reshape(600, 960)
    K = SynthWorld.from_sidecar(sidecar_path(out)).camera.K
    below = np.arctan((599 - K[1, 2]) / K[1, 1])
    expected = 1.6 * np.cos(below) / np.sin(below + np.deg2rad(3.0))
    assert depth[599, 480] == pytest.approx(expected, rel=0.01)
    img = msgs[0].ros_msg
    assert (img.width, img.height, len(img.data)) == (960, 600, 960 * 600 * 3)


def test_road_grows_with_the_drive_and_too_long_a_drive_is_a_config_error():
    from drivesim.pipeline.errors import ConfigError
    from drivesim.stages.synth.synthesize import resolve_config

    short = SynthConfig()
    assert resolve_config(short).world.road.length_m == short.world.road.length_m
    long = resolve_config(SynthConfig.model_validate({"drive": {"duration_s": 120.0}}))
    for seed in range(5):
        lane = build_centreline(long.world.road, np.random.default_rng(seed)).offset(-1.75)
        Trajectory(lane, long.drive).state(120.0)  # the whole drive fits on the lane (raises otherwise)
    with pytest.raises(ConfigError, match="duration_s"):
        resolve_config(SynthConfig.model_validate({"drive": {"duration_s": 3000.0}}))


def test_same_seed_same_bytes(tmp_path):
    cfg = SynthConfig.model_validate(
        {"seed": 9, "camera": {"width_px": 96, "height_px": 64}, "drive": {"duration_s": 0.3}}
    )
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    synthesize(cfg, a)
    synthesize(cfg, b)
    assert a.read_bytes() == b.read_bytes()
