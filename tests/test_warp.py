"""Forward warp (view synthesis, paper eq. 2) against frames rendered directly from the destination pose."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gl_reference import car_meshes, checker_texture

from drivesim.sim import geometry as g
from drivesim.sim import warp as warp_module
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.raster import Lighting, Rasterizer, composite, roi_intrinsics
from drivesim.sim.warp import forward_warp

H, W = 200, 320
K = g.intrinsics_from_hfov(W, H, np.deg2rad(70.0))
T_VEHICLE_CAMERA = g.camera_mount(0.0, 0.0, 1.5, pitch_down_rad=0.05)
FLAT = Lighting(ambient_rgb=np.ones(3), light_rgb=np.zeros(3))  # pure albedo: view-independent colours


def textured_quad_world(corners_m: np.ndarray, texture: np.ndarray, object_id: int) -> Mesh:
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    return Mesh(
        corners_m.astype(np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
        uv=uv,
        texture_rgb=texture,
        material=Material(diffuse_rgb=(1.0, 1.0, 1.0)),
        object_id=object_id,
    )


def plane_world() -> list[Mesh]:
    """Textured ground (60 m square) and a textured wall 25 m ahead."""
    ground = textured_quad_world(
        np.array([[-5, 30, 0], [55, 30, 0], [55, -30, 0], [-5, -30, 0]]), checker_texture(512, 48), object_id=1
    )
    wall = textured_quad_world(
        np.array([[25, 12, 8], [25, -12, 8], [25, -12, 0], [25, 12, 0]]), checker_texture(256, 16), object_id=2
    )
    return [ground, wall]


def render_from(vehicle_pose: np.ndarray, meshes: list[Mesh]) -> tuple[torch.Tensor, torch.Tensor]:
    T_camera_world = g.invert(vehicle_pose @ T_VEHICLE_CAMERA)
    out = Rasterizer(W, H).render(meshes, T_camera_world, K, lighting=FLAT)
    return out.rgb, out.depth_m


def seen_by_source(depth_dst: torch.Tensor, T_src_dst: np.ndarray) -> torch.Tensor:
    """(H, W) bool: destination pixels whose surface point projects inside the source image (1 px margin)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = depth_dst.numpy().astype(np.float64)
    finite = np.isfinite(z)
    z = np.where(finite, z, 1.0)
    p_dst = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    p_src = p_dst @ T_src_dst[:3, :3].T + T_src_dst[:3, 3]
    us = K[0, 0] * p_src[..., 0] / p_src[..., 2] + K[0, 2]
    vs = K[1, 1] * p_src[..., 1] / p_src[..., 2] + K[1, 2]
    inside = (us >= 1) & (us <= W - 2) & (vs >= 1) & (vs <= H - 2) & (p_src[..., 2] > 0)
    return torch.as_tensor(finite & inside)


def psnr_db(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(1.0 / ((a - b) ** 2).mean()))


def test_identity_warp_reproduces_the_frame():
    rng = np.random.default_rng(0)
    rgb = torch.as_tensor(rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8))
    depth = torch.as_tensor(rng.uniform(1.0, 50.0, (2, H, W)).astype(np.float32))
    depth[:, :40] = torch.inf  # sky
    out = forward_warp(rgb, depth, K, np.eye(4), K, W, H)
    assert out.rgb.dtype == torch.uint8
    assert torch.equal(out.rgb, rgb)
    assert torch.equal(out.depth_m, depth)
    assert out.valid.all()


