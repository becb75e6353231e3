"""Each agent's view (sim/view.py) and harmonization (sim/harmonize.py), on a small hand-made world whose geometry is
known exactly: a flat ground plane in front of a camera 1.6 m high, and a wall 40 m ahead above the horizon."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydantic
import pytest
import torch
from sim_worlds import straight_path

from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, invert, pose_2d
from drivesim.sim.harmonize import (
    LEARNED_MODEL,
    LearnedHarmonizer,
    OnnxHarmonizer,
    StatisticalHarmonizer,
    harmonize_view_uint8_,
)
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.vehicle_library import VehicleModel
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer, fit_roi
from drivesim.sim.world import World

W_PX, H_PX = 320, 200
CAMERA_HEIGHT_M = 1.6
WALL_M = 40.0
NO_EFFECTS = {"lighting": False, "harmonization": False}


def _box(length_m: float, width_m: float, height_m: float, rgb: tuple[float, float, float]) -> Mesh:
    """A closed box on the ground (z = 0), centred on its footprint, faces counter-clockwise seen from outside."""
    v = np.array(
        [
            [x, y, z]
            for x in (-length_m / 2, length_m / 2)
            for y in (-width_m / 2, width_m / 2)
            for z in (0.0, height_m)
        ],
        dtype=np.float32,
    )  # vertex 4 * ix + 2 * iy + iz
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]]
    faces += [[2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return Mesh(v, np.array(faces, dtype=np.int64), material=Material(diffuse_rgb=rgb, specular_rgb=(0, 0, 0)))


def box_model(rgb: tuple[float, float, float] = (0.5, 0.25, 0.1), size=(4.0, 1.8, 1.5)) -> VehicleModel:
    """A one-box vehicle of colour `rgb`, never repainted."""
    return VehicleModel("box", *size, [_box(*size, rgb)], [_box(*size, rgb)], paint_group=None)


def make_world(tmp: Path, rgb_scale=(1.0, 1.0, 1.0), near_wall_left_m: float | None = None, n: int = 4) -> World:
    """A straight drive along +x, one frame every 2 m, over a textured ground plane."""
    K = intrinsics_from_hfov(W_PX, H_PX, np.deg2rad(80.0))
    T_vc = camera_mount(0.0, 0.0, CAMERA_HEIGHT_M)
    v, u = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    below = v > K[1, 2] + 0.5
    depth = np.full((H_PX, W_PX), WALL_M, dtype=np.float32)
    depth[below] = np.minimum(K[1, 1] * CAMERA_HEIGHT_M / (v[below] - K[1, 2]), WALL_M)
    rng = np.random.default_rng(0)
    frames = np.empty((n, H_PX, W_PX, 3), dtype=np.uint8)
    for i in range(n):
        base = np.where(below[..., None], [110, 110, 105], [70, 110, 170]).astype(np.float64)
        base += rng.normal(0, 12, size=base.shape)
        frames[i] = np.clip(base * np.asarray(rgb_scale), 0, 255).astype(np.uint8)
    depths = np.repeat(depth[None], n, axis=0)
    if near_wall_left_m is not None:
        depths[:, :, : W_PX // 2] = near_wall_left_m
        frames[:, :, : W_PX // 2] = (20, 200, 20)
    x = 2.0 * np.arange(n)
    T_wv = np.stack([pose_2d(xi, 0.0, 0.0) for xi in x])
    path = straight_path(x, T_wv, T_vc, 200_000_000)
    return World(
        root=tmp, frames=frames, depth_m=depths, K=K, T_vehicle_camera=T_vc, width_px=W_PX, height_px=H_PX,
        camera_height_m=CAMERA_HEIGHT_M, path=path, road_width_m=8.0, lane_width_m=3.5, info={"format": 1},
    )  # fmt: skip


def render_one(vs: ViewSynthesizer, cars, frame=0, x=None, y=0.0, yaw=0.0):
    x = vs.world.path["x_m"][frame] if x is None else x
    return vs.render(np.array([frame]), np.array([x]), np.array([y]), np.array([yaw]), [cars])


def projected_bbox(vs: ViewSynthesizer, model: VehicleModel, T_vehicle_car: np.ndarray) -> tuple[float, ...]:
    """Pixel bounding box (u0, v0, u1, v1) of the car's 8 box corners projected into the view."""
    L, Wd, H = model.length_m, model.width_m, model.height_m
    corners = np.array([[x, y, z, 1.0] for x in (-L / 2, L / 2) for y in (-Wd / 2, Wd / 2) for z in (0.0, H)])
    p = (invert(vs.world.T_vehicle_camera) @ T_vehicle_car @ corners.T)[:3]
    uv = (vs.K_view @ p)[:2] / p[2]
    return uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()


