"""The synth world made a stretch at a time: a seed keeps its world, and the meshes held do not grow with the road."""

from __future__ import annotations

import numpy as np
import pytest

from drivesim.sim.geometry import invert, pose_2d
from drivesim.sim.mesh import Mesh
from drivesim.stages.synth import world as world_module
from drivesim.stages.synth.config import SynthConfig
from drivesim.stages.synth.render import CellCulling, Scratch, render_packed
from drivesim.stages.synth.world import HAZE_DISTANCE_M, WHOLE_WORLD_TRIANGLES, SynthWorld

W, H = 320, 200

# Seed 0's world (default road, 320x200 camera) as the whole build made it before the world was made in pieces
# (commit 23433c9), mesh by mesh: object id, triangles, sums over the faces' corners of the vertices, uv, vertex
# colours and |normals| (None: the mesh has none), and the sum of its texture's bytes.
SEED0_MESHES = [
    (0, 600, 235470.082, 1800.0, None, None, 24939014),
    (1, 1216, 487352.656, 3648.0, None, None, 7796040),
    (1, 3648, 1461455.389, None, 20687.808, None, None),
    (2, 9538, 4122851.58, 28510.5, None, None, 16447438),
    (2, 1704, 766544.4, None, None, None, None),
    (3, 42, 9434.408, 103.757, None, None, 164102245),
    (3, 54, 13970.459, 137.94, None, None, 236107381),
    (3, 54, 21047.762, 138.163, None, None, 202553546),
    (3, 18, 14321.426, 44.431, None, None, 49751437),
    (4, 11440, 4695414.653, None, 22346.148, 50275.913, None),
    (4, 3432, 1372518.359, None, 8403.831, 12389.665, None),
    (5, 14288, 6198213.226, None, 56151.841, None, None),
    (5, 752, 327416.65, None, 4399.2, None, None),
    (5, 6016, 2604030.85, None, 2526.72, None, None),
    (5, 3008, 1305606.977, None, 13942.08, None, None),
    (5, 752, 325287.731, None, 203.04, None, None),
]


def small_cfg(road_length_m: float = 400.0) -> SynthConfig:
    return SynthConfig.model_validate(
        {"camera": {"width_px": W, "height_px": H}, "world": {"road": {"length_m": road_length_m}}}
    )


def camera_pose(world: SynthWorld, s_m: float) -> np.ndarray:
    p = world.path.at(s_m)
    return pose_2d(float(p["x_m"]), float(p["y_m"]), float(p["yaw_rad"])) @ world.camera.T_vehicle_camera


def digest(m: Mesh) -> tuple:
    """A mesh's `SEED0_MESHES` row."""

    def corner_sum(a: np.ndarray | None, absolute: bool = False) -> float | None:
        if a is None:
            return None
        x = np.asarray(a, np.float64)[m.faces]
        return round(float((np.abs(x) if absolute else x).sum()), 3)

    texture = None if m.texture_rgb is None else int(np.asarray(m.texture_rgb, np.int64).sum())
    return (
        m.object_id, len(m.faces), corner_sum(m.vertices_m), corner_sum(m.uv), corner_sum(m.vertex_rgb),
        corner_sum(m.normals, absolute=True), texture,
    )  # fmt: skip


@pytest.fixture(scope="module")
def long_world() -> SynthWorld:
    return SynthWorld.from_seed(0, small_cfg(1000.0))


def test_a_seed_keeps_its_world():
    """Seed 0's meshes are those the whole build made, mesh by mesh (so are its frames: see the notebook)."""
    world = SynthWorld.from_seed(0, small_cfg())
    got = [digest(m) for m in world.meshes]
    assert [row[:2] for row in got] == [row[:2] for row in SEED0_MESHES]
    for row, want in zip(got, SEED0_MESHES, strict=True):
        for x, y in zip(row[2:], want[2:], strict=True):
            assert (x is None and y is None) or x == pytest.approx(y, rel=1e-9, abs=2e-3)


def test_pieces_joined_are_the_whole_meshes(long_world):
    """Held a stretch at a time or whole, the world has the same faces, in the same order, to the bit."""
    assert long_world.triangle_count <= WHOLE_WORLD_TRIANGLES  # so the world's own culling holds it whole
    whole = long_world._culling.whole_meshes()
    pieces = CellCulling(long_world._sources, long_world._facades, whole_below_triangles=0).whole_meshes()
    assert len(whole) == len(pieces)
    for a, b in zip(whole, pieces, strict=True):
        assert a.object_id == b.object_id and a.material == b.material
        for name in ("vertices_m", "uv", "vertex_rgb", "normals"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None)
            if x is not None:
                assert np.array_equal(x[a.faces], y[b.faces])


def test_frames_through_pieces_are_the_whole_worlds_but_for_rounding(long_world):
    """A packing of pieces holds the same faces as a packing of whole meshes; only its origin (the mean of the
    vertices it holds) differs, so a few edge pixels may round the other way."""
    pieces = CellCulling(long_world._sources, long_world._facades, whole_below_triangles=0)
    cam = long_world.camera
    for s_m in (100.0, 500.0, 900.0):
        T = camera_pose(long_world, s_m)
        rgb, depth, ids = long_world.render_full(T, cam.K, W, H)
        packed, triangles = pieces.scene(T[:2, 3], long_world.config.scenery.view_distance_m)
        frame = render_packed(
            packed, triangles, invert(T), cam.K, W, H, long_world.lighting(T), HAZE_DISTANCE_M, long_world._sky,
            Scratch(),
        )  # fmt: skip
        assert np.sum(frame.object_id != ids) <= 8
        diff = np.abs(frame.rgb.astype(int) - rgb.astype(int)).max(-1)
        assert np.mean(diff <= 1) > 0.999 and np.mean(diff > 0) < 0.03
        both = np.isfinite(depth) & np.isfinite(frame.depth_m)
        assert np.median(np.abs(frame.depth_m[both] - depth[both]) / depth[both]) < 1e-5


def test_meshes_held_do_not_grow_with_the_road(monkeypatch):
    """Along a 2 km road (seen to 120 m), the pieces held are those near the camera: at most half of the world, as
    many at the end of the road as near its start, and those left behind are dropped."""
    monkeypatch.setattr(world_module, "WHOLE_WORLD_TRIANGLES", 0)  # held a stretch at a time, however small
    world = SynthWorld.from_seed(0, small_cfg(2000.0))
    culling = world._culling
    held = {}
    for s_m in np.arange(0.0, world.path.length_m, 100.0):
        culling.scene(camera_pose(world, float(s_m))[:2, 3], 120.0)
        held[float(s_m)] = culling.held_triangles
    assert max(held.values()) < 0.5 * world.triangle_count
    start = max(v for s, v in held.items() if s < 1000.0)
    end = max(v for s, v in held.items() if s >= 1000.0)
    assert end < 1.5 * start
    assert (0, 0) not in culling._held  # the road's first stretch, left behind
