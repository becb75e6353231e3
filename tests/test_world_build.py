"""`drivesim build-world`: trace + preprocessed in, the world the simulator loads out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_preprocess_stage_fakes import (
    FRAME_COUNT,
    HEIGHT_PX,
    RADIUS_M,
    SPEED_MPS,
    WIDTH_PX,
    install_fake_poses,
    make_trace,
)

from drivesim.chain.registry import CHAIN
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import MissingArtifactError
from drivesim.pipeline.status import status_report
from drivesim.pipeline.workspace import Workspace
from drivesim.sim.image_stack import ImageStack
from drivesim.sim.world import World
from drivesim.stages.preprocess import stage as preprocess_stage
from drivesim.stages.preprocess.config import PreprocessConfig
from drivesim.stages.world.build import resize_depth, sim_resolution
from drivesim.stages.world.config import WorldConfig
from drivesim.stages.world.stage import run_build_world


@pytest.fixture
def ws(tmp_path: Path, monkeypatch) -> Workspace:
    workspace = Workspace(tmp_path / "ws")
    make_trace(workspace)
    install_fake_poses(monkeypatch)
    preprocess_stage.run_preprocess(workspace, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
    return workspace


def test_build_world_loads_in_the_simulator(ws: Workspace) -> None:
    cfg = load_config(WorldConfig, preset="world", overrides=["sim_width_px=48", "pointcloud.frame_step=2"])
    result = run_build_world(ws, cfg)
    world = World.load(result.path)
    assert (world.width_px, world.height_px) == (48, 30)
    # read one frame at a time from their image stacks (JPEG frames, lossless float16 depth), never loaded whole
    assert world.frames.shape == (FRAME_COUNT, 30, 48, 3) and isinstance(world.frames, ImageStack)
    assert world.depth_m.shape == (FRAME_COUNT, 30, 48) and isinstance(world.depth_m, ImageStack)
    assert world.frames.codec == "jpeg" and world.depth_m.dtype == np.float16
    # frames are the trace's, in order (the fake trace stores 10 * frame id in the red channel; JPEG's rounding,
    # clipped at 0 for frame 0, moves a frame's mean by under 2 levels)
    np.testing.assert_allclose(world.frames[:, :, :, 0].mean(axis=(1, 2)), np.arange(FRAME_COUNT) * 10, atol=2.0)
    assert world.path_length_m == pytest.approx(SPEED_MPS * (FRAME_COUNT - 1) * 0.1, abs=1e-6)
    assert world.lane_width_m == 3.5 and world.road_width_m == 7.0
    assert world.info["far_depth_m"] == 80.0 and np.asarray(world.depth_m).max() == pytest.approx(80.0)

    # K at the sim resolution still maps a world point to the same place in the image (half the pixels)
    trace_K = np.asarray(json.loads((ws.artifact_dir("trace") / "calibration.json").read_text())["K"])
    point = np.array([0.7, 0.4, 9.0])
    u_src, v_src = (trace_K @ point)[:2] / point[2]
    u_sim, v_sim = (world.K @ point)[:2] / point[2]
    assert (u_sim + 0.5) == pytest.approx((u_src + 0.5) * 48 / WIDTH_PX)
    assert (v_sim + 0.5) == pytest.approx((v_src + 0.5) * 30 / HEIGHT_PX)

    # the ground seen at the bottom-centre of the sim image lies on z = 0 with the sim K and the stored pose
    i, u, v = 5, 24, 29
    ray = np.linalg.inv(world.K) @ np.array([u, v, 1.0])
    ground = world.path["T_world_camera"][i] @ np.append(ray * world.depth_m[i, v, u], 1.0)
    assert ground[2] == pytest.approx(0.0, abs=0.06)  # min-pooling takes the block's nearest ground (lowest row)

    # the association finds each recorded frame at its own pose
    for j in (0, 6, FRAME_COUNT - 1):
        index, q_lat, q_long, q_rot = world.closest_frame(*world.pose(j))
        assert index == j and abs(q_lat) < 1e-9 and abs(q_long) < 1e-9 and abs(q_rot) < 1e-9


def test_world_summary_in_status_and_people_files(ws: Workspace) -> None:
    result = run_build_world(ws, WorldConfig())
    stages = {row["stage"]: row for row in status_report(ws, CHAIN)["stages"]}
    world = stages["build-world"]
    assert world["state"] == "fresh"
    summary = world["summary"]
    assert summary["frame_count"] == FRAME_COUNT
    assert summary["path_length_m"] == pytest.approx(11.0, abs=1e-3)
    assert summary["curvature_min_1pm"] == pytest.approx(1.0 / RADIUS_M)
    assert summary["curvature_max_1pm"] == pytest.approx(1.0 / RADIUS_M)
    assert (summary["sim_width_px"], summary["sim_height_px"]) == (320, 200)
    assert (result.path / "birdseye.png").read_bytes()[:4] == b"\x89PNG"

    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(result.path / "pointcloud.ply"))
    points = np.asarray(cloud.points)
    assert len(points) == summary["pointcloud_points"] > 100
    # plane depth: every fused point is on the ground, within 30 m of the path, and coloured
    assert np.abs(points[:, 2]).max() < 1e-3  # float16 depth: under 0.05 % of the range
    assert np.hypot(points[:, 0], points[:, 1]).max() < 30.0 + 11.0 + 2.0
    assert np.asarray(cloud.colors).shape == points.shape


def test_fresh_force_and_upstream_change(ws: Workspace) -> None:
    cfg = WorldConfig()
    assert not run_build_world(ws, cfg).skipped
    assert run_build_world(ws, cfg).skipped
    assert not run_build_world(ws, cfg, force=True).skipped
    # preprocessing again with another config changes the input hash: the world is stale and rebuilt
    preprocess_stage.run_preprocess(ws, load_config(PreprocessConfig, overrides=["frames.step=2"]))
    stages = {row["stage"]: row for row in status_report(ws, CHAIN)["stages"]}
    assert stages["build-world"]["state"] == "stale"
    rebuilt = run_build_world(ws, cfg)
    assert not rebuilt.skipped and rebuilt.summary.frame_count == FRAME_COUNT // 2


def test_missing_preprocessed_says_run_preprocess(tmp_path: Path) -> None:
    workspace = Workspace(tmp_path / "ws")
    make_trace(workspace)
    with pytest.raises(MissingArtifactError, match=r"run `drivesim preprocess` first"):
        run_build_world(workspace, WorldConfig())
    assert workspace.read_manifest("world") is None


def test_sim_resolution_keeps_the_aspect() -> None:
    assert sim_resolution(960, 600, 320) == (320, 200)
    assert sim_resolution(1242, 375, 320) == (320, 97)


def test_min_pooling_keeps_a_thin_near_pole_that_nearest_loses() -> None:
    depth = np.full((60, 96), 40.0, np.float32)
    depth[:, 48] = 3.0  # a one-pixel-wide pole at 3 m, between the columns nearest samples
    pooled = resize_depth(depth, 32, 20, "min")
    nearest = resize_depth(depth, 32, 20, "nearest")
    assert pooled.shape == nearest.shape == (20, 32)
    assert (pooled == 3.0).all(axis=0).sum() == 1 and pooled.min() == 3.0
    assert nearest.min() == 40.0  # the pole falls between the sampled columns
    # stacks of frames and NaN (no estimate) are handled: NaN never wins the minimum
    stack = np.stack([depth, np.full_like(depth, np.nan)])
    out = resize_depth(stack, 32, 20, "min")
    assert out.shape == (2, 20, 32) and out[0].min() == 3.0 and np.isinf(out[1]).all()
    # upscaling (a sim image wider than the trace) repeats source pixels
    up = resize_depth(np.array([[1.0, 2.0], [3.0, 4.0]], np.float32), 4, 4, "min")
    np.testing.assert_array_equal(up, [[1, 1, 2, 2], [1, 1, 2, 2], [3, 3, 4, 4], [3, 3, 4, 4]])