def test_every_frame_is_prepared_when_the_synthesizer_is_made(tmp_path, monkeypatch):
    """The CPU path prepares each recorded frame once, when it is made: rendering views of every frame afterwards
    prepares none again."""
    world = make_world(tmp_path, n=6)
    view = ViewSynthesizer(world, ViewConfig(**NO_EFFECTS))
    prepared = []
    monkeypatch.setattr(view, "_frame_arrays", lambda index: prepared.append(index))
    for frame in range(6):
        x, y, yaw = world.pose(frame)
        view.render(np.array([frame]), np.array([x]), np.array([y]), np.array([yaw]), [[]])
    assert prepared == []


def test_car_ahead_at_projected_position_and_size(tmp_path):
    world = make_world(tmp_path)
    vs = ViewSynthesizer(world, ViewConfig(**NO_EFFECTS))
    model = box_model()
    for ahead_m, lateral_m in ((8.0, 0.0), (12.0, 1.5), (20.0, -2.0)):
        out = render_one(vs, [CarPlacement(model, ahead_m, lateral_m, 0.0)])
        mask = out.car_mask[0]
        rows, cols = np.nonzero(mask)
        u0, v0, u1, v1 = projected_bbox(vs, model, pose_2d(ahead_m, lateral_m, 0.0))
        # Pixel centres inside the projected box: first/last covered pixel within half a pixel (+1 for the edge rule).
        assert abs(cols.min() - u0) <= 1.5 and abs(cols.max() - u1) <= 1.5, (ahead_m, cols.min(), cols.max(), u0, u1)
        assert abs(rows.min() - v0) <= 1.5 and abs(rows.max() - min(v1, 63)) <= 1.5, (ahead_m, rows.min(), v0)
        expected_area = (u1 - u0) * (min(v1, 63.5) - v0)
        assert mask.sum() == pytest.approx(expected_area, rel=0.15)


def test_agent_offset_moves_the_car_in_the_view(tmp_path):
    """The agent 1 m to the left of its recorded frame sees the car 1 m further right, as the projection says."""
    world = make_world(tmp_path)
    vs = ViewSynthesizer(world, ViewConfig(**NO_EFFECTS))
    model = box_model()
    out = render_one(vs, [CarPlacement(model, 12.0, 0.0, 0.0)], frame=0, x=0.0, y=1.0)
    cols = np.nonzero(out.car_mask[0])[1]
    u0, _, u1, _ = projected_bbox(vs, model, pose_2d(12.0, -1.0, 0.0))
    assert abs(cols.min() - u0) <= 1.5 and abs(cols.max() - u1) <= 1.5


def test_occlusion_both_ways(tmp_path):
    """A recorded surface 6 m away (left half) hides a car at 12 m; the car hides the ground and wall behind it."""
    world = make_world(tmp_path, near_wall_left_m=6.0)
    vs = ViewSynthesizer(world, ViewConfig(**NO_EFFECTS))
    model = box_model(rgb=(0.8, 0.2, 0.2))
    out = render_one(vs, [CarPlacement(model, 12.0, 0.0, 0.0)])
    u0, v0, u1, v1 = projected_bbox(vs, model, pose_2d(12.0, 0.0, 0.0))
    centre_col = vs.config.out_width_px / 2
    inside = np.zeros_like(out.car_mask[0])
    inside[int(np.ceil(v0)) + 1 : int(v1), int(np.ceil(u0)) + 1 : int(u1)] = True
    left, right = inside.copy(), inside.copy()
    left[:, int(centre_col) - 1 :] = False
    right[:, : int(centre_col) + 1] = False
    assert left.any() and right.any()
    assert not out.car_mask[0][left].any(), "the nearer recorded surface must hide the car"
    assert np.abs(out.rgb[0][left].astype(int) - (20, 200, 20)).max() <= 1
    assert out.car_mask[0][right].all(), "the car must hide what is behind it"
    assert np.abs(out.rgb[0][right].astype(int) - (204, 51, 51)).max() <= 1  # unlit colour, ground hidden


