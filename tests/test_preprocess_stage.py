"""`drivesim preprocess` orchestration: trace in, poses + streamed depth + preview out, fresh/force, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_preprocess_stage_fakes import (
    CAMERA_HEIGHT_M,
    FRAME_COUNT,
    HEIGHT_PX,
    RADIUS_M,
    SPEED_MPS,
    T_VEHICLE_CAMERA,
    WIDTH_PX,
    K,
    add_lidar_wall,
    install_fake_poses,
    make_trace,
)

from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError, InputError, MissingArtifactError, StaleArtifactError
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess import run as run_module
from drivesim.stages.preprocess import stage
from drivesim.stages.preprocess.artifact import load_preprocessed
from drivesim.stages.preprocess.config import PreprocessConfig


@pytest.fixture
def ws(tmp_path: Path) -> Workspace:
    workspace = Workspace(tmp_path / "ws")
    make_trace(workspace)
    return workspace


def test_preprocess_writes_poses_depth_and_summary(ws: Workspace, monkeypatch) -> None:
    calls = install_fake_poses(monkeypatch)
    result = stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
    assert not result.skipped
    pre = load_preprocessed(result.path)
    assert pre.frame_count == FRAME_COUNT
    assert calls[0]["frames_shape"] == (FRAME_COUNT, HEIGHT_PX, WIDTH_PX, 3)
    # the arc: 10 m/s for 1.1 s
    duration_s = (FRAME_COUNT - 1) * 0.1
    assert result.summary.path_length_m == pytest.approx(SPEED_MPS * duration_s, abs=1e-3)
    assert result.summary.pose_source == "fake_gps_imu"
    assert result.summary.residual_m == pytest.approx(0.2)
    np.testing.assert_allclose(pre.poses["curvature_1pm"], 1.0 / RADIUS_M)
    np.testing.assert_array_equal(pre.poses["frame_index"], np.arange(FRAME_COUNT))
    np.testing.assert_allclose(pre.poses["T_world_camera"], pre.poses["T_world_vehicle"] @ T_VEHICLE_CAMERA)

    # plane depth: the bottom-centre pixel sees the ground; its world point must lie at z = 0
    assert pre.depth_m.shape == (FRAME_COUNT, HEIGHT_PX, WIDTH_PX) and pre.depth_m.dtype == np.float16
    K = np.asarray(json.loads((ws.artifact_dir("trace") / "calibration.json").read_text())["K"])
    u, v = WIDTH_PX // 2, HEIGHT_PX - 1
    for i in (0, FRAME_COUNT - 1):
        depth = float(pre.depth_m[i, v, u])
        point_camera = np.linalg.inv(K) @ np.array([u, v, 1.0]) * depth
        point_world = pre.poses["T_world_camera"][i] @ np.append(point_camera, 1.0)
        assert point_world[2] == pytest.approx(0.0, abs=2e-3)  # float16 depth: steps of 2 mm at 2-4 m
        assert 1.0 < depth < 10.0
    assert pre.origin["pose_source"] == "fake_gps_imu" and pre.origin["origin_lat_deg"] == 49.0
    assert result.summary.depth_method == "plane"
    assert 0.1 < result.summary.depth_far_fraction < 0.9  # the sky half of the image is far
    assert result.summary.depth_median_m > CAMERA_HEIGHT_M

    preview = result.path / "depth_preview.png"
    assert preview.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    manifest = ws.read_manifest("preprocessed")
    assert manifest["inputs"]["trace"]["hash"] == ws.read_manifest("trace")["artifact_hash"]
    assert set(manifest["outputs"]) == {"poses.npz", "depth.imgs", "origin.json", "depth_preview.png"}


def test_second_run_is_fresh_and_force_redoes(ws: Workspace, monkeypatch) -> None:
    calls = install_fake_poses(monkeypatch)
    cfg = PreprocessConfig()
    first = stage.run_preprocess(ws, cfg)
    created = ws.read_manifest("preprocessed")["created_utc"]
    again = stage.run_preprocess(ws, cfg)
    assert again.skipped and len(calls) == 1
    assert again.summary == first.summary
    forced = stage.run_preprocess(ws, cfg, force=True)
    assert not forced.skipped and len(calls) == 2
    # a different config is not fresh
    other = stage.run_preprocess(ws, load_config(PreprocessConfig, overrides=["preview.frame_count=2"]))
    assert not other.skipped and len(calls) == 3
    assert ws.read_manifest("preprocessed")["created_utc"] >= created


def test_frame_selection_keeps_trace_indices(ws: Workspace, monkeypatch) -> None:
    calls = install_fake_poses(monkeypatch)
    cfg = load_config(PreprocessConfig, overrides=["frames.start=1", "frames.step=3"])
    result = stage.run_preprocess(ws, cfg)
    pre = load_preprocessed(result.path)
    np.testing.assert_array_equal(pre.poses["frame_index"], [1, 4, 7, 10])
    trace_times = np.load(ws.artifact_dir("trace") / "frame_times_ns.npy")
    np.testing.assert_array_equal(calls[0]["frame_times_ns"], trace_times[[1, 4, 7, 10]])
    assert pre.depth_m.shape[0] == 4


def test_selecting_fewer_than_two_frames_is_an_input_error(ws: Workspace, monkeypatch) -> None:
    install_fake_poses(monkeypatch)
    cfg = load_config(PreprocessConfig, overrides=["frames.start=11"])
    with pytest.raises(InputError, match="select 1 of the trace's 12 frames"):
        stage.run_preprocess(ws, cfg)
    assert ws.read_manifest("preprocessed") is None


def test_unknown_config_key_names_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match="unknown config key 'depth.methd'.*method"):
        load_config(PreprocessConfig, preset="preprocess", overrides=["depth.methd=mvs"])


def test_no_trace_says_run_ingest(tmp_path: Path) -> None:
    with pytest.raises(MissingArtifactError, match=r"run `drivesim ingest PATH` first"):
        stage.run_preprocess(Workspace(tmp_path / "empty"), PreprocessConfig())


def test_a_failure_mid_depth_leaves_no_artifact(ws: Workspace, monkeypatch) -> None:
    install_fake_poses(monkeypatch)
    stage.run_preprocess(ws, PreprocessConfig())
    before = ws.read_manifest("preprocessed")

    def broken_depth(*args, **kwargs):
        args[6][0] = 1.0  # some depth was written into the memmap before the failure
        raise RuntimeError("disk full")

    monkeypatch.setattr(run_module.depth_mod, "estimate_depth", broken_depth)
    with pytest.raises(RuntimeError, match="disk full"):
        stage.run_preprocess(ws, PreprocessConfig(), force=True)
    assert ws.read_manifest("preprocessed") == before
    assert not [p for p in ws.root.iterdir() if p.name.startswith(".tmp-")]


def test_truncated_trace_is_one_clear_error(ws: Workspace, monkeypatch) -> None:
    install_fake_poses(monkeypatch)
    (ws.artifact_dir("trace") / "frame_times_ns.npy").unlink()
    # A file of the trace removed after ingest makes the trace stale: refused before preprocess reads it.
    with pytest.raises(StaleArtifactError, match=r"frame_times_ns\.npy.*drivesim ingest"):
        stage.run_preprocess(ws, PreprocessConfig())
    assert ws.read_manifest("preprocessed") is None


@pytest.mark.parametrize(
    ("command", "hint"), [("preprocess", "drivesim ingest PATH"), ("build-world", "drivesim ingest")]
)
def test_cli_without_trace_is_one_line_and_exit_2(tmp_path: Path, command: str, hint: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(tmp_path / "ws"), command],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "no trace artifact" in lines[0] and hint in lines[0]
    assert not (tmp_path / "ws" / "preprocessed").exists() and not (tmp_path / "ws" / "world").exists()


def test_cli_bad_override_is_one_line_and_exit_2(tmp_path: Path) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "drivesim.cli.main",
            "--workspace",
            str(tmp_path),
            "preprocess",
            "--set",
            "depth.method=x",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "depth.method" in lines[0]


def test_lidar_scans_are_motion_compensated_to_the_frame_time(ws: Workspace, monkeypatch) -> None:
    # scans 50 ms after frames 0..9 of a car at 10 m/s: uncompensated, the wall would be ~0.5 m too near
    wall_x_m = 25.0
    add_lidar_wall(ws.artifact_dir("trace"), scan_offset_s=0.05, scan_count=10, wall_x_m=wall_x_m)
    install_fake_poses(monkeypatch)
    cfg = load_config(PreprocessConfig, overrides=["depth.method=lidar", "depth.lidar.fallback=plane"])
    pre = load_preprocessed(stage.run_preprocess(ws, cfg).path)
    u, v = WIDTH_PX // 2, HEIGHT_PX // 2 - 6  # a pixel just above the horizon: it sees the wall, not the ground
    ray_camera = np.linalg.inv(K) @ np.array([u, v, 1.0])
    for i in (2, 6, 10):
        T = pre.poses["T_world_camera"][i]
        ray_world = T[:3, :3] @ ray_camera
        expected_m = (wall_x_m - T[0, 3]) / ray_world[0]  # optical depth where the ray meets x = wall_x_m
        assert float(pre.depth_m[i, v, u]) == pytest.approx(expected_m, abs=0.15), i
    # frame 11 is 150 ms from the last scan: no scan is used and the plane fallback (far above the horizon) fills it
    assert float(pre.depth_m[11, v, u]) == pytest.approx(80.0)


def test_lidar_depth_without_point_cloud_fails_before_pose_fusion(ws: Workspace, monkeypatch) -> None:
    calls = install_fake_poses(monkeypatch)
    with pytest.raises(InputError, match="no point cloud"):
        stage.run_preprocess(ws, load_config(PreprocessConfig, overrides=["depth.method=lidar"]))
    assert calls == [] and ws.read_manifest("preprocessed") is None
