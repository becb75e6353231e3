"""The synthetic world: layout sanity, ground-truth depth against geometry, determinism, rebuild from a sidecar."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivesim.sim.geometry import intrinsics_from_hfov, pose_2d
from drivesim.stages.synth.config import SynthConfig
from drivesim.stages.synth.scenery import sidewalk_outer_m
from drivesim.stages.synth.world import SEMANTIC_IDS, SynthWorld

W, H = 320, 200


@pytest.fixture(scope="module")
def small_cfg() -> SynthConfig:
    return SynthConfig.model_validate({"camera": {"width_px": W, "height_px": H}})


@pytest.fixture(scope="module")
def world(small_cfg) -> SynthWorld:
    return SynthWorld.from_seed(0, small_cfg)


def camera_pose(world: SynthWorld, s_m: float, lateral_m: float = 0.0) -> np.ndarray:
    p = world.path.at(s_m)
    T = pose_2d(float(p["x_m"]), float(p["y_m"]), float(p["yaw_rad"]))
    T[:2, 3] += lateral_m * np.array([-np.sin(p["yaw_rad"]), np.cos(p["yaw_rad"])])
    return T @ world.camera.T_vehicle_camera


def test_layout_keeps_objects_off_the_road_and_has_all_kinds(world):
    lay = world.layout
    assert len(lay.buildings) > 5 and len(lay.trees) > 20 and len(lay.cars) > 3
    road_xy = np.column_stack([world.road.x_m, world.road.y_m])
    outer = sidewalk_outer_m(world.config.road)
    for b in lay.buildings:
        d = np.min(np.hypot(*(road_xy - [b.x_m, b.y_m]).T))
        assert d > outer + min(b.length_m, b.depth_m) / 2 - 0.1
    # parked cars stand in the parking strip: beyond the lane, inside the curb
    lane = world.config.road.lane_width_m
    for c in lay.cars:
        d = np.min(np.hypot(*(road_xy - [c.x_m, c.y_m]).T))
        assert lane < d < lane + world.config.road.parking_width_m
    assert 20_000 < world.triangle_count < 80_000


def test_road_pixel_depth_matches_the_ground_plane(world):
    """Bottom-centre pixel sees the flat road: depth = h cos(a) / sin(a + pitch) for the ray a below the axis."""
    cam = world.camera
    rgb, depth = world.render(camera_pose(world, 30.0), cam.K, W, H)
    v = H - 1
    below_axis = np.arctan((v - cam.K[1, 2]) / cam.K[1, 1])
    pitch = np.deg2rad(3.0)
    expected = cam.height_m * np.cos(below_axis) / np.sin(below_axis + pitch)
    assert depth[v, W // 2] == pytest.approx(expected, rel=0.01)
    # a whole row near the bottom is road at the same depth (flat, level road)
    row = depth[v, W // 2 - 20 : W // 2 + 20]
    assert np.allclose(row, expected, rtol=0.01)
    assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3)


def test_sky_has_infinite_depth_and_is_blue(world):
    cam = world.camera
    rgb, depth, ids = world.render_full(camera_pose(world, 30.0), cam.K, W, H)
    top = depth[0]
    assert np.isinf(top).mean() > 0.3
    sky = rgb[0][np.isinf(top)].astype(int)
    assert np.all(sky[:, 2] > sky[:, 0])  # blue over red
    assert np.all(ids[np.isinf(depth)] == -1)
    assert np.all(np.isfinite(depth[-1]))
    assert ids[-1, W // 2] == SEMANTIC_IDS["road"]
    present = set(np.unique(ids).tolist())
    assert {SEMANTIC_IDS["road"], SEMANTIC_IDS["building"], SEMANTIC_IDS["sidewalk"]} <= present


def test_lane_markings_are_white_on_dark_asphalt(world):
    """The right edge line is painted 1.75 m right of the lane centre: brighter than the asphalt beside it."""
    K = intrinsics_from_hfov(W, H, np.deg2rad(80.0))
    T = camera_pose(world, 30.0)
    rgb, depth = world.render(T, K, W, H)
    # project a point on the edge line 8 m ahead and asphalt 1 m inside the lane
    p = world.path.at(30.0 + world.camera.T_vehicle_camera[0, 3] + 8.0)
    yaw = float(p["yaw_rad"])
    normal = np.array([-np.sin(yaw), np.cos(yaw)])

    def pixel(lateral_m: float) -> tuple[int, int]:
        xy = np.array([p["x_m"], p["y_m"]]) + lateral_m * normal
        pc = np.linalg.inv(T) @ np.array([xy[0], xy[1], 0.0, 1.0])
        uv = K @ pc[:3]
        return int(round(uv[1] / uv[2])), int(round(uv[0] / uv[2]))

    line = rgb[pixel(-1.75)].astype(float).mean()
    asphalt = rgb[pixel(-0.75)].astype(float).mean()
    assert line > asphalt + 60


def test_render_is_deterministic_for_a_seed_and_differs_between_seeds(world, small_cfg):
    cam = world.camera
    T = camera_pose(world, 40.0)
    rgb_a, depth_a = world.render(T, cam.K, W, H)
    again = SynthWorld.from_seed(0, small_cfg)
    rgb_b, depth_b = again.render(T, cam.K, W, H)
    assert np.array_equal(rgb_a, rgb_b)
    assert np.array_equal(depth_a, depth_b)
    other = SynthWorld.from_seed(1, small_cfg)
    n = min(len(other.road.curvature_1pm), len(world.road.curvature_1pm))
    assert not np.allclose(other.road.curvature_1pm[:n], world.road.curvature_1pm[:n])


def test_moving_the_camera_sideways_moves_the_view(world):
    """A camera 1 m to the left sees the road edge 1 m farther away: depth changes, image changes."""
    cam = world.camera
    rgb0, depth0 = world.render(camera_pose(world, 40.0), cam.K, W, H)
    rgb1, depth1 = world.render(camera_pose(world, 40.0, lateral_m=1.0), cam.K, W, H)
    assert np.mean(np.abs(rgb0.astype(int) - rgb1.astype(int))) > 5
    # the flat road at the bottom row is at the same depth from anywhere on it
    assert depth1[-1, W // 2] == pytest.approx(depth0[-1, W // 2], rel=1e-3)


def test_world_rebuilds_from_a_sidecar(tmp_path, world, small_cfg):
    sidecar = tmp_path / "x.world.json"
    sidecar.write_text(json.dumps({"seed": 0, "config": small_cfg.model_dump(mode="json")}))
    rebuilt = SynthWorld.from_sidecar(sidecar)
    assert rebuilt.triangle_count == world.triangle_count
    assert np.array_equal(rebuilt.path.x_m, world.path.x_m)
    assert rebuilt.camera.width_px == W


def test_view_distance_culls_far_surfaces_only(world, small_cfg):
    near_cfg = small_cfg.model_copy(deep=True)
    near_cfg.world.scenery.view_distance_m = 60.0
    near_world = SynthWorld.from_seed(0, near_cfg)
    cam = world.camera
    T = camera_pose(world, 40.0)
    _, depth_all = world.render(T, cam.K, W, H)
    _, depth_near = near_world.render(T, cam.K, W, H)
    close = depth_all < 30.0
    # identical but for float rounding, which can differ by millimetres on a pixel at a car's silhouette when the
    # rasterizer gets another set of triangles
    assert np.isclose(depth_near[close], depth_all[close], rtol=1e-4).mean() > 0.999
    assert np.allclose(depth_near[close], depth_all[close], rtol=1e-3)
    assert np.isinf(depth_near).sum() > np.isinf(depth_all).sum()
    assert np.nanmax(np.where(np.isinf(depth_near), np.nan, depth_near)) < 60.0 + 2 * 90.0


def test_a_town_without_edge_lines_paints_only_the_dashed_centre_line():
    """road.edge_lines off: across the asphalt texture, no white at the lanes' outer edges, the dashed centre line as
    before, and the rest of the texture (the same seed's noise) unchanged."""
    from drivesim.stages.synth.textures import LINE_WIDTH_M, ROAD_PX_PER_M, RoadLayout, asphalt_texture

    with_lines, without = (
        asphalt_texture(np.random.default_rng(3), RoadLayout(3.5, 5.7, edge_lines=flag)) for flag in (True, False)
    )
    lateral_m = 5.7 - (np.arange(with_lines.shape[1]) + 0.5) / ROAD_PX_PER_M
    edge = np.abs(np.abs(lateral_m) - 3.5) < LINE_WIDTH_M / 2
    centre = np.abs(lateral_m) < LINE_WIDTH_M / 2
    dash_rows = slice(0, int(2.5 * ROAD_PX_PER_M))
    assert with_lines[:, edge].mean() > 160 and without[:, edge].mean() < 110
    assert without[dash_rows][:, centre].mean() > 160
    far = np.abs(np.abs(lateral_m) - 3.5) > 0.5
    assert np.array_equal(with_lines[:, far], without[:, far])
