"""Issue 20 in the policy's view: holes filled from neighbouring frames and inpainted, a contact shadow under inserted
cars, and inserted cars drawn in gray on a gray camera.

The world here is a ground plane with a texture fixed to the ground (so any pose's true view is known) and a sky,
recorded by a camera driving straight along +x, one frame a metre."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sim_worlds import straight_path

from drivesim.sim.fill import fill_wedges_from_neighbours, hole_box, inpaint_holes, side_wedges, widen_frame
from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, invert, pose_2d
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer, frames_are_monochrome
from drivesim.sim.world import World

W_PX, H_PX = 160, 100
CAMERA_HEIGHT_M = 1.6
SKY_M = 80.0
SKY_RGB = (90, 140, 200)
SMALL = {"roi_px": (0, 40, 160, 60), "out_width_px": 80, "out_height_px": 30}
K = intrinsics_from_hfov(W_PX, H_PX, np.deg2rad(70.0))
T_VC = camera_mount(0.0, 0.0, CAMERA_HEIGHT_M)


def ground_rgb(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """The ground's colour at world (x, y): smooth stripes along and across the road, different per channel."""
    r = 120 + 60 * np.sin(x_m / 0.9)
    g = 110 + 50 * np.cos(y_m / 0.6)
    b = 100 + 40 * np.sin((x_m + y_m) / 1.3)
    return np.stack([r, g, b], axis=-1)


