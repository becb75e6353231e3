"""The torch rasterizer against OpenGL (moderngl on EGL) and against closed-form answers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from gl_reference import (
    GLRenderer,
    car_meshes,
    checker_texture,
    create_context,
    ground_plane,
    textured_quad,
)

from drivesim.sim import geometry as g
from drivesim.sim import raster_kernel
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.raster import Lighting, PackedScene, Rasterizer, pack_meshes
from drivesim.sim.shading import specular_exponent

H, W = 200, 320
K = g.intrinsics_from_hfov(W, H, np.deg2rad(70.0))
CAMERA_HEIGHT_M = 1.5


def camera_at(x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0, pitch_down_rad: float = 0.05) -> np.ndarray:
    """T_camera_world of a car-mounted camera 1.5 m above flat ground."""
    T_world_cam = g.pose_2d(x_m, y_m, yaw_rad) @ g.camera_mount(
        0.0, 0.0, CAMERA_HEIGHT_M, pitch_down_rad=pitch_down_rad
    )
    return g.invert(T_world_cam)


def street_scene() -> list[Mesh]:
    """A car (~5k triangles), a textured sign facing the camera and a ground plane passing behind the camera."""
    car = [m.transformed(g.pose_2d(8.0, 0.8, 0.6)) for m in car_meshes(object_id=0)]
    sign = textured_quad(object_id=5).transformed(g.se3(g.rot_z(-np.pi / 2 + 0.3), [6.0, -2.5, 1.2]))
    return [*car, sign, ground_plane(object_id=100)]


@pytest.fixture(scope="module")
def gl_context():
    try:
        ctx = create_context()
    except Exception as exc:  # noqa: BLE001 - any failure to open EGL means: no reference renderer here
        pytest.skip(
            f"moderngl EGL context unavailable ({exc}); install Mesa EGL (Debian: libegl1 libgl1-mesa-dri) to run it"
        )
    yield ctx
    ctx.release()


def test_car_scene_matches_opengl(gl_context):
    meshes = street_scene()
    assert 4500 <= sum(m.triangle_count for m in meshes[:3]) <= 6000
    T = camera_at()
    ref = GLRenderer(gl_context, W, H).render(meshes, T, K)
    out = Rasterizer(W, H).render(meshes, T, K)
    object_id, depth, rgb = out.object_id[0].numpy(), out.depth_m[0].numpy(), out.rgb[0].numpy()
    assert np.array_equal(np.isfinite(depth), object_id >= 0) and (depth > 0).all()
    for obj in (0, 5, 100):
        ours, theirs = object_id == obj, ref["object_id"] == obj
        assert theirs.sum() > 400, f"object {obj} barely visible: the test scene is wrong"
        iou = (ours & theirs).sum() / (ours | theirs).sum()
        assert iou >= 0.99, f"object {obj}: mask IoU {iou:.4f}"
    assert ((object_id >= 0) == (ref["object_id"] >= 0)).mean() >= 0.995
    same = (object_id == ref["object_id"]) & (object_id >= 0)
    depth_err_m = np.abs(depth[same] - ref["depth_m"][same])
    assert np.median(depth_err_m) <= 0.01
    assert np.percentile(depth_err_m, 99) <= 0.05
    # Same Blinn-Phong formula on both sides; differences come from interpolation precision and edge pixels.
    rgb_err = np.abs(rgb - ref["rgb"])[same]
    assert np.median(rgb_err) <= 2e-3
    assert np.percentile(rgb_err, 99) <= 0.03


def test_textured_sign_matches_opengl(gl_context):
    """A textured quad filling much of the view: uv interpolation and bilinear filtering as in OpenGL."""
    sign = textured_quad(width_m=2.0, height_m=1.5, object_id=3).transformed(
        g.se3(g.rot_z(-np.pi / 2 + 0.4), [4.0, 0.0, CAMERA_HEIGHT_M])
    )
    T = camera_at(pitch_down_rad=0.0)
    ref = GLRenderer(gl_context, W, H).render([sign], T, K)
    out = Rasterizer(W, H).render([sign], T, K)
    same = (out.object_id[0].numpy() == 3) & (ref["object_id"] == 3)
    assert same.sum() > 5000
    rgb_err = np.abs(out.rgb[0].numpy() - ref["rgb"])[same]
    assert np.median(rgb_err) <= 2e-3
    assert np.percentile(rgb_err, 99) <= 0.03


def test_ground_plane_crossing_the_camera_has_exact_depth():
    """Two huge ground triangles pass behind the camera: every pixel below the horizon must be drawn, at the
    depth of the plane, z = h fy / (v - cy) for a level camera at height h."""
    T = camera_at(pitch_down_rad=0.0)
    out = Rasterizer(W, H).render([ground_plane(size_m=500.0)], T, K)
    v = np.arange(H, dtype=np.float64)
    below = v > K[1, 2] + 1  # rows whose ray hits the ground inside the 500 m square
    expected = CAMERA_HEIGHT_M * K[1, 1] / (v[below] - K[1, 2])
    depth = out.depth_m[0].numpy()[below]
    assert np.isfinite(depth).all(), "ground pixels missing below the horizon"
    np.testing.assert_allclose(depth, np.broadcast_to(expected[:, None], depth.shape), rtol=1e-4)
    assert not out.mask[0, : int(K[1, 2]) - 1].any(), "ground drawn above the horizon"


def test_surface_cut_at_near_plane():
    """A wall crossing the near plane is drawn only beyond it, not dropped."""
    wall = Mesh(
        np.array([[-5.0, 1.0, -2.0], [5.0, 1.0, -2.0], [5.0, 1.0, 8.0], [-5.0, 1.0, 8.0]], np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
    )
    rast = Rasterizer(W, H, near_m=0.5)
    out = rast.render([wall], np.eye(4), K)  # camera frame = world frame; the floor y = 1 m below the camera
    depth = out.depth_m[0].numpy()
    assert out.mask[0].sum() > 0.3 * H * W
    assert np.array_equal(np.isfinite(depth), out.mask[0].numpy()) and (depth > 0).all()
    assert depth[np.isfinite(depth)].min() >= 0.5 - 1e-4
    assert depth[np.isfinite(depth)].max() <= 8.0 + 1e-3


def test_shading_follows_the_blinn_phong_formula():
    """A flat quad facing a camera lit from the viewpoint: n.l = n.h = 1 at the centre pixel."""
    material = Material(diffuse_rgb=(0.6, 0.3, 0.1), specular_rgb=(0.5, 0.4, 0.3), shininess=40.0, metalness=0.25)
    quad = Mesh(
        np.array([[-1, -1, 5], [1, -1, 5], [1, 1, 5], [-1, 1, 5]], np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
        material=material,
    )
    light = Lighting(ambient_rgb=np.array([0.2, 0.25, 0.3]), light_rgb=np.array([0.7, 0.6, 0.5]))
    K_centred = g.intrinsics(200.0, 200.0, 100.0, 100.0)
    out = Rasterizer(201, 201).render([quad], np.eye(4), K_centred, lighting=light)
    base = np.array(material.diffuse_rgb)
    f0 = (1 - material.metalness) * np.array(material.specular_rgb) + material.metalness * base
    expected = light.ambient_rgb * base + light.light_rgb * ((1 - material.metalness) * base + f0)
    np.testing.assert_allclose(out.rgb[0, 100, 100].numpy(), np.clip(expected, 0, 1), atol=1e-5)
    np.testing.assert_allclose(out.normal_cam[0, 100, 100].numpy(), [0, 0, -1], atol=1e-6)
    # Off-centre the highlight falls with (n.h)^exponent.
    exponent = float(specular_exponent(torch.tensor(40.0), torch.tensor(0.5)))
    assert exponent == pytest.approx(11.0)
    assert out.rgb[0, 100, 100].sum() > out.rgb[0, 100, 140].sum()


def test_unlit_material_background_and_ids():
    sky = Mesh(
        np.array([[-50, -50, 40], [50, -50, 40], [0, 50, 40]], np.float32),
        np.array([[0, 1, 2]]),
        material=Material(diffuse_rgb=(0.5, 0.7, 0.9), unlit=True),
        object_id=7,
    )
    out = Rasterizer(64, 48).render([sky], np.eye(4), g.intrinsics(40, 40, 32, 24), background_rgb=(1.0, 0.0, 1.0))
    inside = out.object_id[0] == 7
    assert inside.sum() > 100 and (~inside).sum() > 100
    np.testing.assert_allclose(
        out.rgb[0][inside].numpy(), np.broadcast_to([0.5, 0.7, 0.9], (int(inside.sum()), 3)), rtol=1e-6
    )
    assert (out.rgb[0][~inside] == torch.tensor([1.0, 0.0, 1.0])).all()
    assert torch.isinf(out.depth_m[0][~inside]).all() and (out.object_id[0][~inside] == -1).all()
    np.testing.assert_allclose(out.depth_m[0][inside].numpy(), 40.0, rtol=1e-6)


def test_batch_of_cameras_equals_single_renders():
    meshes = street_scene()
    poses = [camera_at(), camera_at(1.0, 0.3, 0.1), camera_at(-2.0, -1.0, -0.2)]
    rast = Rasterizer(W, H)
    batch = rast.render(meshes, np.stack(poses), K)
    for b, T in enumerate(poses):
        single = rast.render(meshes, T, K)
        assert torch.equal(batch.object_id[b], single.object_id[0])
        assert torch.equal(batch.depth_m[b], single.depth_m[0])
        torch.testing.assert_close(batch.rgb[b], single.rgb[0])


def assert_depths_agree(a: torch.Tensor, b: torch.Tensor) -> None:
    """Depths of the kernel and the torch path: within 1 mm on 99 % of pixels and 1 cm everywhere (triangles that
    cross the near plane have large edge coefficients, where float32 rounding reaches a few mm)."""
    error_m = (a - b).abs()
    assert error_m.max() < 0.01
    assert (error_m < 1e-3).float().mean() > 0.99


def test_cpu_kernel_matches_the_torch_path():
    """The compiled CPU kernels and the torch path (the one a GPU runs) draw the same surfaces with the same depth,
    colour and normals: the street scene (small car triangles, a ground plane through the camera) from three cameras
    in one call."""
    meshes = street_scene()
    poses = np.stack([camera_at(), camera_at(1.0, 0.3, 0.1), camera_at(-2.0, -1.0, -0.2)])
    kernel = Rasterizer(W, H).render(meshes, poses, K)
    reference = Rasterizer(W, H, use_kernel=False).render(meshes, poses, K)
    assert (reference.object_id == 0).sum() > 3000  # the car is in view
    assert (kernel.object_id == reference.object_id).float().mean() > 0.999
    both = kernel.mask & reference.mask
    assert_depths_agree(kernel.depth_m[both], reference.depth_m[both])
    same = (kernel.rgb - reference.rgb).abs().amax(-1) < 1e-3
    assert same[both].float().mean() > 0.999
    same_normal = (kernel.normal_cam - reference.normal_cam).abs().amax(-1) < 1e-3
    assert same_normal[both].float().mean() > 0.999


def test_cpu_kernel_matches_the_torch_path_for_placed_cars():
    """The agent's case: per-camera packed cars placed in camera frames, back faces culled, each camera with its own
    lighting, and one camera beside the car, so that its triangles cross the near plane."""
    car = pack_meshes(car_meshes())
    lights = [Lighting(), Lighting(ambient_rgb=np.array([0.6, 0.5, 0.4]), light_rgb=np.array([0.3, 0.3, 0.2]))]
    T = np.stack([camera_at(), camera_at(4.0, 0.0, 0.1)])
    scenes = [[car.transformed(g.pose_2d(9.0, 1.0, 0.3))], [car.transformed(g.pose_2d(4.5, 2.2, 0.0))]]
    results = [
        Rasterizer(W, H, cull_back_faces=True, use_kernel=use_kernel).render(scenes, T, K, lighting=lights)
        for use_kernel in (True, False)
    ]
    kernel, reference = results
    assert (reference.object_id[0] >= 0).sum() > 1000 and (reference.object_id[1] >= 0).sum() > 4000
    assert (kernel.object_id == reference.object_id).float().mean() > 0.999
    both = kernel.mask & reference.mask
    assert_depths_agree(kernel.depth_m[both], reference.depth_m[both])
    assert ((kernel.rgb - reference.rgb).abs().amax(-1) < 1e-3)[both].float().mean() > 0.999
    assert not torch.equal(kernel.rgb[0][both[0]].mean(0), kernel.rgb[1][both[1]].mean(0)), "lighting differs"


@pytest.mark.parametrize(("gray", "threads"), [(False, 1), (True, 1), (False, 3)])
def test_drawing_into_views_equals_render_then_composite(gray, threads):
    """`draw_into` (the CPU view path: the car rasterized and composited into the warped view in one call) writes the
    pixels and the car mask that `render` then `composite_uint8` write: three cameras drawing into views 2, 0 and 3
    of four (view 1 without a car), a wall nearer than part of a car, the second camera beside the car (triangles
    across the near plane), each camera with its own lighting; on one thread and with the rows shared among three."""
    car = pack_meshes(car_meshes())
    scenes = [car.transformed(g.pose_2d(9.0, 1.0, 0.3)), car.transformed(g.pose_2d(4.5, 2.2, 0.0)), car]
    T = np.stack([camera_at(), camera_at(4.0, 0.0, 0.1), camera_at(-7.0, -0.5, 0.2)])
    lights = np.array([[1, 1, 1, 0, 0.5, 0.8, 0.4, 0.4, 0.4], [0.6, 0.5, 0.4, 0, 0.6, 0.8, 0.3, 0.3, 0.2],
                       [0.9, 0.9, 1.0, 0.2, 0.5, 0.8, 0.5, 0.5, 0.5]], dtype=np.float32)  # fmt: skip
    rng = np.random.default_rng(3)
    views = rng.integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)
    depth = np.full((4, H, W), np.inf, np.float32)
    depth[:, :, 120:200] = 6.5  # a wall across the middle, in front of the first car
    view_of_camera = np.array([2, 0, 3])
    rasterizer = Rasterizer(W, H, cull_back_faces=True)
    drawn = rasterizer.render(scenes, T, K, lighting=lights)
    expected, expected_front = views.copy(), np.zeros((4, H, W), dtype=bool)
    for cam, v in enumerate(view_of_camera):
        car_rgb, car_depth = drawn.rgb[cam].numpy(), drawn.depth_m[cam].numpy()
        raster_kernel.composite_uint8(expected[v], depth[v], car_rgb, car_depth, expected_front[v], gray)
    out, front = views.copy(), np.zeros((4, H, W), dtype=bool)
    rasterizer.draw_into(scenes, T, K, lights, out, depth, front, view_of_camera, gray, threads)
    assert expected_front[0].sum() > 4000 and expected_front[2].sum() > 1000 and not expected_front[1].any()
    hidden = np.isfinite(drawn.depth_m.numpy()) & ~expected_front[view_of_camera]
    assert hidden.sum() > 500  # the wall hides part of a car
    np.testing.assert_array_equal(front, expected_front)
    np.testing.assert_array_equal(out, expected)


def test_per_camera_scenes_and_lighting():
    """One call renders B different scenes (one per agent) with their own lighting."""
    cars_a = [m.transformed(g.pose_2d(8.0, 0.0, 0.0)) for m in car_meshes(object_id=1)]
    cars_b = [m.transformed(g.pose_2d(12.0, 2.0, 0.5)) for m in car_meshes(object_id=2, body_rgb=(0.1, 0.2, 0.8))]
    # Textured signs in both scenes: texture tables are concatenated, their offsets must follow.
    sign = textured_quad(object_id=3).transformed(g.se3(g.rot_z(-np.pi / 2 + 0.3), [6.0, -2.5, 1.2]))
    other_texture = (255 - checker_texture(32, 4)).astype(np.uint8)
    sign_b = textured_quad(object_id=4, texture=other_texture).transformed(g.se3(g.rot_z(-np.pi / 2), [9.0, 3.0, 1.5]))
    cars_a, cars_b = [*cars_a, sign], [sign_b, *cars_b]
    lights = [Lighting(), Lighting(ambient_rgb=np.array([0.6, 0.5, 0.4]))]
    rast = Rasterizer(W, H)
    T = np.stack([camera_at(), camera_at(0.0, 0.5)])
    batch = rast.render([cars_a, cars_b], T, K, lighting=lights)
    for b, (meshes, light) in enumerate(zip([cars_a, cars_b], lights, strict=True)):
        single = rast.render(meshes, T[b], K, lighting=light)
        assert torch.equal(batch.object_id[b], single.object_id[0])
        assert torch.equal(batch.depth_m[b], single.depth_m[0])
        torch.testing.assert_close(batch.rgb[b], single.rgb[0])
    assert set(batch.object_id[0].unique().tolist()) == {-1, 1, 3}
    assert set(batch.object_id[1].unique().tolist()) == {-1, 2, 4}


def test_packed_scene_is_cached_and_reusable():
    meshes = street_scene()
    rast = Rasterizer(W, H)
    assert rast.pack(meshes) is rast.pack(meshes)
    packed = pack_meshes(meshes)
    assert isinstance(packed, PackedScene) and packed.triangle_count == sum(m.triangle_count for m in meshes)
    a = rast.render(packed, camera_at(), K)
    b = rast.render(meshes, camera_at(), K)
    assert torch.equal(a.depth_m, b.depth_m)


def test_a_repainted_model_is_packed_from_its_first_packing():
    """A repaint (same geometry arrays, new body material) packs as `pack_meshes` would, from the rasterizer's cached
    packing of the model, and renders the new colour; a different geometry is packed afresh."""
    from dataclasses import replace

    from drivesim.sim.raster import repainted_pack

    car = car_meshes(object_id=0)
    red = Material(diffuse_rgb=(0.9, 0.1, 0.1), metalness=0.3)
    repaint = [replace(m, material=red) if k == 0 else m for k, m in enumerate(car)]
    rasterizer = Rasterizer(W, H)
    original = rasterizer.pack(car)
    derived = rasterizer.pack(repaint)
    fresh = pack_meshes(repaint)
    for name in ("vertex_components", "attribute_table", "material", "texture_index", "object_id", "texels"):
        assert torch.equal(getattr(derived, name), getattr(fresh, name)), name
    assert not torch.equal(derived.attribute_table, original.attribute_table), "the body's colour changed"
    assert rasterizer.pack(repaint) is derived
    moved = [m.transformed(g.pose_2d(1.0, 0.0, 0.0)) for m in car]
    assert repainted_pack(original, car, moved) is None


def test_far_from_origin_world_keeps_precision():
    """ENU coordinates kilometres away: packing relative to the scene centre keeps depth at float32 precision."""
    offset = g.se3(np.eye(3), [3000.0, -2000.0, 0.0])
    near = Rasterizer(W, H).render(street_scene(), camera_at(), K)
    far_meshes = [m.transformed(offset) for m in street_scene()]
    far = Rasterizer(W, H).render(far_meshes, camera_at() @ g.invert(offset), K)
    agree = (near.object_id == far.object_id) & near.mask
    assert agree.float().mean() > 0.99 * near.mask.float().mean()
    assert (near.depth_m[agree] - far.depth_m[agree]).abs().median() < 1e-3


CUDA_ONLY = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@CUDA_ONLY
def test_cuda_matches_cpu():
    meshes = street_scene()
    cpu = Rasterizer(W, H).render(meshes, camera_at(), K)
    gpu = Rasterizer(W, H, device="cuda").render(meshes, camera_at(), K)
    assert (cpu.object_id == gpu.object_id.cpu()).float().mean() > 0.999
    same = (cpu.object_id == gpu.object_id.cpu()) & cpu.mask
    # float32 arithmetic in another order (the CPU's compiled kernel, the GPU's torch kernels): within a millimetre
    # per metre (an H200 gave 1.3 mm at 3.1 m, 2026-11-26).
    relative = (cpu.depth_m[same] - gpu.depth_m.cpu()[same]).abs() / cpu.depth_m[same]
    assert relative.max() < 1e-3


def test_placed_packed_vehicles_match_transformed_meshes():
    """The agent fast path: pack a car once in its own frame, place copies with PackedScene.transformed."""
    car = pack_meshes(car_meshes())
    poses = [g.pose_2d(8.0, 1.0, 0.3), g.pose_2d(15.0, -3.0, -0.2)]
    rast = Rasterizer(W, H)
    T = camera_at()
    placed = rast.render([[car.transformed(P, object_id=i) for i, P in enumerate(poses)], []], np.stack([T, T]), K)
    direct = rast.render([m.transformed(P) for i, P in enumerate(poses) for m in car_meshes(object_id=i)], T, K)
    assert set(placed.object_id[0].unique().tolist()) == {-1, 0, 1}
    assert (placed.object_id[0] == direct.object_id[0]).float().mean() > 0.999
    both = placed.mask[0] & direct.mask[0]
    # Float rounding may flip a pixel centre lying on a silhouette edge to the surface behind: a few pixels at most.
    assert ((placed.depth_m[0][both] - direct.depth_m[0][both]).abs() < 0.02).float().mean() > 0.998
    assert (placed.rgb[0][both] - direct.rgb[0][both]).abs().mean() < 1e-3
    assert not placed.mask[1].any(), "an empty per-camera scene draws nothing"


def test_back_face_culling_keeps_closed_meshes_intact():
    """Vehicles are closed and wound counter-clockwise from outside: culling back faces changes nothing visible."""
    meshes = [m.transformed(g.pose_2d(x, y, yaw)) for x, y, yaw in ((7, 1, 0.5), (12, -2, 2.0), (20, 3, -1.2))
              for m in car_meshes()]  # fmt: skip
    both_sides = Rasterizer(W, H).render(meshes, camera_at(), K)
    culled = Rasterizer(W, H, cull_back_faces=True).render(meshes, camera_at(), K)
    assert both_sides.mask.sum() > 3000
    assert (culled.object_id == both_sides.object_id).float().mean() > 0.9995
    same = culled.mask & both_sides.mask
    assert (culled.depth_m[same] - both_sides.depth_m[same]).abs().max() < 1e-4
    # A lone ground plane seen from below disappears: its front side faces up.
    from_below = g.invert(g.se3(g.rot_x(np.pi), [0.0, 0.0, -2.0]) @ g.camera_mount(0.0, 0.0, 0.0))
    assert Rasterizer(W, H).render([ground_plane()], from_below, K).mask.any()
    assert not Rasterizer(W, H, cull_back_faces=True).render([ground_plane()], from_below, K).mask.any()


def test_textured_ground_through_the_camera_matches_opengl(gl_context):
    """Texture coordinates on two ground triangles that pass under and behind the camera (cut at the near plane):
    perspective-correct interpolation must agree with OpenGL's clipper everywhere on screen."""
    s = 40.0
    ground = Mesh(
        np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
        uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32),
        texture_rgb=checker_texture(512, 64),
        material=Material(diffuse_rgb=(1.0, 1.0, 1.0)),
        object_id=1,
    )
    T = camera_at(2.0, 1.0, 0.4, pitch_down_rad=0.3)
    ref = GLRenderer(gl_context, W, H).render([ground], T, K)
    out = Rasterizer(W, H).render([ground], T, K)
    drawn = ref["object_id"] == 1
    assert drawn.mean() > 0.8
    assert ((out.object_id[0].numpy() == 1) == drawn).mean() > 0.999
    same = drawn & (out.object_id[0].numpy() == 1)
    assert np.median(np.abs(out.depth_m[0].numpy()[same] - ref["depth_m"][same])) < 1e-3
    rgb_err = np.abs(out.rgb[0].numpy() - ref["rgb"])[same]
    assert np.median(rgb_err) <= 2e-3
    assert np.percentile(rgb_err, 99) <= 0.05