def test_lighting_follows_the_scene_mean(tmp_path):
    model = box_model(rgb=(0.5, 0.5, 0.5))
    cars = [CarPlacement(model, 10.0, 0.0, 0.0)]
    bright = make_world(tmp_path, rgb_scale=(1.0, 1.0, 1.0))
    reddish = make_world(tmp_path, rgb_scale=(1.0, 0.5, 0.5))
    cfg = ViewConfig(harmonization=False)
    views = [render_one(ViewSynthesizer(w, cfg), cars) for w in (bright, reddish)]
    car = [v.rgb[0][v.car_mask[0]].astype(float).mean(axis=0) for v in views]
    mean_bright = bright.frames[0].reshape(-1, 3).mean(0) / 255
    mean_red = reddish.frames[0].reshape(-1, 3).mean(0) / 255
    # A grey car lit by ambient = mean and directional = gain * mean: its colour is proportional to the scene mean.
    for c in range(3):
        assert car[1][c] / car[0][c] == pytest.approx(mean_red[c] / mean_bright[c], rel=0.03)
    # The rear face (normal toward the viewer) gets 0.5 * mean * (1 + gain).
    assert car[0] == pytest.approx(255 * 0.5 * mean_bright * (1 + cfg.directional_gain), rel=0.05)


def test_raised_light_dims_the_face_towards_the_viewer(tmp_path):
    """With the light raised by 60 degrees the rear face (normal towards the viewer) gets cos(60) of it."""
    world = make_world(tmp_path)
    cars = [CarPlacement(box_model(rgb=(0.5, 0.5, 0.5)), 10.0, 0.0, 0.0)]
    cfg = ViewConfig(harmonization=False, light_elevation_deg=60.0)
    view = render_one(ViewSynthesizer(world, cfg), cars)
    rear = view.rgb[0][view.car_mask[0]].astype(float)
    mean = world.frames[0].reshape(-1, 3).mean(0) / 255
    assert np.median(rear, axis=0) == pytest.approx(255 * 0.5 * mean * (1 + 0.5 * cfg.directional_gain), rel=0.05)


def test_harmonization_moves_car_statistics_toward_surroundings(tmp_path):
    world = make_world(tmp_path, rgb_scale=(0.6, 0.7, 1.0))
    model = box_model(rgb=(0.9, 0.9, 0.1))
    cars = [CarPlacement(model, 10.0, 0.0, 0.0)]
    plain = render_one(ViewSynthesizer(world, ViewConfig(harmonization=False, camera_look=False)), cars)
    harmonized = render_one(ViewSynthesizer(world, ViewConfig(harmonization=True, camera_look=False)), cars)
    mask = plain.car_mask[0]
    assert (harmonized.car_mask[0] == mask).all()
    assert (harmonized.rgb[0][~mask] == plain.rgb[0][~mask]).all(), "only the car may change"
    ring = torch.nn.functional.max_pool2d(torch.from_numpy(mask)[None, None].float(), 13, 1, 6)[0, 0].bool().numpy()
    ring &= ~mask
    surroundings = plain.rgb[0][ring].astype(float).mean(0)
    before = np.abs(plain.rgb[0][mask].astype(float).mean(0) - surroundings).sum()
    after = np.abs(harmonized.rgb[0][mask].astype(float).mean(0) - surroundings).sum()
    assert after < 0.8 * before


def test_statistical_harmonizer_leaves_views_without_a_car_alone():
    rgb = torch.rand(2, 8, 10, 3)
    mask = torch.zeros(2, 8, 10, dtype=torch.bool)
    mask[0, 2:5, 3:6] = True
    out = StatisticalHarmonizer()(rgb, mask)
    assert torch.equal(out[1], rgb[1]) and torch.equal(out[0][~mask[0]], rgb[0][~mask[0]])
    assert not torch.equal(out[0][mask[0]], rgb[0][mask[0]])


