"""Import a user's vehicle mesh (.obj / .glb / .gltf / .ply / .stl) into the vehicle frame at its real size.

The file is read with trimesh (a scene is flattened with its node transforms); its axes are turned so the front
points along +x and up along +z; it is scaled to the real length, its footprint centred on the origin and its
lowest point put on the ground (z = 0). Each geometry keeps its own material (glTF PBR base colour, metallic and
roughness factors; otherwise the file's colour), and the light level of detail is a quadric decimation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.vehicle_library import VehicleModel, model_from_meshes
from drivesim.stages.meshes.config import ImportConfig

SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".stl")
_GLTF_LIKE = (".obj", ".glb", ".gltf")
CAR_LENGTH_RANGE_M = (2.0, 12.0)
_UNIT_SCALES = ((1.0, "m"), (0.01, "cm"), (0.001, "mm"))

_AXES = {"+x": (1.0, 0, 0), "-x": (-1.0, 0, 0), "+y": (0, 1.0, 0), "-y": (0, -1.0, 0), "+z": (0, 0, 1.0),
         "-z": (0, 0, -1.0)}  # fmt: skip


def axes_rotation(up_axis: str, forward_axis: str) -> np.ndarray:
    """3x3 rotation taking the file's forward axis to +x and its up axis to +z (InputError if they are parallel)."""
    up, forward = np.array(_AXES[up_axis]), np.array(_AXES[forward_axis])
    if abs(up @ forward) > 0.5:
        raise InputError(f"up axis {up_axis} and forward axis {forward_axis} are parallel: pick two different axes")
    left = np.cross(up, forward)
    return np.stack([forward, left, up])  # rows: the vehicle axes expressed in the file's frame


def resolved_axes(cfg: ImportConfig) -> tuple[str, str]:
    """The (up, forward) axes with "auto" replaced by the file type's convention."""
    gltf_like = Path(cfg.path).suffix.lower() in _GLTF_LIKE
    up = cfg.up_axis if cfg.up_axis != "auto" else ("+y" if gltf_like else "+z")
    forward = cfg.forward_axis if cfg.forward_axis != "auto" else ("+z" if gltf_like else "+x")
    return up, forward


def _material_of(geometry) -> tuple[Material, np.ndarray | None]:
    """The material of a trimesh geometry (PBR factors where the file has them) and per-vertex colours."""
    visual = geometry.visual
    if visual.kind == "vertex":
        rgb = np.asarray(visual.vertex_colors)[:, :3].astype(np.float32) / 255.0
        return Material(diffuse_rgb=(1.0, 1.0, 1.0), roughness=0.5), rgb
    material = getattr(visual, "material", None)
    base = getattr(material, "baseColorFactor", None)
    if base is not None:
        rgb = np.asarray(base, dtype=np.float64)[:3]
        rgb = rgb / 255.0 if rgb.max() > 1.0 else rgb
        metallic = getattr(material, "metallicFactor", None)
        roughness = getattr(material, "roughnessFactor", None)
        return Material(
            diffuse_rgb=tuple(float(c) for c in rgb),
            metalness=float(0.0 if metallic is None else metallic),
            roughness=float(0.5 if roughness is None else roughness),
        ), None
    if visual.kind == "face":
        colour = np.asarray(visual.face_colors)[:, :3].mean(0) / 255.0
        return Material(diffuse_rgb=tuple(float(c) for c in colour)), None
    main = getattr(material, "main_color", None)
    if main is not None:
        return Material(diffuse_rgb=tuple(float(c) / 255.0 for c in np.asarray(main)[:3])), None
    return Material(diffuse_rgb=(0.6, 0.6, 0.6)), None


