"""Ingest of the real recordings in /work/shared/data/real: KITTI raw drive, KITTI odometry snippet, Husky bag."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import REAL_DATA

from drivesim.pipeline.errors import InputError
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.kitti import parse_calib_file
from drivesim.stages.ingest.run import ingest_recording
from drivesim.stages.ingest.trace import validate_trace

REAL = REAL_DATA
KITTI_DATE = REAL / "kitti_raw" / "2011_09_26"
KITTI_DRIVE = KITTI_DATE / "2011_09_26_drive_0001_sync"
KITTI_ODOMETRY = REAL / "kitti_odometry_straight"
HUSKY = REAL / "husky_gps_imu_odom.bag"


def _need(path: Path) -> None:
    if not path.exists():
        pytest.skip(f"real data not available at {path}")


@pytest.fixture(scope="module")
def kitti_raw(tmp_path_factory):
    _need(KITTI_DRIVE)
    out = tmp_path_factory.mktemp("kitti_raw")
    result = ingest_recording(KITTI_DRIVE, IngestConfig(), out)
    return result, validate_trace(out)


def test_kitti_raw_frames_and_times(kitti_raw) -> None:
    result, info = kitti_raw
    assert info.frame_count == 108
    assert info.calibration["source_width_px"] == 1242 and info.calibration["source_height_px"] == 375
    assert (info.width_px, info.height_px) == (640, 193)
    assert 10.4 <= info.duration_s <= 11.1  # 11.04 s from the first to the last image stamp
    assert info.time_base == "unix"
    # 2011-09-26 13:02:25.967790592 (KITTI logs local time; stored as recorded)
    assert info.frame_times_ns()[0] == np.datetime64("2011-09-26T13:02:25.967790592", "ns").astype(np.int64)
    frames = info.frames()
    assert frames.shape == (108, 193, 640, 3)
    # grayscale camera: equal channels, and a real image (not blank)
    assert np.array_equal(frames[50][..., 0], frames[50][..., 2]) and frames[50].std() > 20
    assert result.summary["frame_count"] == 108 and result.summary["sensors"]["camera"]["topic"] == "image_00"


def test_kitti_raw_intrinsics_match_p_rect(kitti_raw) -> None:
    _, info = kitti_raw
    P = parse_calib_file(KITTI_DATE / "calib_cam_to_cam.txt")["P_rect_00"].reshape(3, 4)
    sx = 640 / 1242
    assert info.K[0, 0] == pytest.approx(P[0, 0] * sx)  # 721.5377 px at 1242 wide
    assert info.K[0, 0] == pytest.approx(371.8, abs=0.1)
    assert info.K[0, 2] == pytest.approx((P[0, 2] + 0.5) * sx - 0.5)


def test_kitti_raw_extrinsics(kitti_raw) -> None:
    _, info = kitti_raw
    T = info.T_vehicle_camera
    assert info.calibration["extrinsics_source"] == "kitti_calib"
    assert info.camera_height_m == pytest.approx(1.65, abs=0.03)  # KITTI setup: camera 0 at 1.65 m
    # optical z (viewing direction) is the vehicle's forward axis; optical y (down) is the vehicle's -z
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=0.02)
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=0.02)
    assert 0.9 < T[0, 3] < 1.3  # camera ~1.08 m ahead of the IMU


def test_kitti_raw_gps_imu_speed(kitti_raw) -> None:
    _, info = kitti_raw
    gps = info.load_series("gps")
    assert len(gps["t_ns"]) == 108
    assert gps["lat_deg"].mean() == pytest.approx(49.01, abs=0.01)  # Karlsruhe
    assert gps["lon_deg"].mean() == pytest.approx(8.43, abs=0.01)
    assert np.all(gps["status"] == 2)  # OXTS RTK solution
    assert 0.0 < gps["covariance_m2"][0, 0, 0] < 1.0
    imu = info.load_series("imu")
    assert np.all(np.abs(imu["linear_acceleration_mps2"][:, 2] - 9.8) < 0.5)  # gravity on the up axis
    assert np.all(np.isfinite(imu["orientation_xyzw"]))
    speed = info.load_series("speed")["speed_mps"]
    assert 8.0 < speed.mean() < 14.0  # ~107 m in 11 s


def test_kitti_odometry_snippet_is_accepted_with_given_poses(tmp_path: Path) -> None:
    _need(KITTI_ODOMETRY)
    result = ingest_recording(KITTI_ODOMETRY, IngestConfig(), tmp_path)
    info = validate_trace(tmp_path)
    assert info.frame_count == 51 and info.time_base == "relative"
    assert info.calibration["source_width_px"] == 1226 and info.width_px == 640
    np.testing.assert_array_equal(np.diff(info.frame_times_ns()), 100_000_000)
    poses = info.load_series("poses")
    assert poses["T_world_camera"].shape == (51, 4, 4)
    travelled = np.linalg.norm(poses["T_world_camera"][-1, :3, 3] - poses["T_world_camera"][0, :3, 3])
    assert 40 < travelled < 80  # ~60 m straight street
    assert info.K[0, 0] == pytest.approx(707.0912 * 640 / 1226)
    assert result.summary["sensors"]["poses"]["message_count"] == 51


def test_husky_bag_without_camera_is_refused(tmp_path: Path) -> None:
    _need(HUSKY)
    with pytest.raises(InputError) as err:
        ingest_recording(HUSKY, IngestConfig(), tmp_path)
    assert err.value.one_line() == (
        f"{HUSKY}: no camera topic (sensor_msgs/Image or CompressedImage) in the recording; found: /fix NavSatFix, "
        "/husky_velocity_controller/odom Odometry, /imu/data Imu"
    )


def test_kitti_date_folder_points_to_the_drive(tmp_path: Path) -> None:
    _need(KITTI_DATE)
    with pytest.raises(InputError, match=r"KITTI date folder; pass one drive folder inside it \(e\.g\. .*_sync\)"):
        ingest_recording(KITTI_DATE, IngestConfig(), tmp_path)