def test_random_big_triangles_around_the_camera_match_opengl(gl_context):
    """Large triangles in every orientation, many crossing the near plane or passing behind the camera: the cases
    where screen-space tricks go wrong. Coverage must match OpenGL, and depth is finite exactly where drawn."""
    rng = np.random.default_rng(7)
    meshes = [
        Mesh(rng.uniform(-20.0, 20.0, (3, 3)).astype(np.float32), np.array([[0, 1, 2]]), object_id=i) for i in range(40)
    ]
    T = np.eye(4)  # world = camera frame
    ref = GLRenderer(gl_context, W, H).render(meshes, T, K)
    out = Rasterizer(W, H).render(meshes, T, K)
    object_id, depth = out.object_id[0].numpy(), out.depth_m[0].numpy()
    assert np.array_equal(np.isfinite(depth), object_id >= 0) and (depth > 0).all()
    assert (ref["object_id"] >= 0).mean() > 0.5
    assert (object_id == ref["object_id"]).mean() > 0.995
    same = (object_id == ref["object_id"]) & (object_id >= 0)
    assert np.median(np.abs(depth[same] - ref["depth_m"][same])) < 1e-3


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA_ONLY)])
def test_instances_of_a_model_library_match_one_scene_per_camera(device):
    """`render_instances` (the batched views' raster: every camera's triangles gathered from one packed library of
    models) draws what `render` draws with one scene per camera: the same pixels, depths, ids and colours, for a mix
    of two models (one textured) and five cameras."""
    car = pack_meshes(car_meshes(), device)
    sign = pack_meshes([textured_quad(width_m=2.0, height_m=1.5, object_id=3)], device)
    library = [sign, car]
    which = np.array([1, 0, 1, 1, 0])
    poses = np.stack([camera_at(-8.0 - 2 * b, 0.4 * b - 1.0, 0.1 * b) for b in range(5)])
    rast = Rasterizer(W, H, device, use_kernel=False)
    per_camera = rast.render([library[i] for i in which], poses, K)
    gathered = rast.render_instances(library, which, poses, K)
    assert per_camera.mask.reshape(5, -1).any(axis=1).all()
    for name in ("object_id", "depth_m", "rgb", "normal_cam"):
        assert torch.equal(getattr(per_camera, name), getattr(gathered, name)), name