def test_statistical_harmonizer_uint8_path_matches_the_torch_path():
    """The simulator's CPU path (OpenCV, in place on uint8 views) gives the torch path's colours: a bright car on a
    darker, noisy road, one near the image border (its ring is cut there)."""
    rng = np.random.default_rng(1)
    harmonizer = StatisticalHarmonizer()
    for box in ((slice(20, 40), slice(50, 90)), (slice(0, 15), slice(0, 30))):
        rgb = np.clip(rng.normal((90, 100, 110), 15, size=(64, 160, 3)), 0, 255).astype(np.uint8)
        mask = np.zeros((64, 160), dtype=bool)
        mask[box] = True
        rgb[mask] = np.clip(rng.normal((220, 60, 40), 20, size=(int(mask.sum()), 3)), 0, 255).astype(np.uint8)
        expected = harmonizer(torch.from_numpy(rgb)[None].float() / 255.0, torch.from_numpy(mask)[None])[0]
        expected = (expected * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
        out = rgb.copy()
        harmonizer.harmonize_view_uint8_(out, mask)
        assert (out[~mask] == rgb[~mask]).all()
        assert not (out[mask] == rgb[mask]).all()
        assert np.abs(out.astype(int) - expected.astype(int)).max() <= 1


def test_one_view_helper_takes_any_harmonizer():
    """`harmonize_view_uint8_` runs a harmonizer without an in-place path (a learned one) through its float call and
    changes only the masked pixels; the statistical one through its own uint8 path."""

    class Gray:
        def __call__(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            return torch.full_like(rgb, 0.5)

    rgb = np.random.default_rng(2).integers(0, 256, size=(16, 24, 3), dtype=np.uint8)
    mask = np.zeros((16, 24), dtype=bool)
    mask[4:9, 6:15] = True
    out = rgb.copy()
    harmonize_view_uint8_(Gray(), out, mask)
    assert (out[mask] == 128).all() and (out[~mask] == rgb[~mask]).all()
    statistical, expected = rgb.copy(), rgb.copy()
    harmonize_view_uint8_(StatisticalHarmonizer(), statistical, mask)
    StatisticalHarmonizer().harmonize_view_uint8_(expected, mask)
    assert (statistical == expected).all()


def test_cpu_view_path_matches_the_torch_path(tmp_path):
    """The CPU path (compiled raster, numpy composite, OpenCV harmonization) renders what the all-torch path (the
    GPU's) renders: the same car pixels and colours, for a batch with two cars, one car and none."""
    world = make_world(tmp_path)
    fast = ViewSynthesizer(world, ViewConfig())
    reference = ViewSynthesizer(world, ViewConfig())
    reference.rasterizer.use_kernel = False
    reference._insert_cpu = reference._insert_torch
    request = _batch_request(world)
    a, b = fast.render(*request), reference.render(*request)
    assert a.car_mask.sum() > 1000
    assert (a.car_mask == b.car_mask).mean() > 0.999
    assert (np.abs(a.rgb.astype(int) - b.rgb.astype(int)) <= 1).mean() > 0.999


def _onnx_half(path: Path, two_inputs: bool) -> None:
    """A tiny harmonization graph: output = 0.5 * image (of the 4-channel input, or of the image input)."""
    import onnx
    from onnx import TensorProto, helper

    half = helper.make_tensor("half", TensorProto.FLOAT, [], [0.5])
    if two_inputs:
        inputs = [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["B", 3, "H", "W"]),
                  helper.make_tensor_value_info("mask", TensorProto.FLOAT, ["B", 1, "H", "W"])]  # fmt: skip
        nodes = [helper.make_node("Mul", ["image", "half"], ["out"])]
        inits = [half]
    else:
        inputs = [helper.make_tensor_value_info("composite", TensorProto.FLOAT, ["B", 4, "H", "W"])]
        starts = helper.make_tensor("starts", TensorProto.INT64, [1], [0])
        ends = helper.make_tensor("ends", TensorProto.INT64, [1], [3])
        axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
        nodes = [helper.make_node("Slice", ["composite", "starts", "ends", "axes"], ["rgb"]),
                 helper.make_node("Mul", ["rgb", "half"], ["out"])]  # fmt: skip
        inits = [half, starts, ends, axes]
    output = helper.make_tensor_value_info("out", TensorProto.FLOAT, ["B", 3, "H", "W"])
    graph = helper.make_graph(nodes, "half", inputs, [output], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)


@pytest.mark.parametrize("two_inputs", [False, True])
def test_onnx_harmonizer_applies_the_graph_under_the_mask(tmp_path, two_inputs):
    path = tmp_path / "harmonizer.onnx"
    _onnx_half(path, two_inputs)
    harmonizer = OnnxHarmonizer(path)
    rgb = torch.rand(2, 6, 7, 3)
    mask = torch.rand(2, 6, 7) > 0.5
    out = harmonizer(rgb, mask)
    assert torch.allclose(out[mask], 0.5 * rgb[mask]) and torch.equal(out[~mask], rgb[~mask])
    # Plugged into the view.
    world = make_world(tmp_path)
    view = render_one(
        ViewSynthesizer(world, ViewConfig(camera_look=False), harmonizer=harmonizer),
        [CarPlacement(box_model(), 10, 0, 0)],
    )
    plain = render_one(
        ViewSynthesizer(world, ViewConfig(harmonization=False, camera_look=False)),
        [CarPlacement(box_model(), 10, 0, 0)],
    )
    m = view.car_mask[0]
    assert np.abs(view.rgb[0][m].astype(float) - 0.5 * plain.rgb[0][m]).max() <= 1.0


def test_onnx_harmonizer_bad_file_is_one_line(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such harmonization model"):
        OnnxHarmonizer(tmp_path / "missing.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a graph")
    with pytest.raises(ValueError, match="not a usable ONNX model"):
        OnnxHarmonizer(bad)


@pytest.mark.parametrize(
    ("view_hw", "rows", "cols"),
    [((64, 160), (30, 44), (70, 100)), ((64, 160), (31, 46), (71, 98)), ((63, 159), (40, 63), (3, 40))],
    ids=["even-box", "odd-box", "odd-view-at-edge"],
)
def test_learned_harmonizer_on_the_box_gives_what_the_whole_view_gives(view_hw, rows, cols):
    """The shipped learned harmonizer run on the car's box and ring (the simulator's CPU path) changes the view as
    running it on the whole view does, only under the mask, wherever the box falls on the network's half-resolution
    grid and at the view's edge, and leaves a view without a car alone."""
    assert LEARNED_MODEL.is_file(), "the learned harmonizer ships with drivesim (benchmarks/bench_harmonizer.py)"
    harmonizer = LearnedHarmonizer()
    rng = np.random.default_rng(3)
    rgb = np.clip(rng.normal((110, 105, 100), 25, size=(*view_hw, 3)), 0, 255).astype(np.uint8)
    mask = np.zeros(view_hw, dtype=bool)
    mask[slice(*rows), slice(*cols)] = True
    rgb[mask] = np.clip(rng.normal((40, 45, 60), 10, size=(int(mask.sum()), 3)), 0, 255).astype(np.uint8)
    whole = harmonizer(torch.from_numpy(rgb)[None].float() / 255.0, torch.from_numpy(mask)[None])[0]
    whole = (whole * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
    boxed = rgb.copy()
    harmonizer.harmonize_view_uint8_(boxed, mask)
    assert (boxed[~mask] == rgb[~mask]).all()
    assert np.abs(boxed.astype(int) - rgb.astype(int)).max() >= 3  # it does something to the car
    assert np.abs(boxed.astype(int) - whole.astype(int)).max() <= 1
    empty = rgb.copy()
    harmonizer.harmonize_view_uint8_(empty, np.zeros_like(mask))
    assert (empty == rgb).all()


def test_view_config_names_the_harmonizer(tmp_path):
    """`harmonizer: learned` puts the learned model in the view; an unknown name is refused."""
    world = make_world(tmp_path)
    cars = [CarPlacement(box_model(), 10, 0, 0)]
    learned = ViewSynthesizer(world, ViewConfig(harmonizer="learned", camera_look=False))
    assert isinstance(learned.harmonizer, LearnedHarmonizer)
    statistical = ViewSynthesizer(world, ViewConfig(camera_look=False))
    a, b = render_one(learned, cars), render_one(statistical, cars)
    assert a.car_mask[0].any() and (a.car_mask[0] == b.car_mask[0]).all()
    assert (a.rgb[0][~a.car_mask[0]] == b.rgb[0][~b.car_mask[0]]).all()
    assert not (a.rgb[0][a.car_mask[0]] == b.rgb[0][b.car_mask[0]]).all()
    with pytest.raises(pydantic.ValidationError, match="harmonizer"):
        ViewConfig(harmonizer="idih")


@pytest.mark.parametrize("path", ["cpu", "torch"])
def test_learned_harmonizer_keeps_a_gray_cameras_car_gray(tmp_path, path):
    """On a monochrome camera the learned harmonizer's colour map may tint the car; the view draws it in luma again."""
    world = make_world(tmp_path)
    view = ViewSynthesizer(world, ViewConfig(harmonizer="learned", monochrome=True, camera_look=False))
    if path == "torch":
        view._insert_cpu = view._insert_torch
    out = render_one(view, [CarPlacement(box_model((0.7, 0.3, 0.2)), 10, 0, 0)])
    car = out.rgb[0][out.car_mask[0]].astype(int)
    assert len(car) and (car.max(axis=1) - car.min(axis=1)).max() == 0


def _batch_request(world: World):
    model_a, model_b = box_model((0.2, 0.3, 0.8)), box_model((0.7, 0.7, 0.2), size=(5.0, 2.0, 1.9))
    frames = np.array([0, 1, 2])
    x = np.array([0.3, 2.5, 3.6])
    y = np.array([0.0, -0.6, 0.8])
    yaw = np.array([0.0, 0.05, -0.08])
    cars = [
        [CarPlacement(model_a, 10.0, 0.5, 0.1)],
        [],
        [CarPlacement(model_a, 14.0, 1.0, 0.0), CarPlacement(model_b, 18.0, -2.0, -0.2)],
    ]
    return frames, x, y, yaw, cars


def test_same_inputs_same_bytes_and_batch_equals_one_by_one(tmp_path):
    world = make_world(tmp_path)
    frames, x, y, yaw, cars = _batch_request(world)
    batch = ViewSynthesizer(world).render(frames, x, y, yaw, cars)
    again = ViewSynthesizer(world).render(frames, x, y, yaw, cars)
    assert batch.rgb.tobytes() == again.rgb.tobytes() and (batch.car_mask == again.car_mask).all()
    assert batch.car_mask[0].any() and not batch.car_mask[1].any() and batch.car_mask[2].any()
    vs = ViewSynthesizer(world)
    for b in range(len(frames)):
        one = vs.render(frames[b : b + 1], x[b : b + 1], y[b : b + 1], yaw[b : b + 1], cars[b : b + 1])
        assert one.rgb[0].tobytes() == batch.rgb[b].tobytes(), b
        assert (one.car_mask[0] == batch.car_mask[b]).all()
    assert set(batch.timings_ms) == {"warp", "raster", "composite", "lighting", "harmonize"}


def test_render_threads_draw_the_same_views(tmp_path):
    """`render_threads` (each view's warp cut into bands warped at the same time) changes no pixel: the same batch
    of views, with and without cars, offsets and turns, as with one thread."""
    world = make_world(tmp_path)
    frames, x, y, yaw, cars = _batch_request(world)
    one = ViewSynthesizer(world).render(frames, x, y, yaw, cars)
    for threads in (2, 3):
        banded = ViewSynthesizer(world, ViewConfig(render_threads=threads)).render(frames, x, y, yaw, cars)
        assert banded.rgb.tobytes() == one.rgb.tobytes(), threads
        assert (banded.car_mask == one.car_mask).all()


def test_bad_requests_are_one_line(tmp_path):
    world = make_world(tmp_path)
    vs = ViewSynthesizer(world)
    with pytest.raises(ValueError, match="frame_index must be in"):
        vs.render(np.array([9]), np.zeros(1), np.zeros(1), np.zeros(1), [[]])
    with pytest.raises(ValueError, match="car lists"):
        vs.render(np.array([0]), np.zeros(1), np.zeros(1), np.zeros(1), [])


def test_region_of_interest_fits_smaller_images():
    assert fit_roi((0, 72, 320, 128), 320, 200) == (0, 72, 320, 128)
    # A KITTI world (320 x 96): the 2.5:1 band shrinks about its bottom centre to 240 x 96.
    assert fit_roi((0, 72, 320, 128), 320, 96) == pytest.approx((40, 0, 240, 96))
    # Too far down or right: moved inside, size kept.
    assert fit_roi((100, 100, 240, 100), 320, 200) == pytest.approx((80, 100, 240, 100))


CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_batched_path_renders_what_the_per_view_path_renders(tmp_path, device):
    """The batched path (all views in one batch of torch operations: what runs on a GPU, and here on the CPU too)
    gives the per-view path's views for a batch with two cars, one car and none, off the recorded path: the same car
    pixels, the same colours up to rounding, its holes filled (no black); and several views of one car model are
    rasterized as one scene seen from many poses."""
    world = make_world(tmp_path)
    per_view = ViewSynthesizer(world, ViewConfig(fill_frames=()))  # the batched path has no neighbour frames
    batched = ViewSynthesizer(world, ViewConfig(), device=device, batched=True if device == "cpu" else None)
    assert batched.batched and not per_view.batched
    request = _batch_request(world)
    a, b = per_view.render(*request), batched.render(*request)
    holes = ViewSynthesizer(world, ViewConfig(inpaint=False, fill_frames=())).render(*request).rgb.max(axis=-1) == 0
    assert 0.005 < holes.mean() < 0.3, "the test needs some holes to fill"
    assert a.car_mask.sum() > 1000
    assert (a.car_mask == b.car_mask).mean() > 0.999
    difference = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(axis=-1)
    assert (difference[~holes] <= 2).mean() > 0.999
    assert (b.rgb.max(axis=-1) > 0).all()
    assert difference[holes].mean() < 1, "both paths fill holes with the same pull-push"
    calls = []  # cameras of each raster call: `render` on the CPU's compiled path, `render_instances` on torch's
    rasterizer = batched.rasterizer
    render, instances = rasterizer.render, rasterizer.render_instances
    rasterizer.render = lambda *args, **kw: calls.append(len(args[1])) or render(*args, **kw)
    rasterizer.render_instances = lambda *args, **kw: calls.append(len(args[2])) or instances(*args, **kw)
    model = box_model()
    frames, x = np.array([0, 1, 2, 3]), np.array([0.0, 2.0, 4.0, 6.0])
    cars = [[CarPlacement(model, xi + 12.0, 0.5 * i, 0.0)] for i, xi in enumerate(x)]
    out = batched.render(frames, x, np.zeros(4), np.zeros(4), cars)
    assert out.car_mask.reshape(4, -1).any(axis=1).all()
    assert calls == [4], "four views of one model: one raster call with four poses"


def test_batched_path_needs_no_neighbour_frames(tmp_path):
    world = make_world(tmp_path)
    with pytest.raises(ValueError, match="fill_frames"):
        ViewSynthesizer(world, ViewConfig(fill_frames=(-1, 1)), batched=True)
    assert not ViewSynthesizer(world, ViewConfig(fill_frames=(-1, 1)), device="cpu").batched


def test_batched_torch_path_draws_repainted_library_cars_and_memory_stays_bounded(tmp_path):
    """The GPU's path (batched views, torch raster from one library of unpainted geometry, each car its own paint;
    run here on the CPU) draws the procedural library's repainted cars as the per-view path does; and 300 episodes'
    repainted cars keep at most the model cache's worth of packed cars and one geometry per shape and detail."""
    from drivesim.sim import view as view_module
    from drivesim.sim.vehicle_library import VehicleLibrary

    world = make_world(tmp_path)
    library = VehicleLibrary.procedural(count=3, seed=0)
    rng = np.random.default_rng(0)
    models = [library.sample(rng) for _ in range(4)]
    frames, x = np.array([0, 1, 2, 3]), np.array([0.0, 2.0, 4.0, 6.0])
    cars = [[CarPlacement(models[i], xi + 9.0 + 4 * i, 0.6 * (i - 1.5), 0.1)] for i, xi in enumerate(x)]
    per_view = ViewSynthesizer(world, ViewConfig())
    batched = ViewSynthesizer(world, ViewConfig(), batched=True)
    batched.rasterizer.use_kernel = False
    a = per_view.render(frames, x, np.zeros(4), np.zeros(4), cars)
    b = batched.render(frames, x, np.zeros(4), np.zeros(4), cars)
    assert a.car_mask.reshape(4, -1).any(axis=1).all()
    assert (a.car_mask == b.car_mask).mean() > 0.999
    both = a.car_mask & b.car_mask
    assert (np.abs(a.rgb[both].astype(int) - b.rgb[both]) <= 2).mean() > 0.99
    for _ in range(300):
        per_view._model_scenes(library.sample(rng))
        batched._geometry(library.sample(rng), True)
    assert len(per_view._packed) <= view_module._MODEL_CACHE_SIZE
    assert len(batched._geometries) <= 2 * len(library.models)