def test_lateral_shift_matches_direct_render():
    """Warp a rendered frame to a camera 0.5 m to the side, turned 3 degrees: it must match rendering there."""
    meshes = plane_world()
    src_pose = g.pose_2d(0.0, 0.0, 0.0)
    dst_pose = g.pose_2d(0.3, 0.5, np.deg2rad(3.0))
    rgb_src, depth_src = render_from(src_pose, meshes)
    rgb_dst, depth_dst = render_from(dst_pose, meshes)
    T_dst_src = g.invert(dst_pose @ T_VEHICLE_CAMERA) @ (src_pose @ T_VEHICLE_CAMERA)
    out = forward_warp(rgb_src, depth_src, K, T_dst_src, K, W, H)

    seen = seen_by_source(depth_dst[0], g.invert(T_dst_src))
    assert seen.sum() > 0.6 * H * W
    assert out.valid[0][seen].float().mean() > 0.995, "warp left holes where the source saw the surface"
    both = out.valid & torch.isfinite(depth_dst)
    rel_depth_err = ((out.depth_m - depth_dst).abs() / depth_dst)[both]
    assert rel_depth_err.median() < 0.005
    # Nearest-pixel splatting of a sharp checkerboard: ~21 dB; a wrong transform gives ~10 dB (the unwarped frame).
    warped_psnr = psnr_db(out.rgb[both], rgb_dst[both])
    assert warped_psnr > 19.0
    assert psnr_db(rgb_src[both], rgb_dst[both]) < warped_psnr - 8.0


@pytest.mark.parametrize("roi", [(96, 80, 160, 64), (0, 0, 50, 30), (300, 180, 20, 20), (0, 0, W, H)])
def test_region_of_interest_is_the_crop_of_the_full_warp(roi):
    meshes = plane_world()
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), meshes)
    T_dst_src = g.se3(g.rot_y(0.02), [0.4, 0.05, -0.6])  # forward and sideways: cracks to fill
    full = forward_warp(rgb_src, depth_src, K, T_dst_src, K, W, H)
    part = forward_warp(rgb_src, depth_src, K, T_dst_src, K, W, H, roi=roi)
    x0, y0, w, h = roi
    assert part.rgb.shape == (1, h, w, 3)
    assert torch.equal(part.rgb, full.rgb[:, y0 : y0 + h, x0 : x0 + w])
    assert torch.equal(part.depth_m, full.depth_m[:, y0 : y0 + h, x0 : x0 + w])
    assert torch.equal(part.valid, full.valid[:, y0 : y0 + h, x0 : x0 + w])


