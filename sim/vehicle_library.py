"""The vehicle library: the cars the simulator inserts into each agent's view.

Loaded from the `meshes/` artifact (`drivesim meshes build` / `meshes import`) or made procedurally in memory.

Artifact layout (written by `stages/meshes/build.py`)::

    meshes/library.json                 {"format": 1, "models": [{"name", "length_m", "width_m", "height_m",
                                          "source", "groups": [...], "paint_group": "body" | null}, ...]}
    meshes/<name>/materials.json        {group: {diffuse_rgb, specular_rgb, shininess, metalness, roughness, unlit}}
    meshes/<name>/<detail>/<group>.ply  one closed mesh per material group and level of detail (vertex colours kept)
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.vehicles import (
    GROUP_NAMES,
    build_vehicle_meshes,
    sample_paint,
    sample_part_materials,
    sample_vehicle_shape,
)

LIBRARY_FORMAT = 1
LIBRARY_INDEX = "library.json"
MATERIALS_FILE = "materials.json"


@dataclass
class VehicleModel:
    """One vehicle at two levels of detail, in the vehicle frame (x forward, z up, origin at the centre of the
    footprint on the ground).

    :param name: unique name in its library.
    :param length_m: bounding length. :param width_m: bounding width. :param height_m: bounding height.
    :param full: the meshes to look at, one per material group.
    :param light: the meshes for the policy's small view (a few hundred triangles), same groups.
    :param paint_group: index of the group `repainted` changes (the body), or None when it has none (an import
        without a body group keeps its own materials).
    """

    name: str
    length_m: float
    width_m: float
    height_m: float
    full: list[Mesh]
    light: list[Mesh]
    paint_group: int | None = 0

    def repainted(self, paint: Material) -> VehicleModel:
        """The same shape with the body in a new material (meshes shared, not copied)."""
        if self.paint_group is None:
            return self
        i = self.paint_group

        def swap(meshes: list[Mesh]) -> list[Mesh]:
            return [replace(m, material=paint) if k == i else m for k, m in enumerate(meshes)]

        return replace(self, full=swap(self.full), light=swap(self.light))


class VehicleLibrary:
    """A set of vehicle models to draw other cars from.

    :param models: the models (at least one).
    """

    def __init__(self, models: list[VehicleModel]):
        if not models:
            raise ValueError("a vehicle library needs at least one model")
        self.models = list(models)

    @classmethod
    def procedural(cls, count: int = 8, seed: int = 0) -> VehicleLibrary:
        """`count` procedural vehicles (body types in turn, shapes and paints from `seed`), in memory."""
        return cls(procedural_models(count, seed))

    @classmethod
    def load(cls, root: Path | str) -> VehicleLibrary:
        """The library of a `meshes/` artifact; FileNotFoundError / ValueError with one line naming the bad file."""
        root = Path(root)
        index_path = root / LIBRARY_INDEX
        if not index_path.is_file():
            raise FileNotFoundError(
                f"no vehicle library at {root}: {LIBRARY_INDEX} is missing (run drivesim meshes build)"
            )
        try:
            index = json.loads(index_path.read_text())
            entries = index["models"]
            if index.get("format") != LIBRARY_FORMAT:
                raise ValueError(f"format {index.get('format')!r}, expected {LIBRARY_FORMAT}")
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(
                f"{index_path} is not a vehicle library index ({exc}); rebuild with drivesim meshes build"
            ) from None
        return cls([load_model(root, entry) for entry in entries])

    def sample(self, rng: np.random.Generator, repaint: bool = True) -> VehicleModel:
        """A model drawn uniformly, with a fresh paint from `sim.vehicles.sample_paint` when `repaint`."""
        model = self.models[int(rng.integers(len(self.models)))]
        return model.repainted(sample_paint(rng)) if repaint else model


def procedural_models(count: int, seed: int) -> list[VehicleModel]:
    """`count` procedural models: body types in turn (sedan, hatchback, SUV, van, pickup), shapes, paints and the
    other parts' materials drawn from `seed` (the parts from a stream of their own per model)."""
    from drivesim.sim.vehicles import BODY_TYPES

    rng = np.random.default_rng(seed)
    models = []
    for i in range(count):
        body_type = BODY_TYPES[i % len(BODY_TYPES)]
        shape = sample_vehicle_shape(rng, body_type)
        paint = sample_paint(rng)
        parts = sample_part_materials(np.random.default_rng([seed, i]))
        full = build_vehicle_meshes(shape, paint, "full", parts=parts)
        light = build_vehicle_meshes(shape, paint, "light", parts=parts)
        models.append(model_from_meshes(f"{body_type}-{i:02d}", full, light, paint_group=0))
    return models


def model_from_meshes(name: str, full: list[Mesh], light: list[Mesh], paint_group: int | None) -> VehicleModel:
    """A model whose bounding size is measured from its full meshes."""
    vertices = np.concatenate([m.vertices_m for m in full])
    size = vertices.max(0) - vertices.min(0)
    return VehicleModel(
        name=name,
        length_m=float(size[0]),
        width_m=float(size[1]),
        height_m=float(size[2]),
        full=full,
        light=light,
        paint_group=paint_group,
    )


