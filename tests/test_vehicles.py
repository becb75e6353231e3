"""The vehicle builder and library: closed outward meshes, sizes, levels of detail, paints, save/load."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from drivesim.sim import geometry as g
from drivesim.sim.raster import Rasterizer
from drivesim.sim.vehicle_library import VehicleLibrary, save_library
from drivesim.sim.vehicles import (
    BODY_TYPES,
    DETAILS,
    GROUP_NAMES,
    PAINT_RANGES,
    VehicleShape,
    build_vehicle_meshes,
    sample_paint,
    sample_vehicle_shape,
)


def _shapes() -> list[VehicleShape]:
    rng = np.random.default_rng(3)
    return [sample_vehicle_shape(rng, body_type) for body_type in BODY_TYPES for _ in range(2)]


@pytest.mark.parametrize("detail", DETAILS)
def test_every_group_is_closed_and_faces_outward(detail):
    paint = sample_paint(np.random.default_rng(0))
    for shape in _shapes():
        meshes = build_vehicle_meshes(shape, paint, detail, object_id=7)
        assert len(meshes) == len(GROUP_NAMES)
        for name, mesh in zip(GROUP_NAMES, meshes, strict=True):
            assert mesh.object_id == 7
            tm = trimesh.Trimesh(mesh.vertices_m, mesh.faces, process=True)
            assert tm.is_watertight, f"{shape.body_type} {detail} {name} is not closed"
            assert tm.is_winding_consistent, f"{shape.body_type} {detail} {name} has flipped faces"
            # outward: every closed component encloses positive volume
            for part in tm.split(only_watertight=True):
                assert part.volume > 0, f"{shape.body_type} {detail} {name}: a part faces inward"


def test_sizes_match_the_shape_and_the_vehicle_frame():
    paint = sample_paint(np.random.default_rng(0))
    for shape in _shapes():
        for detail in DETAILS:
            meshes = build_vehicle_meshes(shape, paint, detail)
            v = np.concatenate([m.vertices_m for m in meshes])
            lo, hi = v.min(0), v.max(0)
            np.testing.assert_allclose(hi - lo, [shape.length_m, shape.width_m, shape.height_m], atol=2e-3)
            np.testing.assert_allclose([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]], 0.0, atol=2e-3)
            wheels = meshes[GROUP_NAMES.index("wheels")].vertices_m
            assert abs(wheels[:, 2].min()) < 1e-4  # the tyres stand on the ground
            np.testing.assert_allclose(wheels[:, 2].max(), 2 * shape.wheel_radius_m, atol=1e-4)
            front = wheels[wheels[:, 0] > 0, 0]
            rear = wheels[wheels[:, 0] < 0, 0]
            wheelbase = (front.max() + front.min()) / 2 - (rear.max() + rear.min()) / 2
            assert wheelbase == pytest.approx(shape.wheelbase_fraction * shape.length_m, abs=0.02)
            roof = meshes[0].vertices_m[:, 2].max()
            assert roof == pytest.approx(shape.height_m, abs=1e-4)


def test_body_types_differ_where_they_should():
    rng = np.random.default_rng(0)
    sizes = {}
    for body_type in BODY_TYPES:
        shapes = [sample_vehicle_shape(rng, body_type) for _ in range(50)]
        sizes[body_type] = np.mean([[s.length_m, s.height_m, s.trunk_fraction] for s in shapes], axis=0)
        for s in shapes:
            assert 3.4 < s.length_m < 6.0 and 1.6 < s.width_m < 2.1 and 1.3 < s.height_m < 2.2
            assert s.hood_fraction + s.cabin_fraction + s.trunk_fraction == pytest.approx(1.0)
    assert sizes["van"][1] > sizes["suv"][1] > sizes["sedan"][1]  # heights
    assert sizes["hatchback"][0] < sizes["sedan"][0] < sizes["pickup"][0]  # lengths
    assert sizes["pickup"][2] > sizes["sedan"][2] > sizes["hatchback"][2]  # bed / trunk / hatch overhang


def test_light_detail_is_a_few_hundred_triangles_and_full_is_finer():
    paint = sample_paint(np.random.default_rng(0))
    for shape in _shapes():
        light = sum(m.triangle_count for m in build_vehicle_meshes(shape, paint, "light"))
        full = sum(m.triangle_count for m in build_vehicle_meshes(shape, paint, "full"))
        assert 200 <= light <= 600, f"{shape.body_type}: {light} light triangles"
        assert full >= 3 * light, f"{shape.body_type}: full {full} vs light {light}"


def test_back_face_culling_leaves_the_image_unchanged():
    """Faces counter-clockwise from outside: culling back faces (the vehicles' fast path) drops nothing visible."""
    shape = sample_vehicle_shape(np.random.default_rng(1), "suv")
    meshes = build_vehicle_meshes(shape, sample_paint(np.random.default_rng(1)), "full", object_id=1)
    K = g.intrinsics_from_hfov(160, 100, np.radians(60.0))
    views = [g.pose_2d(-8.0, 2.0, -0.2), g.pose_2d(6.0, -5.0, 2.4), g.pose_2d(0.5, 7.0, -1.6)]
    T = np.stack([g.invert(P @ g.camera_mount(0.0, 0.0, 1.6, pitch_down_rad=0.1)) for P in views])
    plain = Rasterizer(160, 100).render(meshes, T, K)
    culled = Rasterizer(160, 100, cull_back_faces=True).render(meshes, T, K)
    assert plain.mask.sum() > 3 * 800  # the car fills part of every view
    assert np.array_equal(plain.object_id.numpy(), culled.object_id.numpy())
    # the culled path shades in another order: float rounding only
    np.testing.assert_allclose(plain.rgb.numpy(), culled.rgb.numpy(), atol=5e-3)


def test_paints_stay_in_their_physical_ranges_with_street_frequencies():
    rng = np.random.default_rng(0)
    paints = [sample_paint(rng) for _ in range(3000)]
    diffuse = np.array([p.diffuse_rgb for p in paints])
    assert diffuse.min() >= PAINT_RANGES["albedo"][0] and diffuse.max() <= PAINT_RANGES["albedo"][1]
    f0 = np.array([p.specular_rgb for p in paints])
    assert np.all(f0[:, 0] == f0[:, 2])  # achromatic clear coat
    assert PAINT_RANGES["specular_f0"][0] <= f0.min() and f0.max() <= PAINT_RANGES["specular_f0"][1]
    shininess = np.array([p.shininess for p in paints])
    assert shininess.min() >= 64.0 and shininess.max() <= 256.0
    roughness = np.array([p.roughness for p in paints])
    assert roughness.min() >= 0.05 and roughness.max() <= 0.3
    metal = np.array([p.metalness for p in paints])
    assert np.all((metal == 0.0) | ((metal >= 0.3) & (metal <= 0.7)))
    assert 0.2 < (metal > 0).mean() < 0.45
    white = (diffuse.min(1) > 0.55).mean()
    black = (diffuse.max(1) < 0.05).mean()
    assert white == pytest.approx(0.35, abs=0.04) and black == pytest.approx(0.19, abs=0.04)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="body_type"):
        VehicleShape("tank", 4.0, 1.8, 1.5, 0.3, 0.5, 0.2, 0.3)
    with pytest.raises(ValueError, match="sum to 1"):
        VehicleShape("sedan", 4.0, 1.8, 1.5, 0.3, 0.5, 0.5, 0.3)
    with pytest.raises(ValueError, match="detail"):
        build_vehicle_meshes(
            sample_vehicle_shape(np.random.default_rng(0)), sample_paint(np.random.default_rng(0)), "x"
        )