def test_instances_take_each_cameras_own_paint():
    """A repainted car drawn as an instance of its white-painted geometry with the camera's paint (the batched views'
    path) matches the car packed with that paint, to float rounding, camera by camera."""
    from dataclasses import replace

    from drivesim.sim.raster import material_row

    meshes = car_meshes()
    body = 0
    paints = [
        Material(diffuse_rgb=(0.8, 0.1, 0.1), specular_rgb=(0.3, 0.3, 0.3), shininess=30.0),
        Material(diffuse_rgb=(0.1, 0.3, 0.9), specular_rgb=(0.6, 0.6, 0.6), shininess=80.0, metalness=0.5),
    ]
    white = [replace(m, material=replace(m.material, diffuse_rgb=(1.0, 1.0, 1.0))) if k == body else m
             for k, m in enumerate(meshes)]  # fmt: skip
    mask = np.concatenate([np.full(len(m.faces), k == body) for k, m in enumerate(meshes) if len(m.faces)])
    rast = Rasterizer(W, H, use_kernel=False)
    poses = np.stack([camera_at(-9.0, 0.5, 0.2), camera_at(-7.0, -1.0, -0.3)])
    rows = np.stack([np.concatenate([p.diffuse_rgb, material_row(p)]) for p in paints]).astype(np.float32)
    gathered = rast.render_instances([pack_meshes(white)], np.zeros(2, int), poses, K, paint=([mask], rows))
    for b, paint in enumerate(paints):
        painted = [replace(m, material=paint) if k == body else m for k, m in enumerate(meshes)]
        direct = rast.render(pack_meshes(painted), poses[b], K)
        assert torch.equal(direct.object_id[0], gathered.object_id[b])
        assert direct.mask[0].sum() > 2000
        assert (direct.rgb[0] - gathered.rgb[b]).abs().max() < 1e-5
    assert (gathered.rgb[0] - gathered.rgb[1]).abs().amax(-1)[gathered.mask[0]].mean() > 0.1, "two paints"


def test_gray_composite_matches_opencvs_rgb2gray_on_every_colour() -> None:
    """A gray camera's car is composited in gray in the same pass: its luma must be cv2.cvtColor's RGB2GRAY to the
    grey level, checked on all 2^24 8-bit colours (a row of 65536 car pixels per red level)."""
    green_blue = np.arange(65536)
    for red in range(256):
        colours = np.stack([np.full(65536, red), green_blue >> 8, green_blue & 255], axis=-1).astype(np.uint8)[None]
        view = np.zeros_like(colours)
        front = np.zeros((1, 65536), dtype=bool)
        car_rgb = colours.astype(np.float32) / np.float32(255.0)
        raster_kernel.composite_uint8(
            view, np.full((1, 65536), np.inf, np.float32), car_rgb, np.ones((1, 65536), np.float32), front, True
        )
        expected = cv2.cvtColor(colours, cv2.COLOR_RGB2GRAY)
        assert front.all()
        np.testing.assert_array_equal(view, np.repeat(expected[..., None], 3, axis=-1), err_msg=f"red {red}")
