"""Occlusion of inserted cars by the warped world: a recorded surface covers a car only where it is really nearer, and
no background pixel is drawn through a car body (`raster.through_body_count`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gl_reference import car_meshes

from drivesim.sim import geometry as g
from drivesim.sim.raster import Rasterizer, RenderResult, composite, pack_meshes, through_body_count
from drivesim.sim.raster_kernel import OCCLUDER_MIN_GAP

H, W = 96, 160
K = g.intrinsics_from_hfov(W, H, np.deg2rad(70.0))


def _camera() -> np.ndarray:
    """T_camera_world of a camera 1.5 m above flat ground looking along +x."""
    return g.invert(g.pose_2d(0.0, 0.0, 0.0) @ g.camera_mount(0.0, 0.0, 1.5, pitch_down_rad=0.05))


def _car_render() -> tuple[Rasterizer, list, np.ndarray, np.ndarray, RenderResult]:
    """A car 10 m ahead: the rasterizer, its scene, pose, lighting and its own render (depth buffer)."""
    scene = [pack_meshes(car_meshes()).transformed(g.pose_2d(10.0, 0.0, 0.2))]
    T = _camera()[None]
    lights = np.array([[1, 1, 1, 0, 0.5, 0.8, 0.4, 0.4, 0.4]], dtype=np.float32)
    rasterizer = Rasterizer(W, H, cull_back_faces=True)
    return rasterizer, scene, T, lights, rasterizer.render(scene, T, K, lighting=lights)


def _world_depth(car_depth_m: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A world depth (H, W) over the car's columns in four bands: an occluder at half the car's depth, a surface at
    95 % of it (the road the car stands on, as estimated), a wall at twice it and a hole (+inf); 30 m elsewhere."""
    car = np.isfinite(car_depth_m)
    cols = np.flatnonzero(car.any(axis=0))
    edges = np.linspace(cols[0], cols[-1] + 1, 5).round().astype(int)
    depth = np.full((H, W), 30.0, np.float32)
    bands = {}
    for name, (a, b), factor in zip(
        ("occluder", "road", "behind", "hole"),
        zip(edges[:-1], edges[1:], strict=True),
        (0.5, 0.95, 2.0, np.inf),
        strict=True,
    ):
        band = np.zeros((H, W), bool)
        band[:, a:b] = car[:, a:b]
        depth[band] = car_depth_m[band] * factor
        bands[name] = band
    return depth, bands


@pytest.mark.parametrize("path", ["draw_into", "composite_torch"])
def test_world_covers_the_car_only_where_really_nearer(path):
    rasterizer, scene, T, lights, drawn = _car_render()
    car_depth = drawn.depth_m[0].numpy()
    assert np.isfinite(car_depth).sum() > 300
    depth, bands = _world_depth(car_depth)
    view = np.full((1, H, W, 3), 250, np.uint8)  # a bright background
    if path == "draw_into":
        out, shown = view.copy(), np.zeros((1, H, W), bool)
        rasterizer.draw_into(scene, T, K, lights, out, depth[None].copy(), shown, np.array([0]), False)
    else:
        rgb, _, front = composite(torch.from_numpy(view), torch.from_numpy(depth[None]), drawn)
        out, shown = rgb.numpy(), front.numpy()
    shown = shown[0]
    car_rgb = (drawn.rgb[0].numpy() * 255.0 + 0.5).astype(np.uint8)
    assert not shown[bands["occluder"]].any()  # the nearer recorded object hides the car
    assert (out[0][bands["occluder"]] == 250).all()
    for name in ("road", "behind", "hole"):  # no background through the body
        assert shown[bands[name]].all(), name
        np.testing.assert_array_equal(out[0][bands[name]], car_rgb[bands[name]], err_msg=name)  # the car's colour
    assert through_body_count(car_depth, depth, shown) == 0
    assert not shown[~np.isfinite(car_depth)].any()


def test_through_body_count_counts_background_shown_over_the_car():
    car = np.full((4, 4), np.inf, np.float32)
    car[1:3, 1:3] = 10.0
    world = np.full((4, 4), 20.0, np.float32)
    world[1, 1] = 10.0 * (1.0 - OCCLUDER_MIN_GAP) - 0.5  # really nearer: may cover the car
    world[1, 2] = 9.5  # the road under the car: within the gap
    shown = np.zeros((4, 4), bool)
    shown[2, 2] = True
    # (1, 2) and (2, 1) show the world where the car stands in front; (1, 1) is rightly covered
    assert through_body_count(car, world, shown) == 2
    shown[1:3, 1:3] = True
    shown[1, 1] = False
    assert through_body_count(car, world, shown) == 0