def test_procedural_library_is_deterministic_and_repaints_only_the_body():
    a, b = VehicleLibrary.procedural(6, seed=4), VehicleLibrary.procedural(6, seed=4)
    assert [m.name for m in a.models] == [m.name for m in b.models]
    assert {m.name.split("-")[0] for m in a.models} == set(BODY_TYPES)
    for x, y in zip(a.models, b.models, strict=True):
        np.testing.assert_array_equal(x.full[0].vertices_m, y.full[0].vertices_m)
    rng = np.random.default_rng(0)
    drawn = [a.sample(rng) for _ in range(40)]
    assert len({m.name for m in drawn}) == 6
    base = next(m for m in a.models if m.name == drawn[0].name)
    assert drawn[0].full[0].material != base.full[0].material
    assert drawn[0].full[0].vertices_m is base.full[0].vertices_m  # meshes shared, not copied
    assert drawn[0].full[1:] == base.full[1:] and drawn[0].light[1].material == base.light[1].material
    assert a.sample(np.random.default_rng(0), repaint=False) in a.models


def test_library_save_load_round_trip(tmp_path):
    lib = VehicleLibrary.procedural(5, seed=2)
    save_library(tmp_path, lib.models, ["procedural"] * 5)
    loaded = VehicleLibrary.load(tmp_path)
    assert [m.name for m in loaded.models] == [m.name for m in lib.models]
    for x, y in zip(lib.models, loaded.models, strict=True):
        assert (x.length_m, x.width_m, x.height_m) == pytest.approx((y.length_m, y.width_m, y.height_m), abs=1e-6)
        for mx, my in zip(x.full + x.light, y.full + y.light, strict=True):
            np.testing.assert_allclose(mx.vertices_m, my.vertices_m, atol=1e-6)
            np.testing.assert_array_equal(mx.faces, my.faces)
            assert mx.material == my.material
            assert (mx.vertex_rgb is None) == (my.vertex_rgb is None)
            if mx.vertex_rgb is not None:
                np.testing.assert_allclose(mx.vertex_rgb, my.vertex_rgb, atol=1 / 255)
        assert y.repainted(sample_paint(np.random.default_rng(0))).full[0].material != y.full[0].material


def test_library_load_names_the_bad_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="library.json"):
        VehicleLibrary.load(tmp_path)
    lib = VehicleLibrary.procedural(2, seed=0)
    save_library(tmp_path, lib.models, ["procedural"] * 2)
    bad = tmp_path / lib.models[1].name / "light" / "wheels.ply"
    bad.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(ValueError, match="wheels.ply"):
        VehicleLibrary.load(tmp_path)
    bad.unlink()
    with pytest.raises(FileNotFoundError, match="wheels.ply"):
        VehicleLibrary.load(tmp_path)
    (tmp_path / "library.json").write_text(json.dumps({"format": 99, "models": []}))
    with pytest.raises(ValueError, match="library.json"):
        VehicleLibrary.load(tmp_path)
