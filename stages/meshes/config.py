"""The `drivesim meshes` config (preset configs/meshes.yaml)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from drivesim.pipeline.config import StageConfig

Axis = Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"]


class ImportConfig(StageConfig):
    """One user mesh file imported into the library, normalized into the vehicle frame at its real size."""

    path: str
    """The .obj / .glb / .gltf / .ply file (absolute path)."""
    name: str | None = None
    """Model name in the library; default the file's stem."""
    up_axis: Axis = "auto"
    """The file's up axis; auto: +y for .obj / .glb / .gltf (the glTF convention), +z for .ply / .stl."""
    forward_axis: Axis = "auto"
    """The axis the car's front points along in the file; auto: +z for .obj / .glb / .gltf (glTF), +x otherwise."""
    length_m: float | None = Field(None, gt=0.5, le=25.0)
    """Real bumper-to-bumper length (m) the model is scaled to; default: the file's own size when it reads as a
    car in metres, centimetres or millimetres (2-12 m once converted)."""
    light_triangles: int = Field(600, ge=50, le=20000)
    """Triangle budget of the light level of detail (quadric decimation of the full mesh)."""


class MeshesConfig(StageConfig):
    """The vehicle library: procedural vehicles (sedan, hatchback, SUV, van, pickup) plus imported user meshes."""

    count: int = Field(10, ge=0, le=500)
    """Procedural vehicles in the library (body types in turn)."""
    seed: int = Field(0, ge=0)
    """Seed of the procedural shapes and paints."""
    imports: list[ImportConfig] = []
    """User meshes added with `drivesim meshes import` (kept so a rebuild keeps them)."""
