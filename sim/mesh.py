"""Triangle meshes and their materials: what the rasterizer draws (vehicles, and the synthetic world).

Material parameters follow the paper (§III-A, Fig. 3B): diffuse colour, specular colour, specular highlight
(Blinn–Phong shininess exponent), metalness and roughness.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Material:
    """Surface appearance under Blinn–Phong / PBR-lite shading.

    :param diffuse_rgb: base colour, linear RGB in [0, 1].
    :param specular_rgb: specular colour, linear RGB in [0, 1].
    :param shininess: Blinn–Phong specular exponent (the paper's "specular highlight"), 1..512.
    :param metalness: 0 = dielectric, 1 = metal (tints specular by the diffuse colour), [0, 1].
    :param roughness: 0 = mirror-like, 1 = fully rough (damps the highlight), [0, 1].
    :param unlit: draw the colour as is, without lighting (sky, emissive lights).
    """

    diffuse_rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    specular_rgb: tuple[float, float, float] = (0.04, 0.04, 0.04)
    shininess: float = 32.0
    metalness: float = 0.0
    roughness: float = 0.5
    unlit: bool = False


@dataclass
class Mesh:
    """A triangle mesh in its own object frame (metres).

    :param vertices_m: (V, 3) float32 vertex positions.
    :param faces: (F, 3) int64 (or int32) vertex indices, counter-clockwise seen from outside.
    :param vertex_rgb: (V, 3) float32 per-vertex colour in [0, 1] multiplying the material's diffuse colour, or None.
    :param uv: (V, 2) float32 texture coordinates in [0, 1] (u right, v down), or None.
    :param texture_rgb: (Ht, Wt, 3) uint8 texture sampled at `uv`, or None.
    :param normals: (V, 3) float32 unit vertex normals, or None for flat (per-face) normals.
    :param material: the surface material.
    :param object_id: id written to the rasterizer's object mask (>= 0; -1 is background).
    """

    vertices_m: np.ndarray
    faces: np.ndarray
    vertex_rgb: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture_rgb: np.ndarray | None = None
    normals: np.ndarray | None = None
    material: Material = field(default_factory=Material)
    object_id: int = 0

    @property
    def triangle_count(self) -> int:
        """Number of triangles."""
        return int(len(self.faces))

    def transformed(self, T: np.ndarray) -> Mesh:
        """A copy with vertices (and normals) moved by the 4x4 transform `T`."""
        R, t = T[:3, :3], T[:3, 3]
        normals = None if self.normals is None else (self.normals @ R.T).astype(np.float32)
        return Mesh(
            vertices_m=(self.vertices_m @ R.T + t).astype(np.float32),
            faces=self.faces,
            vertex_rgb=self.vertex_rgb,
            uv=self.uv,
            texture_rgb=self.texture_rgb,
            normals=normals,
            material=self.material,
            object_id=self.object_id,
        )