def test_roi_at_another_resolution():
    """The policy's camera: half resolution, its own K. Matches the half-resolution direct render."""
    meshes = plane_world()
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), meshes)
    K_half = g.scale_intrinsics(K, 0.5, 0.5)
    out = forward_warp(rgb_src, depth_src, K, np.eye(4), K_half, W // 2, H // 2, roi=(40, 50, 80, 32))
    direct = Rasterizer(W // 2, H // 2).render(meshes, g.invert(T_VEHICLE_CAMERA), K_half, lighting=FLAT)
    crop_depth = direct.depth_m[:, 50:82, 40:120]
    assert out.valid.all()
    # Several source pixels land in each destination pixel and the z-buffer keeps the nearest: on the tilted ground
    # that is up to one source row closer, hence a small bias.
    assert ((out.depth_m - crop_depth).abs() / crop_depth).median() < 0.02


def test_sky_is_warped_at_infinity():
    """Points at infinity ignore translation and follow rotation: no hole in the sky."""
    rgb = torch.rand(1, H, W, 3)
    depth = torch.full((1, H, W), torch.inf)
    moved = forward_warp(rgb, depth, K, g.se3(np.eye(3), [2.0, 0.5, 5.0]), K, W, H)
    assert moved.valid.all() and torch.equal(moved.rgb, rgb)
    R = g.rot_y(np.deg2rad(5.0))
    turned = forward_warp(rgb, depth, K, g.se3(R, [0.0, 0.0, 0.0]), K, W, H)
    # Where each destination pixel's ray came from: the homography K R^T K^-1.
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    src = np.stack([u, v, np.ones_like(u)], -1) @ (K @ R.T @ np.linalg.inv(K)).T
    us, vs = src[..., 0] / src[..., 2], src[..., 1] / src[..., 2]
    inside = torch.as_tensor((us >= 1) & (us <= W - 2) & (vs >= 1) & (vs <= H - 2))
    outside = torch.as_tensor((us < -1) | (us > W) | (vs < -1) | (vs > H))
    assert outside.sum() > 2000, "the test rotation should uncover new sky"
    assert turned.valid[0][inside].all() and not turned.valid[0][outside].any()
    assert torch.isinf(turned.depth_m).all()


def test_cracks_filled_disocclusions_kept():
    """Moving towards a wall magnifies it: 1 px cracks appear and are filled. A pole in front of the wall leaves a
    wide disocclusion behind it when the camera moves sideways, which must stay empty."""
    depth = torch.full((1, H, W), 10.0)
    depth[:, :, 150:170] = 3.0  # the pole, 20 px wide
    rgb = torch.rand(1, H, W, 3)
    closer = g.se3(np.eye(3), [0.0, 0.0, -1.0])  # 10 % magnification of the wall
    unfilled = forward_warp(rgb, depth, K, closer, K, W, H, fill_holes=False)
    filled = forward_warp(rgb, depth, K, closer, K, W, H)
    centre = (slice(None), slice(60, 140), slice(20, 120))
    assert (~unfilled.valid[centre]).float().mean() > 0.05
    assert filled.valid[centre].all()

    sideways = g.se3(np.eye(3), [-0.3, 0.0, 0.0])  # the pole moves ~ 22 px more than the wall behind it
    out = forward_warp(rgb, depth, K, sideways, K, W, H)
    empty_cols = (~out.valid[0, 50:150]).all(0).nonzero().squeeze(1)
    assert len(empty_cols) >= 10, "the disocclusion behind the pole was filled in"


def test_batch_matches_single():
    rng = np.random.default_rng(1)
    rgb = torch.as_tensor(rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8))
    depth = torch.as_tensor(rng.uniform(2.0, 30.0, (2, H, W)).astype(np.float32))
    T = np.stack([g.se3(g.rot_y(0.03), [0.2, 0.0, 0.3]), g.se3(g.rot_y(-0.05), [-0.4, 0.1, 1.0])])
    both = forward_warp(rgb, depth, K, T, K, W, H, roi=(40, 60, 200, 80))
    for b in range(2):
        one = forward_warp(rgb[b : b + 1], depth[b : b + 1], K, T[b], K, W, H, roi=(40, 60, 200, 80))
        assert torch.equal(both.rgb[b], one.rgb[0]) and torch.equal(both.depth_m[b], one.depth_m[0])


@pytest.mark.parametrize(
    "T_dst_src",
    [
        g.se3(g.rot_y(0.03), [0.3, 0.0, -1.0]),
        g.se3(g.rot_y(-0.2) @ g.rot_x(0.05), [-0.8, 0.1, 0.5]),
        g.se3(g.rot_y(0.1), [0.0, 0.0, 2.5]),  # backwards: a wider window
        g.se3(g.rot_y(0.1), [0.0, 0.0, -3.0]),  # 3 m forward, past the nearest point: no bound, all pixels warped
    ],
)
def test_source_window_only_skips_pixels_that_cannot_land(T_dst_src, monkeypatch):
    """For a region of interest only a rectangle of the source is transformed; it must not lose any pixel."""
    meshes = plane_world()
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), meshes)
    roi = (80, 100, 160, 64)
    windowed = forward_warp(rgb_src, depth_src, K, T_dst_src, K, W, H, roi=roi)
    monkeypatch.setattr(warp_module, "_source_window", lambda *args: None)
    everything = forward_warp(rgb_src, depth_src, K, T_dst_src, K, W, H, roi=roi)
    assert everything.valid.float().mean() > 0.5
    assert torch.equal(windowed.rgb, everything.rgb)
    assert torch.equal(windowed.depth_m, everything.depth_m)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