# ---------------------------------------------------------------------------------------------- files
def material_to_json(material: Material) -> dict:
    """A material as plain JSON values."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(material).items()}


def material_from_json(data: dict) -> Material:
    """The inverse of `material_to_json`."""
    return Material(
        diffuse_rgb=tuple(float(c) for c in data["diffuse_rgb"]),
        specular_rgb=tuple(float(c) for c in data["specular_rgb"]),
        shininess=float(data["shininess"]),
        metalness=float(data["metalness"]),
        roughness=float(data["roughness"]),
        unlit=bool(data.get("unlit", False)),
    )


def save_model(root: Path, model: VehicleModel, groups: list[str], source: str) -> dict:
    """Write one model's .ply files and materials.json under `root/<name>/`; its index entry."""
    import trimesh

    folder = root / model.name
    materials = {}
    for detail, meshes in (("full", model.full), ("light", model.light)):
        (folder / detail).mkdir(parents=True, exist_ok=True)
        for group, mesh in zip(groups, meshes, strict=True):
            colours = None
            if mesh.vertex_rgb is not None:
                colours = np.clip(np.round(mesh.vertex_rgb * 255.0), 0, 255).astype(np.uint8)
            tm = trimesh.Trimesh(mesh.vertices_m, mesh.faces, vertex_colors=colours, process=False)
            tm.export(folder / detail / f"{group}.ply")
            materials[group] = material_to_json(mesh.material)
    (folder / MATERIALS_FILE).write_text(json.dumps(materials, indent=1))
    return {
        "name": model.name,
        "length_m": model.length_m,
        "width_m": model.width_m,
        "height_m": model.height_m,
        "source": source,
        "groups": groups,
        "paint_group": None if model.paint_group is None else groups[model.paint_group],
    }


def save_library(root: Path, models: list[VehicleModel], sources: list[str]) -> None:
    """Write `models` (each with its source: "procedural" or the imported file's name) and the index under `root`.

    Procedural models have the groups `GROUP_NAMES`; other models name theirs "body" (the paint group, if any)
    and "part<i>"."""
    entries = []
    for model, source in zip(models, sources, strict=True):
        if len(model.full) == len(GROUP_NAMES) and source == "procedural":
            groups = list(GROUP_NAMES)
        else:
            groups = [("body" if i == model.paint_group else f"part{i}") for i in range(len(model.full))]
        entries.append(save_model(root, model, groups, source))
    (root / LIBRARY_INDEX).write_text(json.dumps({"format": LIBRARY_FORMAT, "models": entries}, indent=1))


def read_index(root: Path) -> list[dict]:
    """The model entries of a library index (empty when there is none)."""
    path = Path(root) / LIBRARY_INDEX
    return json.loads(path.read_text())["models"] if path.is_file() else []


def load_model(root: Path, entry: dict) -> VehicleModel:
    """One model of a library from its index entry (ValueError / FileNotFoundError with one line)."""
    import trimesh

    try:
        name, groups = str(entry["name"]), list(entry["groups"])
    except (KeyError, TypeError) as exc:
        raise ValueError(
            f"{root / LIBRARY_INDEX}: a model entry lacks {exc}; rebuild with drivesim meshes build"
        ) from None
    folder = root / name
    materials_path = folder / MATERIALS_FILE
    if not materials_path.is_file():
        raise FileNotFoundError(f"vehicle library file missing: {materials_path}")
    try:
        materials = {g: material_from_json(m) for g, m in json.loads(materials_path.read_text()).items()}
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{materials_path} is not a materials file ({exc})") from None
    lods = {}
    for detail in ("full", "light"):
        meshes = []
        for group in groups:
            path = folder / detail / f"{group}.ply"
            if not path.is_file():
                raise FileNotFoundError(f"vehicle library file missing: {path}")
            if group not in materials:
                raise ValueError(f"{materials_path} has no material for group {group!r}")
            try:
                tm = trimesh.load(path, file_type="ply", process=False, force="mesh")
            except Exception as exc:  # trimesh raises many types for a damaged file
                raise ValueError(f"{path} is not a readable mesh ({type(exc).__name__}: {exc})") from None
            if len(tm.faces) == 0:
                raise ValueError(f"{path} has no triangles")
            rgb = None
            colours = getattr(tm.visual, "vertex_colors", None)
            if tm.visual.kind == "vertex" and colours is not None and len(colours) == len(tm.vertices):
                rgb = (np.asarray(colours)[:, :3] / 255.0).astype(np.float32)
            meshes.append(
                Mesh(
                    vertices_m=np.asarray(tm.vertices, dtype=np.float32),
                    faces=np.asarray(tm.faces, dtype=np.int64),
                    vertex_rgb=rgb,
                    material=materials[group],
                )
            )
        lods[detail] = meshes
    paint = entry.get("paint_group")
    model = model_from_meshes(name, lods["full"], lods["light"], groups.index(paint) if paint in groups else None)
    return model


__all__ = [
    "VehicleLibrary",
    "VehicleModel",
    "load_model",
    "material_from_json",
    "material_to_json",
    "model_from_meshes",
    "procedural_models",
    "read_index",
    "save_library",
    "save_model",
]