def _read_geometries(path: Path) -> list:
    """The file's triangle meshes with their scene transforms applied (InputError when it holds none)."""
    import trimesh

    if not path.is_file():
        raise InputError("no such mesh file", path)
    if path.suffix.lower() not in SUFFIXES:
        raise InputError(f"not a supported mesh file: expected one of {', '.join(SUFFIXES)}", path)
    if path.stat().st_size == 0:
        raise InputError("is empty (0 bytes): a vehicle needs a surface mesh", path)
    try:
        loaded = trimesh.load(path, force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for a file that is not a mesh
        raise InputError(
            f"not a readable mesh ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})", path
        ) from None
    geometries = []
    for geometry in loaded.dump(concatenate=False) if isinstance(loaded, trimesh.Scene) else [loaded]:
        if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces) > 0:
            geometries.append(geometry)
    if not geometries:
        raise InputError("holds no triangles (empty, or only points / lines): a vehicle needs a surface mesh", path)
    return geometries


def _scale_to_metres(length_file: float, cfg: ImportConfig, path: Path) -> float:
    """The factor from file units to metres: from the given real length, or the unit that makes it a car."""
    if not np.isfinite(length_file) or length_file <= 1e-9:
        raise InputError("has no sensible size (its extent along the forward axis is zero)", path)
    if cfg.length_m is not None:
        return cfg.length_m / length_file
    low, high = CAR_LENGTH_RANGE_M
    for scale, _unit in _UNIT_SCALES:
        if low <= length_file * scale <= high:
            return scale
    raise InputError(
        f"has no sensible size: {length_file:.4g} units long along the forward axis is no car in m, cm or mm; "
        "pass its real length with --length-m (and check --up/--forward)",
        path,
    )


def _decimated(mesh: Mesh, target_faces: int) -> Mesh:
    """The mesh reduced to about `target_faces` triangles (quadric decimation), or itself when already small."""
    import trimesh

    if mesh.triangle_count <= target_faces:
        return mesh
    tm = trimesh.Trimesh(mesh.vertices_m, mesh.faces, process=False)
    small = tm.simplify_quadric_decimation(face_count=target_faces)
    return Mesh(
        vertices_m=np.asarray(small.vertices, dtype=np.float32),
        faces=np.asarray(small.faces, dtype=np.int64),
        material=mesh.material,
        object_id=mesh.object_id,
    )


def import_vehicle(cfg: ImportConfig) -> VehicleModel:
    """The user's mesh file as a library model in the vehicle frame at its real size (InputError on bad input)."""
    path = Path(cfg.path)
    geometries = _read_geometries(path)
    up, forward = resolved_axes(cfg)
    R = axes_rotation(up, forward)
    rotated = [np.asarray(g.vertices, dtype=np.float64) @ R.T for g in geometries]
    allv = np.concatenate(rotated)
    if not np.all(np.isfinite(allv)):
        raise InputError("has no sensible size (vertices that are not finite numbers)", path)
    lo, hi = allv.min(0), allv.max(0)
    scale = _scale_to_metres(float(hi[0] - lo[0]), cfg, path)
    size = (hi - lo) * scale
    if size[1] < 0.5 or size[2] < 0.5 or size[1] > 5.0 or size[2] > 6.0:
        raise InputError(
            f"has no sensible size for a vehicle: {size[0]:.2f} x {size[1]:.2f} x {size[2]:.2f} m "
            "(length x width x height); check --up/--forward and --length-m",
            path,
        )
    offset = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    full = []
    for geometry, vertices in zip(geometries, rotated, strict=True):
        material, rgb = _material_of(geometry)
        full.append(
            Mesh(
                vertices_m=((vertices - offset) * scale).astype(np.float32),
                faces=np.asarray(geometry.faces, dtype=np.int64),
                vertex_rgb=rgb,
                material=material,
            )
        )
    total = sum(m.triangle_count for m in full)
    light = [_decimated(m, max(12, int(cfg.light_triangles * m.triangle_count / total))) for m in full]
    # decimation drops vertex colours: keep the uncoloured light mesh in the group's mean colour
    for i, m in enumerate(full):
        if m.vertex_rgb is not None and light[i] is not m:
            mean = tuple(float(c) for c in m.vertex_rgb.mean(0))
            light[i] = Mesh(light[i].vertices_m, light[i].faces, material=Material(diffuse_rgb=mean))
    name = cfg.name or path.stem
    return model_from_meshes(name, full, light, paint_group=None)
