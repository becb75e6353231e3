"""`drivesim meshes`: build, import (normalization into the vehicle frame), preview, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from cli_helpers import drivesim_ok
from PIL import Image

from drivesim.pipeline.errors import InputError
from drivesim.sim.vehicle_library import VehicleLibrary
from drivesim.stages.meshes.config import ImportConfig
from drivesim.stages.meshes.import_mesh import import_vehicle


def drivesim_fails(ws: Path, *args: str) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2, f"expected exit 2:\n{result.stdout}\n{result.stderr}"
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    return result


def car_like_file(path: Path, scale: float, up: str, forward: str) -> None:
    """A 4.4 x 1.8 x 1.45 m box car with a 0.3 m nose block at its front, written in the given units and axes,
    lifted and shifted off the origin (as a modelling tool would leave it)."""
    body = trimesh.creation.box(extents=[4.4, 1.8, 1.2])
    body.apply_translation([0.0, 0.0, 0.6])
    cabin = trimesh.creation.box(extents=[2.0, 1.6, 0.25])
    cabin.apply_translation([-0.3, 0.0, 1.325])
    nose = trimesh.creation.box(extents=[0.3, 0.6, 0.3])
    nose.apply_translation([2.35, 0.0, 0.5])  # the front: bumper to 2.5 m, so the car is 4.7 m long
    for part, rgb in ((body, (200, 30, 30)), (cabin, (20, 20, 30)), (nose, (220, 220, 220))):
        part.visual.face_colors = (*rgb, 255)
    axis = {"x": 0, "y": 1, "z": 2}
    R = np.zeros((3, 3))  # vehicle frame -> file frame: x (forward) -> `forward`, z (up) -> `up`
    R[axis[forward], 0] = 1.0
    R[axis[up], 2] = 1.0
    R[:, 1] = np.cross(R[:, 2], R[:, 0])
    T = np.eye(4)
    T[:3, :3] = R * scale
    T[:3, 3] = np.array([3.0, -1.0, 0.5]) * scale
    scene = trimesh.Scene()
    for i, part in enumerate((body, cabin, nose)):
        scene.add_geometry(part, node_name=f"part{i}", transform=T)
    scene.export(path)


@pytest.mark.parametrize(
    ("suffix", "scale", "up", "forward", "options"),
    [(".glb", 1000.0, "y", "z", {}), (".ply", 1.0, "z", "x", {}), (".obj", 100.0, "y", "x", {"forward_axis": "+x"})],
)
def test_import_normalizes_into_the_vehicle_frame_at_real_size(tmp_path, suffix, scale, up, forward, options):
    path = tmp_path / f"car{suffix}"
    car_like_file(path, scale, up, forward)
    model = import_vehicle(ImportConfig(path=str(path), **options))
    v = np.concatenate([m.vertices_m for m in model.full])
    np.testing.assert_allclose(v.max(0) - v.min(0), [4.7, 1.8, 1.45], atol=1e-3)
    np.testing.assert_allclose([v[:, 0].max() + v[:, 0].min(), v[:, 1].max() + v[:, 1].min(), v[:, 2].min()], 0.0,
                               atol=1e-3)  # fmt: skip
    assert (model.length_m, model.width_m, model.height_m) == pytest.approx((4.7, 1.8, 1.45), abs=1e-3)
    # the nose (at the file's front) ends up at +x, the cabin on top (+z)
    front = v[v[:, 0] > 2.06]  # only the 0.6 m wide nose reaches past the body's front (2.05 m)
    assert len(front) and np.abs(front[:, 1]).max() == pytest.approx(0.3, abs=1e-3)
    assert front[:, 2].min() == pytest.approx(0.35, abs=1e-3)  # the nose is low: the file's up is +z here
    assert v[:, 2].max() == pytest.approx(1.45, abs=1e-3)


def test_import_keeps_colours_and_decimates_the_light_detail(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20k triangles
    sphere.apply_scale([2.3, 0.9, 0.7])
    sphere.visual.face_colors = (10, 80, 200, 255)
    path = tmp_path / "blob.glb"
    trimesh.Scene(sphere).export(path)
    model = import_vehicle(ImportConfig(path=str(path), up_axis="+z", forward_axis="+x", light_triangles=400))
    assert model.full[0].triangle_count == 20480
    assert 300 <= model.light[0].triangle_count <= 420
    colour = np.asarray(model.full[0].material.diffuse_rgb) * (
        1 if model.full[0].vertex_rgb is None else model.full[0].vertex_rgb.mean(0)
    )
    np.testing.assert_allclose(colour, np.array([10, 80, 200]) / 255, atol=0.02)
    assert model.length_m == pytest.approx(4.6, abs=0.01)


def test_import_given_length_and_bad_sizes(tmp_path):
    path = tmp_path / "car.ply"
    car_like_file(path, 1.0, "z", "x")
    model = import_vehicle(ImportConfig(path=str(path), length_m=3.76))  # 0.8 x
    assert (model.length_m, model.width_m, model.height_m) == pytest.approx((3.76, 1.44, 1.16), abs=1e-3)
    tiny = tmp_path / "tiny.ply"
    car_like_file(tiny, 1e-5, "z", "x")
    with pytest.raises(InputError, match="no sensible size"):
        import_vehicle(ImportConfig(path=str(tiny)))
    flat = tmp_path / "flat.ply"
    trimesh.creation.box(extents=[4.0, 1.8, 0.0001]).export(flat)
    with pytest.raises(InputError, match="no sensible size"):
        import_vehicle(ImportConfig(path=str(flat)))
    with pytest.raises(InputError, match="parallel"):
        import_vehicle(ImportConfig(path=str(path), up_axis="+x", forward_axis="-x"))


def test_build_import_preview_through_the_cli(tmp_path):
    ws = tmp_path / "ws"
    out = drivesim_ok(ws, "meshes", "build", "--count", "5", "--seed", "1").stdout
    assert "5 vehicles" in out
    manifest = json.loads((ws / "meshes" / "manifest.json").read_text())
    assert manifest["summary"]["model_count"] == 5 and 200 <= manifest["summary"]["light_triangles_mean"] <= 600
    assert "fresh" in drivesim_ok(ws, "meshes", "build", "--count", "5", "--seed", "1").stdout
    car = tmp_path / "mycar.glb"
    car_like_file(car, 1000.0, "y", "z")
    out = drivesim_ok(ws, "meshes", "import", str(car), "--name", "user-car").stdout
    assert "4.70 x 1.80 x 1.45 m" in out
    library = VehicleLibrary.load(ws / "meshes")
    assert [m.name for m in library.models][-1] == "user-car" and len(library.models) == 6
    user = library.models[-1]
    assert (user.length_m, user.width_m, user.height_m) == pytest.approx((4.7, 1.8, 1.45), abs=1e-3)
    # a rebuild keeps the import
    drivesim_ok(ws, "meshes", "build", "--count", "3", "--seed", "1")
    assert [m.name for m in VehicleLibrary.load(ws / "meshes").models][-1] == "user-car"
    png = tmp_path / "sheet.png"
    drivesim_ok(ws, "meshes", "preview", "--out", str(png))
    sheet = np.asarray(Image.open(png).convert("RGB")).astype(float)
    assert sheet.shape[1] == 4 * 320
    # every tile shows a car: pixels far from the grey ground and the sky in the middle of each tile
    for i in range(4):
        tile = sheet[60:180, i * 320 + 80 : i * 320 + 240]
        assert (np.abs(tile - tile.mean((0, 1))).sum(-1) > 60).mean() > 0.05


@pytest.mark.parametrize(
    ("name", "content", "args", "message"),
    [
        ("notes.obj", b"hello, this is no mesh\n", (), "no triangles"),
        ("empty.ply", b"", (), "empty"),
        ("broken.glb", b"glTF\x02\x00\x00\x00garbage", (), "not a readable mesh"),
        ("car.stl", None, ("--length-m", "0.1"), "--length-m"),
        ("car.txt", b"v 0 0 0\n", (), "not a supported mesh file"),
        ("tiny.ply", "tiny", (), "no sensible size"),
    ],
)
def test_bad_mesh_files_exit_2_with_one_line_and_no_artifact(tmp_path, name, content, args, message):
    path = tmp_path / name
    if content is None:
        trimesh.creation.box(extents=[4.0, 1.8, 1.5]).export(path)
    elif content == "tiny":
        car_like_file(path, 1e-5, "z", "x")
    else:
        path.write_bytes(content)
    ws = tmp_path / "ws"
    result = drivesim_fails(ws, "meshes", "import", str(path), *args)
    assert message in result.stderr
    assert not (ws / "meshes").exists()
    assert not any(p.name.startswith(".") and "meshes" in p.name for p in ws.glob("*")) if ws.exists() else True


def test_a_failed_import_leaves_the_library_as_it_was(tmp_path):
    ws = tmp_path / "ws"
    drivesim_ok(ws, "meshes", "build", "--count", "2")
    before = (ws / "meshes" / "library.json").read_text()
    bad = tmp_path / "bad.obj"
    bad.write_text("not a mesh\n")
    drivesim_fails(ws, "meshes", "import", str(bad))
    assert (ws / "meshes" / "library.json").read_text() == before
    assert len(VehicleLibrary.load(ws / "meshes").models) == 2