def true_view(T_world_camera: np.ndarray, Kv: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """What a camera at T_world_camera with intrinsics Kv sees: (rgb (h, w, 3) uint8, depth (h, w) float32)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - Kv[0, 2]) / Kv[0, 0], (v - Kv[1, 2]) / Kv[1, 1], np.ones_like(u)], axis=-1)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    down = rays @ R.T  # world direction of each ray (z = 1 along the optical axis)
    with np.errstate(divide="ignore"):
        z = np.where(down[..., 2] < -1e-6, -t[2] / down[..., 2], np.inf)
    ground = (z < SKY_M) & np.isfinite(z)
    points = t + down * np.where(ground, z, 0.0)[..., None]
    rgb = np.where(ground[..., None], ground_rgb(points[..., 0], points[..., 1]), SKY_RGB)
    depth = np.where(ground, z, SKY_M).astype(np.float32)
    return np.clip(rgb + 0.5, 0, 255).astype(np.uint8), depth


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0**2 / np.mean((a.astype(float) - b.astype(float)) ** 2)))


def make_world(tmp: Path, n: int = 8, gray: bool = False) -> World:
    x = np.arange(n, dtype=np.float64)
    T_wv = np.stack([pose_2d(xi, 0.0, 0.0) for xi in x])
    views = [true_view(T @ T_VC, K, W_PX, H_PX) for T in T_wv]
    frames = np.stack([v[0] for v in views])
    if gray:
        frames = np.repeat(frames.mean(axis=-1, keepdims=True).astype(np.uint8), 3, axis=-1)
    path = straight_path(x, T_wv, T_VC, 100_000_000)
    return World(
        root=tmp, frames=frames, depth_m=np.stack([v[1] for v in views]), K=K, T_vehicle_camera=T_VC, width_px=W_PX,
        height_px=H_PX, camera_height_m=CAMERA_HEIGHT_M, path=path, road_width_m=8.0, lane_width_m=3.5,
        info={"format": 1},
    )  # fmt: skip


@dataclass
class BoxModel:
    """Stands in for a vehicle_library.VehicleModel: one box with a red body."""

    length_m: float = 4.0
    width_m: float = 1.8
    height_m: float = 1.5

    @property
    def full(self) -> list[Mesh]:
        L, Wd, H = self.length_m, self.width_m, self.height_m
        v = np.array([[x, y, z] for x in (-L / 2, L / 2) for y in (-Wd / 2, Wd / 2) for z in (0.0, H)], np.float32)
        faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]]
        faces += [[2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
        material = Material(diffuse_rgb=(0.8, 0.1, 0.1), specular_rgb=(0.0, 0.0, 0.0))
        return [Mesh(v, np.array(faces, dtype=np.int64), material=material)]

    light = full


def render(vs: ViewSynthesizer, frame: int, lateral_m: float, yaw_rad: float = 0.0, cars=()):
    return vs.render(np.array([frame]), np.array([float(frame)]), np.array([lateral_m]), np.array([yaw_rad]),
                     [list(cars)])  # fmt: skip


def test_neighbour_frames_fill_the_side_wedge_with_what_is_really_there(tmp_path):
    """2 m to the left of frame 4, the frame alone leaves a wedge on the left; the frames behind it saw most of that
    ground, and what they put there is the true ground (as close to it as the frame's own pixels are, while a wrong
    pose would put the stripes elsewhere); inpainting leaves no black pixel."""
    world = make_world(tmp_path)
    alone = ViewSynthesizer(world, ViewConfig(**SMALL, fill_frames=(), inpaint=False, source_margin=0.0))
    merged = ViewSynthesizer(world, ViewConfig(**SMALL, fill_frames=(-1, -2, 1), inpaint=False, source_margin=0.0))
    full = ViewSynthesizer(world, ViewConfig(**SMALL, source_margin=0.0))
    out_alone, out_merged, out_full = (render(vs, 4, 2.0) for vs in (alone, merged, full))
    hole = out_alone.rgb[0].max(axis=-1) == 0
    assert hole.mean() > 0.05, "the test needs a wedge"
    assert hole[:, :10].mean() > 3 * hole[:, -10:].mean(), "the wedge is on the left"
    stats = merged.fill_stats.fractions()
    assert stats["neighbour"] > 0.6 * hole.mean()
    assert stats["unfilled"] < 0.4 * hole.mean()
    truth, _ = true_view(pose_2d(4.0, 2.0, 0.0) @ T_VC, alone.K_view, 80, 30)
    filled = hole & (out_merged.rgb[0].max(axis=-1) > 0)
    own_db = psnr_db(out_alone.rgb[0][~hole], truth[~hole])  # nearest-pixel splats of a fine texture: ~23 dB
    assert psnr_db(out_merged.rgb[0][filled], truth[filled]) > max(own_db - 1.0, 20.0)
    assert full.fill_stats.fractions()["unfilled"] == 0.0
    assert (out_full.rgb[0].max(axis=-1) > 0).all()
    # Pixels the frame itself filled are the same whatever fills the holes.
    assert np.array_equal(out_full.rgb[0][~hole], out_alone.rgb[0][~hole])


def test_widened_frame_keeps_the_frame_and_shows_what_the_frames_behind_saw_beside_it(tmp_path):
    """Frame 4 widened by 40 px on each side from frames 3 and 2: the middle is the frame itself, the intrinsics move
    by the margin, and the margins hold the true ground beside the frame's view (a wrong pose would shift the
    stripes); a later neighbour fills only what the earlier ones left, even with nearer surfaces."""
    world = make_world(tmp_path)
    T_wc = world.path["T_world_camera"]
    neighbours = [(world.frames[j], world.depth_m[j], invert(T_wc[4]) @ T_wc[j]) for j in (3, 2)]
    wide = widen_frame(world.frames[4], world.depth_m[4], K, 40, neighbours)
    assert wide.rgb.shape == (H_PX, W_PX + 80, 3)
    assert np.array_equal(wide.rgb[:, 40:-40], world.frames[4])
    assert np.array_equal(wide.depth_m[:, 40:-40], world.depth_m[4])
    assert wide.K[0, 2] == pytest.approx(K[0, 2] + 40)
    truth, truth_depth = true_view(T_wc[4], wide.K, W_PX + 80, H_PX)
    margins = np.zeros((H_PX, W_PX + 80), dtype=bool)
    margins[:, :40] = margins[:, -40:] = True
    filled = margins & (wide.depth_m > 0)
    ground = filled & (wide.depth_m < SKY_M - 1)
    assert wide.neighbour_px == int(filled.sum())
    assert ground.sum() > 0.5 * (margins & (truth_depth < SKY_M)).sum()
    assert psnr_db(wide.rgb[ground], truth[ground]) > 20.0
    white = np.full_like(world.frames[3], 255)
    nearer_white = [neighbours[0], (white, world.depth_m[3] * 0.5, neighbours[0][2])]
    first_wins = widen_frame(world.frames[4], world.depth_m[4], K, 40, nearer_white)
    first_only = widen_frame(world.frames[4], world.depth_m[4], K, 40, neighbours[:1])
    taken = first_only.depth_m > 0
    assert np.array_equal(first_wins.rgb[taken], first_only.rgb[taken])


def test_margins_fill_the_side_wedge_with_what_is_really_there(tmp_path):
    """2 m to the left of frame 4, frames widened from their neighbours (the default) leave a fraction of the wedge
    the frame alone leaves, and show the true ground in it; the rest of the view is unchanged."""
    world = make_world(tmp_path)
    narrow = ViewSynthesizer(world, ViewConfig(**SMALL, inpaint=False, source_margin=0.0))
    wide = ViewSynthesizer(world, ViewConfig(**SMALL, inpaint=False))
    out_narrow, out_wide = render(narrow, 4, 2.0).rgb[0], render(wide, 4, 2.0).rgb[0]
    hole_narrow, hole_wide = out_narrow.max(axis=-1) == 0, out_wide.max(axis=-1) == 0
    assert hole_narrow.mean() > 0.05, "the test needs a wedge"
    assert hole_wide.mean() < 0.25 * hole_narrow.mean()
    assert wide.fill_stats.fractions()["unfilled"] == pytest.approx(hole_wide.mean(), abs=1e-6)
    truth, _ = true_view(pose_2d(4.0, 2.0, 0.0) @ T_VC, wide.K_view, 80, 30)
    filled = hole_narrow & ~hole_wide
    own_db = psnr_db(out_narrow[~hole_narrow], truth[~hole_narrow])
    assert psnr_db(out_wide[filled], truth[filled]) > max(own_db - 1.0, 20.0)
    same = np.all(out_wide == out_narrow, axis=-1)[~hole_narrow]
    assert same.mean() > 0.98


def test_side_wedges_are_the_holes_at_the_image_sides_and_not_the_disocclusions():
    """A triangle of holes in the top-left corner (a left and a top wedge), a right wedge, and a hole in the middle (a
    disocclusion): the wedges' boxes, none for the middle hole; a wedge smaller than the minimum is left out; a row
    with no seen pixel is in the left and the right wedge, but not in the top one when seen rows are above it."""
    valid = np.ones((20, 50), bool)
    for row in range(10):
        valid[row, : 10 - row] = False  # 10 px wide at the top, 1 px at row 9
    valid[5:15, 45:] = False  # right wedge
    valid[8:12, 20:24] = False  # disocclusion
    valid[19, 30:33] = False  # a 3-px bottom wedge
    assert side_wedges(valid) == [(0, 0, 10, 10), (45, 5, 5, 10), (0, 0, 10, 10)]
    assert side_wedges(valid, min_px=51) == [(0, 0, 10, 10), (0, 0, 10, 10)], "the right wedge has 50 px"
    assert side_wedges(valid, min_px=3)[-1] == (30, 19, 3, 1)
    valid[:, 45:] = True
    valid[3, :] = False
    assert side_wedges(valid) == [(0, 0, 50, 10), (0, 3, 50, 1), (0, 0, 10, 10)]


def test_neighbours_fill_only_the_wedges_nearest_surface_first():
    """The neighbour warps are asked for the wedge's box only (never for the disocclusion's); where two neighbours
    both see a wedge pixel, the nearer surface wins; a neighbour that adds nothing ends the search, and what it gave
    up on is not searched again for the top and bottom wedges the same columns make."""
    rgb = np.zeros((10, 30, 3), np.uint8)
    depth = np.full((10, 30), np.inf, np.float32)
    valid = np.ones((10, 30), bool)
    valid[:, 24:] = False  # right wedge, 6 px wide
    valid[4:6, 10:12] = False  # disocclusion
    asked = []

    def warp(offset, box):
        asked.append((offset, box))
        x0, y0, w, h = box
        if offset == 3:
            return None  # no such frame
        shade = {-1: 50, 1: 100, -2: 150, 2: 200}[offset]
        columns = np.arange(x0, x0 + w)[None, :]
        rows = np.arange(y0, y0 + h)[:, None]
        # -1 sees columns 24-25 of rows 0-4 at 9 m; +1 sees columns 24-27 of every row at 11 m; -2 sees nothing,
        # 2 everything (it is never asked: -2 ended the search).
        seen = {-1: (columns < 26) & (rows < 5), 1: (columns < 28) & (rows >= 0), -2: columns < 0, 2: columns >= 0}
        other_valid = seen[offset]
        return np.full((h, w, 3), shade, np.uint8), np.full((h, w), 10.0 + offset, np.float32), other_valid

    filled, count = fill_wedges_from_neighbours(rgb, depth, valid, (3, -1, 1, -2, 2), warp)
    assert [box for _, box in asked] == [(24, 0, 6, 10)] * 3 + [(28, 0, 2, 10)]
    assert count == 40 and filled.sum() == 40 and not filled[4:6, 10:12].any()
    assert (rgb[:5, 24:26] == 50).all(), "frame -1 is nearer (9 m) than frame +1 (11 m) where both see"
    assert (rgb[5:, 24:26] == 100).all() and (depth[5:, 24:26] == 11.0).all()
    assert (rgb[:, 26:28] == 100).all() and (rgb[:, 28:] == 0).all()


def test_inpainting_continues_the_border_colours():
    """A hole in a smooth gradient is inpainted close to the gradient, a speck and a large hole alike."""
    u = np.linspace(0, 200, 80)
    image = np.repeat(np.stack([u, 200 - u, np.full_like(u, 100)], -1)[None], 30, axis=0).astype(np.uint8)
    for hole_cols in (slice(38, 42), slice(20, 60)):  # 120 px, 1200 px
        hole = np.zeros((30, 80), bool)
        hole[5:25, hole_cols] = True
        damaged = np.where(hole[..., None], 0, image).astype(np.uint8)
        assert inpaint_holes(damaged, hole) == hole.sum()
        assert np.abs(damaged[hole].astype(int) - image[hole]).mean() < 12
    assert hole_box(~hole) == (20, 5, 40, 20)


def test_contact_shadow_darkens_the_ground_beside_the_car_only(tmp_path):
    """The ground just beside an inserted car is darker than without the shadow; 2 m away it is unchanged."""
    world = make_world(tmp_path)
    # 10 m ahead: near enough that the shadow's 0.5 m beyond the car's rear covers a row of the 80 x 30 view
    car = [CarPlacement(BoxModel(), 10.0, 0.0, 0.0)]
    flags = {**SMALL, "harmonization": False}
    with_shadow = render(ViewSynthesizer(world, ViewConfig(**flags)), 2, 0.0, cars=car)
    without = render(ViewSynthesizer(world, ViewConfig(**flags, contact_shadow=0.0)), 2, 0.0, cars=car)
    mask = with_shadow.car_mask[0]
    assert np.array_equal(mask, without.car_mask[0]) and mask.any()
    rows, cols = np.nonzero(mask)
    below = slice(rows.max() + 1, min(rows.max() + 3, 30))  # the ground in front of the car's rear
    centre = slice(cols.min() + 2, cols.max() - 1)
    darker = without.rgb[0][below, centre].astype(float).mean() - with_shadow.rgb[0][below, centre].mean()
    assert darker > 15
    far_left = slice(0, max(cols.min() - 12, 1))
    assert np.array_equal(with_shadow.rgb[0][:, far_left], without.rgb[0][:, far_left])


@pytest.mark.parametrize("gray", [False, True])
def test_car_on_a_gray_camera_is_gray(tmp_path, gray):
    """A red car inserted into a gray camera's view is drawn gray (R = G = B, lit and harmonized); into a colour
    camera's view it stays red. Whether the camera is gray is read from the frames."""
    world = make_world(tmp_path, gray=gray)
    vs = ViewSynthesizer(world, ViewConfig(**SMALL))
    assert vs.monochrome is gray and frames_are_monochrome(world.frames) is gray
    out = render(vs, 2, 0.0, cars=[CarPlacement(BoxModel(), 10.0, 0.0, 0.0)])
    car = out.rgb[0][out.car_mask[0]].astype(int)
    assert len(car) > 50
    spread = (car.max(axis=-1) - car.min(axis=-1)).max()
    if gray:
        assert spread == 0
        assert (out.rgb[0].max(axis=-1) == out.rgb[0].min(axis=-1)).all(), "the whole view stays gray"
    else:
        assert (car[:, 0] - car[:, 1]).mean() > 30


