"""Small geometry builders for the synthetic world: boxes, prisms, blobs, and a buffer that merges them into Meshes.

Everything is built directly in world coordinates (metres, z up) so that one Mesh per kind of surface holds many
objects: the rasterizer's cost grows with meshes and pixels, not with how objects are grouped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drivesim.sim.mesh import Material, Mesh


@dataclass
class MeshBuffer:
    """Accumulates triangles (with optional uv, vertex colours and normals) and builds one Mesh from them."""

    vertices: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray | None] = field(default_factory=list)
    rgb: list[np.ndarray | None] = field(default_factory=list)
    normals: list[np.ndarray | None] = field(default_factory=list)
    count: int = 0

    def add(
        self,
        vertices_m: np.ndarray,
        faces: np.ndarray,
        uv: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
        normals: np.ndarray | None = None,
    ) -> None:
        """Append a piece; its faces index its own vertices. A part not given (uv, rgb, normals) is filled at `build`
        only if the mesh has it (zeros, white, zeros), so a long road's pieces hold no unused arrays."""
        n = len(vertices_m)
        self.vertices.append(np.asarray(vertices_m, np.float32))
        self.faces.append(np.asarray(faces, np.int64) + self.count)
        self.uv.append(None if uv is None else np.asarray(uv, np.float32))
        self.rgb.append(None if rgb is None else np.broadcast_to(np.asarray(rgb, np.float32), (n, 3)))
        self.normals.append(None if normals is None else np.asarray(normals, np.float32))
        self.count += n

    def _joined(self, parts: list[np.ndarray | None], fill: float, width: int) -> np.ndarray:
        """The pieces' `parts` in one (V, width) float32 array, a piece without them filled with `fill`."""
        return np.concatenate([
            np.full((len(v), width), fill, np.float32) if p is None else p
            for v, p in zip(self.vertices, parts, strict=True)
        ])  # fmt: skip

    def build(
        self,
        material: Material,
        object_id: int,
        texture_rgb: np.ndarray | None = None,
        smooth: bool = False,
        coloured: bool = False,
    ) -> Mesh:
        """One Mesh of everything added: textured when `texture_rgb` is given, with vertex colours when `coloured`,
        with the given vertex normals when `smooth` (else flat shading)."""
        if not self.faces:
            return Mesh(
                np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), material=material, object_id=object_id
            )
        return Mesh(
            vertices_m=np.concatenate(self.vertices),
            faces=np.concatenate(self.faces).astype(np.int32 if self.count < 2**31 else np.int64),
            vertex_rgb=self._joined(self.rgb, 1.0, 3) if coloured else None,
            uv=self._joined(self.uv, 0.0, 2) if texture_rgb is not None else None,
            texture_rgb=texture_rgb,
            normals=self._joined(self.normals, 0.0, 3) if smooth else None,
            material=material,
            object_id=object_id,
        )


def quad_faces(n_quads: int, stride: int = 2) -> np.ndarray:
    """Faces of a strip of quads between two rows of vertices (row 0 then row 1 per column, `stride` apart)."""
    i = np.arange(n_quads) * stride
    a, b, c, d = i, i + 1, i + stride, i + stride + 1
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def box(
    centre_xy_m: np.ndarray, yaw_rad: float, length_m: float, width_m: float, z0_m: float, z1_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """An oriented box: (vertices (24, 3), faces (12, 3)) with 4 vertices per face (sides then top then bottom),
    side order: front (+x), left (+y), back, right; each face's vertices run (bottom-left, bottom-right,
    top-right, top-left) seen from outside, so face uv can be assigned per face."""
    hl, hw = length_m / 2, width_m / 2
    corners = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])  # front-right, front-left, back-left, back-right
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, -s], [s, c]])
    xy = corners @ R.T + np.asarray(centre_xy_m)[:2]
    verts = []
    for i in range(4):
        p, q = xy[i], xy[(i + 1) % 4]
        verts += [[*p, z0_m], [*q, z0_m], [*q, z1_m], [*p, z1_m]]
    verts += [[*xy[k], z1_m] for k in range(4)]
    verts += [[*xy[k], z0_m] for k in (3, 2, 1, 0)]
    faces = []
    for f in range(6):
        o = 4 * f
        faces += [[o, o + 1, o + 2], [o, o + 2, o + 3]]
    return np.array(verts, float), np.array(faces)


def prism(
    centre_xyz_m: np.ndarray, radius_m: float, height_m: float, sides: int, axis: str = "z", yaw_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed regular prism (cylinder approximation) along z, or along the local y axis rotated by `yaw_rad`
    (`axis="y"`, a wheel): (vertices, faces, outward smooth normals)."""
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], 1) * radius_m
    side_v, side_n = [], []
    for h in (-height_m / 2, height_m / 2):
        side_v.append(np.column_stack([ring, np.full(sides, h)]))
        side_n.append(np.column_stack([ring / radius_m, np.zeros(sides)]))
    v = np.concatenate(side_v + [np.array([[0, 0, -height_m / 2], [0, 0, height_m / 2]])])
    n = np.concatenate(side_n + [np.array([[0, 0, -1.0], [0, 0, 1.0]])])
    faces = []
    for i in range(sides):
        j = (i + 1) % sides
        faces += [[i, j, sides + j], [i, sides + j, sides + i]]
        faces += [[2 * sides, j, i], [2 * sides + 1, sides + i, sides + j]]
    if axis == "y":
        # local z -> y
        M = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
        v, n = v @ M.T, n @ M.T
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    v, n = v @ Rz.T + np.asarray(centre_xyz_m), n @ Rz.T
    return v, np.array(faces), n


def icosphere(subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere made by subdividing an icosahedron: (vertices, faces)."""
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t]]
    v += [[t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2]]
    faces += [[10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11]]
    faces += [[6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]

    def mid(i: int, j: int, cache: dict[tuple[int, int], int]) -> int:
        key = (min(i, j), max(i, j))
        if key not in cache:
            m = verts[i] + verts[j]
            verts.append(m / np.linalg.norm(m))
            cache[key] = len(verts) - 1
        return cache[key]

    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}
        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b, cache), mid(b, c, cache), mid(c, a, cache)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts), np.array(faces)
