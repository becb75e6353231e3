"""The synth world's compiled renderer: the rasterizer's pixels, the view distance's faces, bounded packings."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivesim.sim.geometry import invert, pose_2d
from drivesim.sim.mesh import Mesh
from drivesim.sim.raster import Rasterizer, pack_meshes
from drivesim.stages.synth.config import SynthConfig
from drivesim.stages.synth.render import CellCulling
from drivesim.stages.synth.world import HAZE_DISTANCE_M, SEMANTIC_IDS, SKY_HORIZON_RGB, SynthWorld

W, H = 320, 200


def small_cfg(road_length_m: float = 400.0) -> SynthConfig:
    return SynthConfig.model_validate(
        {"camera": {"width_px": W, "height_px": H}, "world": {"road": {"length_m": road_length_m}}}
    )


@pytest.fixture(scope="module")
def world() -> SynthWorld:
    return SynthWorld.from_seed(0, small_cfg())


def camera_pose(world: SynthWorld, s_m: float) -> np.ndarray:
    p = world.path.at(s_m)
    return pose_2d(float(p["x_m"]), float(p["y_m"]), float(p["yaw_rad"])) @ world.camera.T_vehicle_camera


def rasterizer_reference(world: SynthWorld, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb uint8 with haze, depth, ids) of the faces within the view distance through `sim.raster.Rasterizer`."""
    culling = CellCulling(world.meshes)
    near = culling.near_cells(T_world_camera[:2, 3], world.config.scenery.view_distance_m)
    meshes, _ = culling.visible_meshes(near)
    cam = world.camera
    result = Rasterizer(W, H).render(meshes, invert(T_world_camera), cam.K, world.lighting(T_world_camera))
    rgb, depth = result.rgb[0], result.depth_m[0]
    haze = -torch.expm1(-depth.masked_fill(torch.isinf(depth), 0.0) / HAZE_DISTANCE_M)
    rgb = rgb + haze[..., None] * (torch.as_tensor(SKY_HORIZON_RGB) - rgb)
    rgb = (rgb.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()
    return rgb, depth.numpy(), result.object_id[0].numpy()


@pytest.mark.parametrize("s_m", [25.0, 140.0, 290.0])
def test_frames_are_the_rasterizers_but_for_rounding(world, s_m):
    T = camera_pose(world, s_m)
    cam = world.camera
    rgb, depth, ids = world.render_full(T, cam.K, W, H)
    ref_rgb, ref_depth, ref_ids = rasterizer_reference(world, T)
    sky = np.isinf(ref_depth)
    assert 0.05 < sky.mean() < 0.9 and (~sky).mean() > 0.1
    assert np.mean(np.isinf(depth) == sky) > 0.9995
    assert np.mean(ids == ref_ids) > 0.9995
    both = ~sky & np.isfinite(depth)
    rel = np.abs(depth[both] - ref_depth[both]) / ref_depth[both]
    assert np.quantile(rel, 0.999) < 1e-3
    diff = np.abs(rgb.astype(int) - ref_rgb.astype(int)).max(-1)[both]
    assert np.mean(diff <= 1) > 0.995
    assert np.mean(diff > 8) < 0.001
    # the sky: blue over red, lighter toward the horizon
    sky_rgb = rgb[sky & np.isinf(depth)].astype(int)
    assert np.all(sky_rgb[:, 2] >= sky_rgb[:, 0])


def test_a_packing_serves_the_cells_a_camera_sees_and_only_those(world):
    """Along the drive, the triangles drawn from the (wider, reused) packing are exactly the faces of the cells
    within the view distance, in the same order."""
    culling = CellCulling(world.meshes)
    distance_m = 120.0
    packings = set()
    for s_m in np.arange(10.0, 330.0, 7.0):
        xy = camera_pose(world, float(s_m))[:2, 3]
        packed, triangles = culling.scene(xy, distance_m)
        packings.add(id(packed))
        exact = pack_meshes(culling.visible_meshes(culling.near_cells(xy, distance_m))[0])
        chosen = np.arange(len(packed.object_id)) if triangles is None else triangles
        assert len(chosen) == exact.triangle_count
        assert np.array_equal(packed.object_id[chosen], exact.object_id.numpy())
        corners = packed.vertices.reshape(3, 3, -1)[:, :, chosen] + packed.origin_m[:, None, None]
        expected = exact.vertex_components.numpy() + exact.origin_m[:, None, None]
        assert np.allclose(corners, expected, atol=1e-3)
    assert 3 <= len(packings) < 25  # reused over tens of metres, remade as the car moves on


def test_a_packing_holds_what_is_near_however_long_the_road():
    """Textures and triangles in a packing do not grow with the road: a 4 km world's packing holds about what a
    1 km world's does (each building group has its own facade atlas, made when a packing needs it)."""
    sizes = {}
    for length_m in (1000.0, 4000.0):
        world = SynthWorld.from_seed(0, small_cfg(length_m))
        culling = world._culling  # the world's own: its facades are made as cameras come near
        texels, triangles = [], []
        for s_m in (300.0, 600.0):
            packed, _ = culling.scene(camera_pose(world, s_m)[:2, 3], world.config.scenery.view_distance_m)
            texels.append(len(packed.texels))
            triangles.append(len(packed.object_id))
        sizes[length_m] = (max(texels), max(triangles), world.triangle_count)
        groups = [m for m in world._sources if isinstance(m, Mesh) and m.object_id == SEMANTIC_IDS["building"]]
        made = world._culling._textures  # the facade atlases made and kept: those of the packing in use
        assert 0 < len(made) <= len(groups) // (3 if length_m > 2000 else 1)
    short, long = sizes[1000.0], sizes[4000.0]
    assert long[2] > 3 * short[2]  # the long world is larger ...
    assert long[0] < 1.5 * short[0] and long[1] < 1.5 * short[1]  # ... its packings are not


def test_facades_made_on_demand_are_the_whole_worlds(world):
    """The world makes a building group's facade atlas only when a packing needs it; its frames are those of the
    same meshes with every atlas made up front, to the bit."""
    T = camera_pose(world, 120.0)
    cam = world.camera
    rgb, depth, ids = world.render_full(T, cam.K, W, H)
    from drivesim.stages.synth.render import Scratch, render_packed

    culling = CellCulling(world.meshes)
    packed, triangles = culling.scene(T[:2, 3], world.config.scenery.view_distance_m)
    frame = render_packed(
        packed, triangles, invert(T), cam.K, W, H, world.lighting(T), HAZE_DISTANCE_M, world._sky, Scratch()
    )  # fmt: skip
    assert np.array_equal(frame.rgb, rgb) and np.array_equal(frame.depth_m, depth)
    assert np.array_equal(frame.object_id, ids)
