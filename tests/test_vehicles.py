"""The vehicle builder and library: closed outward meshes, sizes, levels of detail, paints, save/load."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from drivesim.sim import geometry as g
from drivesim.sim.mesh import Material
from drivesim.sim.raster import Rasterizer
from drivesim.sim.vehicle_library import VehicleLibrary, save_library
from drivesim.sim.vehicles import (
    BODY_OCCLUSION_FLOOR,
    BODY_TYPES,
    DETAILS,
    GROUP_NAMES,
    PAINT_RANGES,
    PART_RANGES,
    VehicleShape,
    build_vehicle_meshes,
    repaint,
    sample_paint,
    sample_part_materials,
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


def _side_view_pixel(shape: VehicleShape, point_m: np.ndarray, meshes: list) -> tuple[np.ndarray, int]:
    """The unlit colour and object id at the pixel showing vehicle-frame `point_m` to a camera 6 m off the car's
    left side, looking at it square on from the point's height."""
    K = g.intrinsics_from_hfov(320, 200, np.radians(60.0))
    eye = np.array([point_m[0], 6.0, point_m[2]])
    forward = np.array([0.0, -1.0, 0.0])  # towards the car
    right, down = np.cross(forward, [0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    R = np.stack([right, down, forward])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    unlit = np.array([1, 1, 1, 0, 0, 1, 0, 0, 0], dtype=np.float32)[None]
    drawn = Rasterizer(320, 200, cull_back_faces=True).render(meshes, T, K, lighting=unlit)
    p = R @ (point_m - eye)
    u, v = (K @ p)[:2] / p[2]
    r, c = int(round(v)), int(round(u))
    return drawn.rgb[0, r, c].numpy(), int(drawn.object_id[0, r, c])


def test_wheel_arches_are_lined_and_the_body_darkens_toward_the_ground():
    """Behind and in front of each tyre, below the cut-away hull, the camera sees the dark underbody (no background
    through the arch); the painted side is darker at the sill than at the belt line, and stays so when repainted."""
    shape = sample_vehicle_shape(np.random.default_rng(5), "sedan")
    white = Material(diffuse_rgb=(0.8, 0.8, 0.8))
    meshes = build_vehicle_meshes(shape, white, "full", object_id=3)
    r, axle_x = shape.wheel_radius_m, shape.wheelbase_fraction * shape.length_m / 2
    for x in (axle_x + 1.0 * r, axle_x - 1.0 * r, -axle_x + 1.0 * r):
        rgb, obj = _side_view_pixel(shape, np.array([x, shape.width_m / 2, 0.5 * r]), meshes)
        assert obj == 3, f"background seen through the arch at x = {x:.2f} m"
        assert rgb.max() < 0.06, f"arch at x = {x:.2f} m is not lined dark: {rgb}"
    belt_z = shape.belt_fraction * shape.height_m
    low, _ = _side_view_pixel(shape, np.array([0.0, shape.width_m / 2, 0.3]), meshes)
    high, _ = _side_view_pixel(shape, np.array([0.0, shape.width_m / 2, belt_z - 0.08]), meshes)
    assert low[0] < 0.7 * high[0] and high[0] > 0.6
    body = meshes[GROUP_NAMES.index("body")]
    z = body.vertices_m[:, 2]
    expected = BODY_OCCLUSION_FLOOR + (1.0 - BODY_OCCLUSION_FLOOR) * np.clip(z / belt_z, 0.0, 1.0)
    hull = z < belt_z - 0.01  # the hull's vertices below the belt line; roof and pillars stand above it
    np.testing.assert_allclose(body.vertex_rgb[hull, 0], expected[hull], atol=1e-3)
    assert body.vertex_rgb.max() == 1.0
    assert repaint(meshes, sample_paint(np.random.default_rng(0)))[0].vertex_rgb is body.vertex_rgb


def test_trim_and_wheel_parts_at_each_level_of_detail():
    """Full detail: four tyres with hubs, the underbody, both valances and the grille as separate closed parts; light
    detail keeps the tyres and the underbody only. The trim is dark plastic."""
    shape = sample_vehicle_shape(np.random.default_rng(2), "hatchback")
    paint = sample_paint(np.random.default_rng(2))
    for detail, wheel_parts, trim_parts in (("full", 8, 4), ("light", 4, 1)):
        meshes = build_vehicle_meshes(shape, paint, detail)
        wheels = trimesh.Trimesh(meshes[GROUP_NAMES.index("wheels")].vertices_m, meshes[2].faces, process=True)
        trim_mesh = meshes[GROUP_NAMES.index("trim")]
        trim = trimesh.Trimesh(trim_mesh.vertices_m, trim_mesh.faces, process=True)
        assert len(wheels.split(only_watertight=True)) == wheel_parts, detail
        assert len(trim.split(only_watertight=True)) == trim_parts, detail
        assert trim_mesh.vertex_rgb.max() <= PART_RANGES["trim_albedo"][1]
    front = build_vehicle_meshes(shape, paint, "full")[GROUP_NAMES.index("trim")].vertices_m
    assert front[:, 0].max() == pytest.approx(shape.length_m / 2 - 0.004, abs=2e-3)  # the grille and valance
    assert front[:, 2].min() == pytest.approx(0.08)  # the underbody's floor


def test_part_materials_are_sampled_in_their_ranges_and_per_seed():
    rng = np.random.default_rng(0)
    parts = [sample_part_materials(rng) for _ in range(2000)]
    R = PART_RANGES
    glass = np.array([p.glass.diffuse_rgb for p in parts])
    assert R["glass_albedo"][0] * 0.85 - 1e-9 <= glass.min() and glass.max() <= R["glass_albedo"][1]
    assert (glass[:, 2] >= glass[:, 0]).mean() > 0.9  # tinted toward blue-green
    for name, values in (
        ("glass_specular", [p.glass.specular_rgb[0] for p in parts]),
        ("glass_shininess", [p.glass.shininess for p in parts]),
        ("glass_roughness", [p.glass.roughness for p in parts]),
        ("rubber_roughness", [p.rubber.roughness for p in parts]),
        ("rubber_shininess", [p.rubber.shininess for p in parts]),
        ("trim_albedo", [p.trim_rgb[0] for p in parts]),
        ("trim_roughness", [p.trim.roughness for p in parts]),
        ("trim_shininess", [p.trim.shininess for p in parts]),
        ("lens_specular", [p.lens.specular_rgb[0] for p in parts]),
        ("lens_roughness", [p.lens.roughness for p in parts]),
        ("hub_albedo", [p.hub_rgb[0] for p in parts]),
    ):
        values = np.asarray(values)
        assert R[name][0] <= values.min() and values.max() <= R[name][1], name
        assert values.max() - values.min() > 0.5 * (R[name][1] - R[name][0]), f"{name} barely varies"
    hubs = np.array([p.hub_rgb[0] for p in parts])
    assert 0.6 < (hubs >= 0.3).mean() < 0.8  # alloy hubs on most cars, black steel on the rest
    a, b, c = (VehicleLibrary.procedural(3, seed=s).models for s in (7, 7, 8))
    for x, y, z in zip(a, b, c, strict=True):
        assert [m.material for m in x.full[1:]] == [m.material for m in y.full[1:]]  # the same per seed
        assert x.full[1].material != z.full[1].material  # another seed, other glass
        assert x.full[1].material == x.light[1].material  # both levels of detail share the car's parts
    assert len({m.full[1].material.diffuse_rgb for m in a}) == 3  # each car its own glass