@pytest.mark.parametrize(
    ("T_dst_src", "roi"),
    [
        (g.se3(g.rot_y(0.03), [0.3, 0.0, -1.0]), (80, 100, 160, 64)),
        (g.se3(g.rot_y(-0.2) @ g.rot_x(0.05), [-0.8, 0.1, 0.5]), None),
        (g.se3(g.rot_y(0.1), [0.0, 0.0, -3.0]), (0, 60, 320, 128)),
    ],
)
def test_cpu_kernel_matches_the_torch_path(T_dst_src, roi, dtype):
    """The compiled CPU kernel and the torch path (the one a GPU runs) give the same view: the same pixels, depths and
    colours, up to float rounding at pixel borders."""
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), plane_world())
    depth_src[:, :30] = torch.inf  # a band of sky (points at infinity)
    rgb = (rgb_src * 255).to(torch.uint8) if dtype == torch.uint8 else rgb_src
    kernel = forward_warp(rgb, depth_src, K, T_dst_src, K, W, H, roi=roi)
    reference = forward_warp(rgb, depth_src, K, T_dst_src, K, W, H, roi=roi, use_kernel=False)
    assert kernel.rgb.dtype == reference.rgb.dtype == dtype
    assert reference.valid.float().mean() > 0.5
    assert (kernel.valid == reference.valid).float().mean() > 0.999
    same = (kernel.rgb == reference.rgb).all(-1) & kernel.valid & reference.valid
    assert same.float().sum() > 0.99 * reference.valid.float().sum()
    both = kernel.valid & reference.valid & torch.isfinite(reference.depth_m)
    assert (kernel.depth_m[both] - reference.depth_m[both]).abs().max() < 1e-3
    assert torch.equal(torch.isinf(kernel.depth_m) & kernel.valid, torch.isinf(reference.depth_m) & reference.valid)


@pytest.mark.parametrize("bands", [2, 3, 7])
@pytest.mark.parametrize(
    ("T_dst_src", "rendered", "roi"),
    [
        (g.se3(g.rot_y(0.03), [0.6, 0.0, -1.5]), (0, 0, W, H), (0, 0, W, H)),  # the whole image, cracks
        (g.se3(g.rot_y(-0.2) @ g.rot_x(0.05), [-0.8, 0.1, 0.5]), (78, 98, 164, 68), (80, 100, 160, 64)),
    ],
)
def test_a_warp_cut_into_bands_gives_the_same_pixels(T_dst_src, rendered, roi, bands):
    """`KernelWarp(bands=n)` (the view cut into n bands warped at once in numba's threads, `render_threads`) gives
    exactly the pixels, depths and validity of the one warp, also where the crack filling reads across a cut."""
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), plane_world())
    depth_src[:, :30] = torch.inf
    rgb = (rgb_src * 255).to(torch.uint8).numpy()
    depth = depth_src.numpy()
    min_depth = float(depth[np.isfinite(depth)].min())
    partial = rendered[2:] != (W, H)
    one = warp_module.KernelWarp(K, (H, W), K, rendered, roi, fill_holes=True, partial=partial)(
        rgb, depth, min_depth, T_dst_src
    )
    cut = warp_module.KernelWarp(K, (H, W), K, rendered, roi, fill_holes=True, partial=partial, bands=bands)(
        rgb, depth, min_depth, T_dst_src
    )
    assert 0.02 < 1.0 - one[2].mean() < 0.6  # empty pixels before filling: there were cracks and holes to fill
    for whole, banded in zip(one, cut, strict=True):
        np.testing.assert_array_equal(banded, whole)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), plane_world())
    T = g.se3(g.rot_y(0.03), [0.3, 0.0, -1.0])
    cpu = forward_warp(rgb_src, depth_src, K, T, K, W, H, roi=(80, 100, 160, 64))
    gpu = forward_warp(rgb_src.cuda(), depth_src.cuda(), K, T, K, W, H, roi=(80, 100, 160, 64))
    assert (cpu.valid == gpu.valid.cpu()).float().mean() > 0.999
    both = cpu.valid & gpu.valid.cpu()
    assert (cpu.depth_m[both] - gpu.depth_m.cpu()[both]).abs().max() < 1e-3


def test_roi_outside_the_image_is_an_error():
    rgb = torch.zeros(1, H, W, 3, dtype=torch.uint8)
    depth = torch.ones(1, H, W)
    with pytest.raises(ValueError, match="roi"):
        forward_warp(rgb, depth, K, np.eye(4), K, W, H, roi=(300, 0, 64, 32))