def test_the_cpu_inpainting_is_the_gpu_paths_pull_push():
    """`inpaint_holes` (one view, compiled) fills like `pull_push_fill` (torch, a batch) up to a grey level, for
    sizes that halve evenly and not, specks and wedges, and leaves seen pixels and all-hole views as they are."""
    import torch

    from drivesim.sim.fill import pull_push_fill

    rng = np.random.default_rng(0)
    for h, w, share in ((64, 160, 0.02), (33, 77, 0.3), (30, 80, 0.9), (5, 7, 0.5)):
        image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        hole = rng.random((h, w)) < share
        hole[:, : w // 4] = True
        ours = image.copy()
        assert inpaint_holes(ours, hole) == hole.sum()
        torch_fill = pull_push_fill(torch.from_numpy(image[None].copy()), torch.from_numpy(~hole[None])).numpy()[0]
        assert np.array_equal(ours[~hole], image[~hole])
        assert np.abs(ours.astype(int) - torch_fill).max() <= 1
        assert (np.abs(ours.astype(int) - torch_fill) > 0).mean() < 0.001
    everything = np.ones((4, 6), bool)
    black = np.zeros((4, 6, 3), np.uint8)
    assert inpaint_holes(black, everything) == 24 and not black.any()


@pytest.mark.parametrize("threads", [2, 3])
def test_inpainting_on_several_threads_gives_the_same_pixels(threads):
    """`inpaint_holes` with its rows shared among threads (`render_threads`) fills every hole pixel as one thread
    does, to the grey level: specks, a side wedge and scattered holes in a textured view of odd size."""
    rng = np.random.default_rng(4)
    view = rng.integers(0, 256, size=(61, 97, 3), dtype=np.uint8)
    hole = rng.random((61, 97)) < 0.2
    hole[:, :20] = True
    one, several = view.copy(), view.copy()
    assert inpaint_holes(one, hole) == inpaint_holes(several, hole, threads) == int(hole.sum())
    assert np.array_equal(several, one) and not np.array_equal(one, view)


def test_pull_push_fill_continues_the_border_colours_of_every_view():
    """The GPU path's hole filling: holes in smooth gradients of a batch of views take colours close to the
    gradient, seen pixels are kept exactly, and a view with nothing seen is left as it is."""
    import torch

    from drivesim.sim.fill import pull_push_fill

    u = np.linspace(0, 200, 80)
    image = np.repeat(np.stack([u, 200 - u, np.full_like(u, 100)], -1)[None], 30, axis=0).astype(np.uint8)
    views = np.stack([image, image[:, ::-1], np.zeros_like(image)])
    valid = np.ones((3, 30, 80), bool)
    valid[0, 5:25, 38:42] = False  # a speck
    valid[1, :, :16] = False  # a side wedge
    valid[2] = False  # nothing seen
    damaged = np.where(valid[..., None], views, 0).astype(np.uint8)
    out = pull_push_fill(torch.from_numpy(damaged), torch.from_numpy(valid)).numpy()
    assert np.array_equal(out[valid], views[valid])
    assert np.abs(out[0][~valid[0]].astype(int) - views[0][~valid[0]]).mean() < 8
    wedge_error = np.abs(out[1][~valid[1]].astype(int) - views[1][~valid[1]]).mean()
    assert wedge_error < 40, "a wedge is continued from its border, not left black (error of black: ~100)"
    assert (out[1].max(axis=-1) > 0).all()
    assert np.array_equal(out[2], damaged[2])


def test_batched_contact_shadows_match_the_per_car_shadow(tmp_path):
    """contact_shadows_batched (the GPU path) darkens the same pixels as contact_shadow_, by the same amount up to
    rounding, for two views and three cars (two in one view)."""
    import torch

    from drivesim.sim.geometry import invert
    from drivesim.sim.shading import contact_shadow_, contact_shadows_batched

    world = make_world(tmp_path)
    vs = ViewSynthesizer(world, ViewConfig(**SMALL))
    warped = vs.render(np.array([2, 3]), np.array([2.0, 3.0]), np.zeros(2), np.zeros(2), [[], []])
    rgb = warped.rgb.copy()
    depth = np.full(rgb.shape[:3], np.inf, dtype=np.float32)
    T_cam_vehicle = invert(T_VC)
    cars = [(0, pose_2d(12.0, 0.0, 0.0)), (1, pose_2d(9.0, -1.0, 0.2)), (1, pose_2d(15.0, 2.5, 0.0))]
    expected = rgb.copy()
    for view, T_vehicle_car in cars:
        contact_shadow_(expected[view], depth[view], vs.K_view, T_cam_vehicle @ T_vehicle_car, 4.5, 1.9, 0.6)
    got = contact_shadows_batched(
        torch.from_numpy(rgb), torch.from_numpy(depth), vs.K_view, torch.tensor([v for v, _ in cars]),
        torch.from_numpy(np.stack([T_cam_vehicle @ T for _, T in cars])), torch.tensor([[4.5, 1.9]] * 3), 0.6,
    ).numpy()  # fmt: skip
    assert (expected != rgb).sum() > 100, "the test needs shadows"
    assert np.abs(got.astype(int) - expected).max() <= 2
    assert ((got != rgb) != (expected != rgb)).mean() < 0.002, "the same pixels shadowed"