def test_source_cache_never_serves_a_stale_frame():
    """Frames reuse memory (a freed array's address comes back, a buffer is refilled): results must follow content."""
    rng = np.random.default_rng(3)
    T = g.se3(g.rot_y(0.02), [0.2, 0.0, -0.5])
    buffer = torch.zeros(1, H, W, 3, dtype=torch.uint8)
    depth = torch.full((1, H, W), 8.0)
    for _ in range(3):
        frame = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        fresh = forward_warp(torch.from_numpy(frame.copy())[None], depth.clone(), K, T, K, W, H, roi=(96, 80, 128, 64))
        buffer.copy_(torch.from_numpy(frame)[None])  # in place: bumps the version counter
        reused = forward_warp(buffer, depth, K, T, K, W, H, roi=(96, 80, 128, 64))
        assert torch.equal(fresh.rgb, reused.rgb)


def test_vehicle_composited_into_warped_roi_with_occlusion():
    """The step of DESIGN §4.4: warp the frame into the policy's ROI, rasterize vehicles at the same ROI, composite
    by depth. A car before the wall covers it; a car behind the wall stays hidden."""
    meshes = plane_world()
    rgb_src, depth_src = render_from(g.pose_2d(0.0, 0.0, 0.0), meshes)
    rgb_u8 = (rgb_src * 255).to(torch.uint8)
    roi = (60, 60, 200, 80)
    view = forward_warp(rgb_u8, depth_src, K, np.eye(4), K, W, H, roi=roi)
    T_camera_world = g.invert(T_VEHICLE_CAMERA)
    K_roi = roi_intrinsics(K, roi)
    rast = Rasterizer(roi[2], roi[3])
    full = Rasterizer(W, H)
    # Hidden: the car 35 m ahead, its near end well over OCCLUDER_MIN_GAP behind the wall at 25 m.
    for x_m, visible in ((12.0, True), (35.0, False)):
        car = [m.transformed(g.pose_2d(x_m, 0.0, 0.3)) for m in car_meshes(object_id=7)]
        cars = rast.render(car, T_camera_world, K_roi)
        crop = full.render(car, T_camera_world, K).object_id[:, 60:140, 60:260]
        assert (cars.object_id == crop).float().mean() > 0.999  # the ROI render is the crop of the full render
        rgb, depth, front = composite(view.rgb, view.depth_m, cars)
        assert rgb.dtype == torch.uint8
        if visible:
            assert front.sum() > 500 and torch.equal(front, cars.mask)
            assert torch.equal(depth[front], cars.depth_m[front])
            assert torch.equal(rgb[~front], view.rgb[~front])
        else:
            assert cars.mask.sum() > 50 and not front.any()  # drawn by the rasterizer, hidden by the wall
            assert torch.equal(rgb, view.rgb)


def test_source_index_warps_each_view_from_its_frame():
    """With source_index, N frames serve B views (frame of view b = source_index[b]): the same pixels as warping each
    view's frame by itself, on the torch path and the compiled one."""
    rng = np.random.default_rng(2)
    rgb = torch.as_tensor(rng.integers(0, 256, (3, H, W, 3), dtype=np.uint8))
    depth = torch.as_tensor(rng.uniform(2.0, 30.0, (3, H, W)).astype(np.float32))
    frame_of_view = np.array([2, 0, 2, 1])
    T = np.stack([g.se3(g.rot_y(0.02 * b), [0.1 * b, 0.0, 0.2]) for b in range(4)])
    for use_kernel in (False, True):
        out = forward_warp(rgb, depth, K, T, K, W, H, roi=(40, 60, 200, 80), source_index=frame_of_view,
                           use_kernel=use_kernel)  # fmt: skip
        for b, f in enumerate(frame_of_view):
            one = forward_warp(rgb[f : f + 1], depth[f : f + 1], K, T[b], K, W, H, roi=(40, 60, 200, 80),
                               use_kernel=use_kernel)  # fmt: skip
            assert torch.equal(out.rgb[b], one.rgb[0]) and torch.equal(out.depth_m[b], one.depth_m[0])
