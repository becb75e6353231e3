"""The synth world's ground-truth renderer: the world's faces cut down to the cells near the camera, packed once per
set of cells, and drawn by the rasterizer's compiled kernels (set-up and depth test, `sim.raster_kernel`) and the
synth's own compiled per-pixel pass (`render_kernel.shade_world`: texture, shading, haze, uint8).

Why not `sim.raster.Rasterizer.render`: its textured path resolves pixels through whole-image torch operations
(about two thirds of a frame's time on one core), and it keeps up to 16 packings of the mesh lists it is given, each
with a copy of every texture; the synth world hands it a new cut-down list every few metres of driving.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from drivesim.sim.mesh import Mesh
from drivesim.sim.raster import Lighting, pack_meshes

NEAR_M = 0.05  # nearest drawn depth, as the rasterizer's default


@dataclass(frozen=True)
class FrameImages:
    """One rendered frame: colour (H, W, 3) uint8, depth (H, W) float32 m (+inf = sky), semantic object ids (H, W)
    int32 (-1 = sky)."""

    rgb: np.ndarray
    depth_m: np.ndarray
    object_id: np.ndarray


@dataclass(frozen=True)
class Sky:
    """What the sky looks like: cloud opacity (N, N) in [0, 1] on a periodic tile of the cloud layer, the colours
    at the zenith, at the horizon (also the haze's) and of the clouds, the cloud layer's height and tile size (m)."""

    clouds: np.ndarray
    zenith_rgb: np.ndarray
    horizon_rgb: np.ndarray
    cloud_rgb: np.ndarray
    cloud_height_m: float
    cloud_tile_m: float

    def table(self) -> np.ndarray:
        """(12,) float32 as `render_kernel.paint_sky` takes it."""
        row = np.zeros(12, np.float32)
        row[0:3], row[3:6], row[6:9] = self.zenith_rgb, self.horizon_rgb, self.cloud_rgb
        row[9], row[10] = self.cloud_height_m, self.cloud_tile_m
        return row


@dataclass(frozen=True)
class _Packed:
    """A PackedScene's tables as numpy arrays (the compiled kernels' inputs)."""

    origin_m: np.ndarray
    vertices: np.ndarray  # (3 xyz, 3 corners * T)
    attributes: np.ndarray
    material: np.ndarray
    object_id: np.ndarray
    texture_index: np.ndarray
    texels: np.ndarray
    texture_info: np.ndarray

    @classmethod
    def of(cls, meshes: list[Mesh]) -> _Packed:
        """`raster.pack_meshes(meshes)` with the texel table made here, 4 bytes a texel and no more: the rasterizer's
        packing goes through 12 bytes a texel, ~100 MB at a time for the facades near a camera."""
        stand_in = np.zeros((1, 1, 3), np.uint8)
        textures = [m.texture_rgb for m in meshes if m.texture_rgb is not None and m.uv is not None]
        scene = pack_meshes(
            [dataclasses.replace(m, texture_rgb=stand_in) if m.texture_rgb is not None else m for m in meshes]
        )
        n = scene.triangle_count
        return cls(
            origin_m=scene.origin_m,
            vertices=np.ascontiguousarray(scene.vertex_components.numpy().reshape(3, 3 * n)),
            attributes=scene.attribute_table.numpy(),
            material=scene.material.numpy(),
            object_id=scene.object_id.numpy(),
            texture_index=scene.texture_index.numpy(),
            texels=_texel_table(textures),
            texture_info=_texture_info(textures),
        )


def _texel_table(textures: list[np.ndarray]) -> np.ndarray:
    """(N,) int32 RGB8 texels of `textures` one after the other, r in the low byte (`raster.PackedScene.texels`)."""
    rgba = np.zeros((max(sum(t.shape[0] * t.shape[1] for t in textures), 1), 4), np.uint8)
    start = 0
    for t in textures:
        end = start + t.shape[0] * t.shape[1]
        rgba[start:end, :3] = t.reshape(-1, 3)
        start = end
    return rgba.view("<i4").reshape(-1).astype(np.int32, copy=False)


def _texture_info(textures: list[np.ndarray]) -> np.ndarray:
    """(3, X) int32 offset, width, height of each texture in the texel table."""
    sizes = np.array([[t.shape[1], t.shape[0]] for t in textures], np.int64).reshape(-1, 2)
    offsets = np.cumsum(sizes[:, 0] * sizes[:, 1]) - sizes[:, 0] * sizes[:, 1]
    return np.ascontiguousarray(np.stack([offsets, sizes[:, 0], sizes[:, 1]]).astype(np.int32))


@dataclass(frozen=True)
class Piece:
    """Part of one of the world's meshes (the part of a stretch of road): a mesh whose faces index its own vertices,
    and sort keys per face and per vertex that give their order in the whole mesh (not necessarily consecutive)."""

    mesh: Mesh
    face_keys: np.ndarray
    vertex_keys: np.ndarray


# a mesh of the world: the whole mesh, or the functions that make its pieces (each piece made when a camera comes near)
Source = Mesh | Sequence[Callable[[], Piece]]


class CellCulling:
    """The faces in the 40 m cells that come within the view distance of a camera, packed.

    Faces keep their mesh (one texture, one material per kind) and their order; only the face list shrinks. A mesh
    given in pieces is held only in the pieces that have faces in the current packing's cells: the others are made
    when a packing needs them and dropped when it no longer does, so the faces held do not grow with the road. A
    packing holds the cells within the view distance plus `MARGIN_M` of where it was made, and serves every camera
    within `MARGIN_M` of that place: each frame draws only its own cells' triangles of it (the same faces, in the
    same order).

    :param meshes: the world's meshes, each whole or in pieces (`Source`).
    :param textures: per mesh index, what makes that mesh's texture when a packing needs it (the mesh has none).
    :param whole_below_triangles: a world of up to this many triangles is held whole, every mesh as one mesh in its
        whole order: its packings are then those of the same meshes built whole, origin included.
    """

    CELL_M = 40.0
    MARGIN_M = 40.0

    def __init__(
        self,
        meshes: Sequence[Source],
        textures: dict[int, Callable[[], np.ndarray]] | None = None,
        whole_below_triangles: int = 0,
    ) -> None:
        self._sources: list[Mesh | list[Callable[[], Piece]]] = [m if isinstance(m, Mesh) else list(m) for m in meshes]
        self._make_texture = dict(textures or {})  # mesh index -> what makes its texture (the mesh has none)
        self._textures: dict[int, np.ndarray] = {}  # the made textures of the current packing's meshes
        self._held: dict[tuple[int, int], tuple[Piece, np.ndarray]] = {}  # (mesh, piece) -> piece, its faces' cells
        self.triangle_counts = [0] * len(self._sources)  # per mesh, filled by `_cell_stats`
        stats, kept = self._cell_stats(whole_below_triangles)
        keys = np.concatenate([k for _, _, k, _, _ in stats] or [np.zeros(0, np.int64)])
        order = np.argsort(keys, kind="stable")
        self.cell_keys, starts = np.unique(keys[order], return_index=True)
        lo = np.concatenate([lo for _, _, _, lo, _ in stats] or [np.zeros((0, 2))])[order]
        hi = np.concatenate([hi for _, _, _, _, hi in stats] or [np.zeros((0, 2))])[order]
        lo = np.minimum.reduceat(lo, starts).astype(np.float64) if len(starts) else np.zeros((0, 2))
        hi = np.maximum.reduceat(hi, starts).astype(np.float64) if len(starts) else np.zeros((0, 2))
        self.cell_centre = (lo + hi) / 2
        self.cell_radius = np.linalg.norm(hi - lo, axis=1) / 2
        # per mesh: its pieces with faces, and the cells each one has faces in (flat, with where each piece's start)
        self._pieces: list[list[int]] = [[] for _ in self._sources]
        cells: list[list[np.ndarray]] = [[] for _ in self._sources]
        for i, j, k, _, _ in stats:
            self._pieces[i].append(j)
            cells[i].append(np.searchsorted(self.cell_keys, k).astype(np.int32))
        self._piece_cells = [np.concatenate(c) if c else np.zeros(0, np.int32) for c in cells]
        self._piece_starts = [np.cumsum([0] + [len(x) for x in c[:-1]]) for c in cells]
        if kept is not None:
            self._hold_whole(kept)
        self._pack: tuple[np.ndarray, _Packed, np.ndarray] | None = None  # (made at xy, packing, its triangles' cells)

    def _hold_whole(self, pieces: list[list[Piece]]) -> None:
        """Hold every mesh whole (from its `pieces`), as one mesh in the whole mesh's order: packings then hold the
        same meshes as a whole build's (their origin, the mean of their vertices, too)."""
        for i, source in enumerate(self._sources):
            if isinstance(source, Mesh) or not self._pieces[i]:
                continue
            parts = pieces[i]
            order = np.argsort(np.concatenate([p.vertex_keys for p in parts]), kind="stable")
            where = np.empty(len(order), np.int64)
            where[order] = np.arange(len(order))  # a piece's vertex -> its place in the whole mesh
            offsets = np.cumsum([0] + [len(p.mesh.vertices_m) for p in parts[:-1]])
            faces = np.concatenate([where[p.mesh.faces + o] for p, o in zip(parts, offsets, strict=True)])
            faces = faces[np.argsort(np.concatenate([p.face_keys for p in parts]), kind="stable")]

            def joined(name: str, parts: list[Piece] = parts, order: np.ndarray = order) -> np.ndarray | None:
                arrays = [getattr(p.mesh, name) for p in parts]
                return None if arrays[0] is None else np.concatenate(arrays)[order]

            self._sources[i] = dataclasses.replace(
                parts[0].mesh,
                vertices_m=joined("vertices_m"),
                faces=faces.astype(parts[0].mesh.faces.dtype),
                vertex_rgb=joined("vertex_rgb"),
                uv=joined("uv"),
                normals=joined("normals"),
            )
            self._piece_cells[i] = np.unique(self._piece_cells[i])
            self._pieces[i], self._piece_starts[i] = [0], np.zeros(1, np.int64)

    @classmethod
    def _face_keys(cls, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
        """Each face's cell key, and its corners' xy (F, 3, 2)."""
        tri_xy = mesh.vertices_m[mesh.faces][:, :, :2]
        ij = np.floor(tri_xy.mean(axis=1) / cls.CELL_M).astype(np.int64)
        return ij[:, 0] * 1_000_003 + ij[:, 1], tri_xy

    def _piece(self, i: int, j: int) -> Piece:
        """Piece `j` of mesh `i` (a whole mesh is its own one piece)."""
        source = self._sources[i]
        if isinstance(source, Mesh):
            return Piece(source, np.arange(len(source.faces)), np.arange(len(source.vertices_m)))
        return source[j]()

    def _every_piece(self) -> Iterator[tuple[int, int, Piece]]:
        """(mesh, piece, the piece made) for every piece of every mesh, the pieces of one stretch (the same index in
        each mesh) one after another: they may share their making."""
        counts = [1 if isinstance(s, Mesh) else len(s) for s in self._sources]
        for j in range(max(counts, default=0)):
            for i in range(len(self._sources)):
                if j < counts[i]:
                    yield i, j, self._piece(i, j)

    def _cell_stats(
        self, keep_below_triangles: int
    ) -> tuple[list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]], list[list[Piece]] | None]:
        """(mesh, piece, its cell keys, their faces' lower and upper xy bounds) for every piece with faces, each
        piece made once; and the pieces with faces of each mesh given in pieces if the world has no more than
        `keep_below_triangles` (None else: the pieces were dropped as soon as they were more)."""
        stats = []
        kept: list[list[Piece]] | None = [[] for _ in self._sources]
        for i, j, piece in self._every_piece():
            mesh = piece.mesh
            if len(mesh.faces):
                self.triangle_counts[i] += len(mesh.faces)
                if kept is not None and sum(self.triangle_counts) > keep_below_triangles:
                    kept = None
                if kept is not None and not isinstance(self._sources[i], Mesh):
                    kept[i].append(piece)
                key, tri_xy = self._face_keys(mesh)
                order = np.argsort(key, kind="stable")
                keys, starts = np.unique(key[order], return_index=True)
                lo = np.minimum.reduceat(tri_xy.min(1)[order], starts)
                hi = np.maximum.reduceat(tri_xy.max(1)[order], starts)
                stats.append((i, j, keys, lo, hi))
        return stats, kept

    def near_cells(self, camera_xy_m: np.ndarray, distance_m: float) -> np.ndarray:
        """(cells,) bool: the cells that come within `distance_m` of the camera."""
        return np.linalg.norm(self.cell_centre - camera_xy_m, axis=1) - self.cell_radius < distance_m

    def _held_piece(self, i: int, j: int, held: dict[tuple[int, int], tuple[Piece, np.ndarray]]) -> tuple:
        """Piece `j` of mesh `i` and its faces' cells: the one held, else made; recorded in `held`."""
        part = self._held.get((i, j))
        if part is None:
            piece = self._piece(i, j)
            part = (piece, np.searchsorted(self.cell_keys, self._face_keys(piece.mesh)[0]))
        held[(i, j)] = part
        return part

    def visible_meshes(self, near: np.ndarray, keep: bool = True) -> tuple[list[Mesh], np.ndarray]:
        """The meshes with only the faces in the cells `near` (a mask over `cell_keys`), textures included, and each
        of their faces' cell (in the order of the meshes' faces). With `keep`, the pieces made are held until a later
        call no longer needs them (and the textures made kept as the current packing's)."""
        indices, meshes, face_cells = [], [], []
        held: dict[tuple[int, int], tuple[Piece, np.ndarray]] = {}
        for i in range(len(self._sources)):
            if not len(self._pieces[i]):
                continue
            hit = np.flatnonzero(np.logical_or.reduceat(near[self._piece_cells[i]], self._piece_starts[i]))
            if not len(hit):
                continue
            parts = [self._held_piece(i, self._pieces[i][h], held) for h in hit]
            mesh, cells = _joined(parts, near)
            indices.append(i)
            meshes.append(mesh)
            face_cells.append(cells)
        if keep:
            self._held = held
        textured = self._textured(indices, meshes, keep)
        return textured, np.concatenate(face_cells) if face_cells else np.zeros(0, np.int64)

    def _textured(self, indices: list[int], meshes: list[Mesh], keep: bool) -> list[Mesh]:
        """`meshes` (of indices `indices`) with their textures made on demand (or taken from the current packing's);
        with `keep`, the made ones are kept as the current packing's (and the others dropped)."""
        made = {}
        for i in indices:
            if i in self._make_texture:
                made[i] = self._textures[i] if i in self._textures else self._make_texture[i]()
        if keep:
            self._textures = made
        return [
            dataclasses.replace(m, texture_rgb=made[i]) if i in made else m
            for i, m in zip(indices, meshes, strict=True)
        ]

    def whole_meshes(self) -> list[Mesh]:
        """Every mesh whole (each piece made), textures included; nothing held."""
        return self.visible_meshes(np.ones(len(self.cell_keys), bool), keep=False)[0]

    def scene(self, camera_xy_m: np.ndarray, view_distance_m: float) -> tuple[_Packed, np.ndarray | None]:
        """The packing that holds the cells within `view_distance_m` of the camera, and which of its triangles lie
        in them (None: all)."""
        xy = np.asarray(camera_xy_m, np.float64)
        if self._pack is None or np.linalg.norm(xy - self._pack[0]) > self.MARGIN_M:
            self._pack = None  # the old packing's memory goes before the new one is made
            meshes, face_cells = self.visible_meshes(self.near_cells(xy, view_distance_m + self.MARGIN_M))
            self._pack = (xy, _Packed.of(meshes), face_cells)
        _, packed, face_cells = self._pack
        keep = self.near_cells(xy, view_distance_m)[face_cells]
        return packed, None if keep.all() else np.flatnonzero(keep)

    @property
    def held_triangles(self) -> int:
        """Triangles in the pieces held (those of the current packing) and the whole meshes."""
        return sum(len(p.mesh.faces) for p, _ in self._held.values()) + sum(
            len(s.faces) for s in self._sources if isinstance(s, Mesh)
        )


def _joined(parts: list[tuple[Piece, np.ndarray]], near: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """One mesh of the pieces `parts` (each with its faces' cells) with only the faces in the cells `near`, in the
    whole mesh's face order, and those faces' cells."""
    chosen = [np.flatnonzero(near[cells]) for _, cells in parts]
    first = parts[0][0].mesh
    if len(parts) == 1 and len(chosen[0]) == len(first.faces):
        return first, parts[0][1]
    offsets = np.cumsum([0] + [len(p.mesh.vertices_m) for p, _ in parts[:-1]])
    faces = np.concatenate([p.mesh.faces[c] + o for (p, _), c, o in zip(parts, chosen, offsets, strict=True)])
    keys = np.concatenate([p.face_keys[c] for (p, _), c in zip(parts, chosen, strict=True)])
    cells = np.concatenate([cells[c] for (_, cells), c in zip(parts, chosen, strict=True)])
    order = np.argsort(keys, kind="stable")

    def joined(name: str) -> np.ndarray | None:
        arrays = [getattr(p.mesh, name) for p, _ in parts]
        return None if arrays[0] is None else np.concatenate(arrays)

    mesh = dataclasses.replace(
        first,
        vertices_m=joined("vertices_m"),
        faces=faces[order].astype(np.int32 if offsets[-1] + len(parts[-1][0].mesh.vertices_m) < 2**31 else np.int64),
        vertex_rgb=joined("vertex_rgb"),
        uv=joined("uv"),
        normals=joined("normals"),
    )
    return mesh, cells[order]


def lighting_row(lighting: Lighting) -> np.ndarray:
    """(9,) float32: ambient rgb, unit light direction (camera frame), light rgb."""
    direction = np.asarray(lighting.light_dir_cam, dtype=np.float64)
    row = np.zeros(9, np.float32)
    row[0:3] = lighting.ambient_rgb
    row[3:6] = direction / max(np.linalg.norm(direction), 1e-12)
    row[6:9] = lighting.light_rgb
    return row


class Scratch:
    """Working arrays kept from frame to frame (about the same sizes every frame) rather than tens of MB allocated
    and freed per frame."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        """A C-contiguous array `shape` of `dtype` (its content is whatever was there)."""
        need = int(np.prod(shape))
        have = self._arrays.get(name)
        if have is None or have.size < need or have.dtype != np.dtype(dtype):
            have = np.empty(need + need // 4, dtype)  # room to grow: the next packing may hold a few more
            self._arrays[name] = have
        return have[:need].reshape(shape)


def render_packed(
    packed: _Packed,
    triangles: np.ndarray | None,
    T_camera_world: np.ndarray,
    K: np.ndarray,
    width_px: int,
    height_px: int,
    lighting: Lighting,
    haze_distance_m: float,
    sky: Sky,
    scratch: Scratch,
) -> FrameImages:
    """Draw the triangles `triangles` (None: all) of `packed` seen by a camera at T_camera_world (4x4, world ->
    optical frame) with intrinsics K, hazy with distance (`haze_distance_m`), under `sky`; working arrays from
    `scratch`."""
    from drivesim.sim import raster_kernel  # numba compiles (or loads its cache) on first import
    from drivesim.stages.synth import render_kernel

    T = np.asarray(T_camera_world, dtype=np.float64)
    shift = np.eye(4)
    shift[:3, 3] = packed.origin_m
    M = (T @ shift)[:3, :].astype(np.float32)
    vertices = packed.vertices
    if triangles is not None:
        subset = scratch.get("subset", (3, 3, len(triangles)), np.float32)
        vertices = np.take(vertices.reshape(3, 3, -1), triangles, axis=2, out=subset).reshape(3, -1)
    n_tri = vertices.shape[1] // 3
    vc = scratch.get("vc", (3, 3 * n_tri), np.float32)
    for r in range(3):  # row by row: numpy's (3, 3) @ (3, N) matrix product was 25 times slower
        np.multiply(vertices[0], M[r, 0], out=vc[r])
        vc[r] += M[r, 1] * vertices[1]
        vc[r] += M[r, 2] * vertices[2]
        vc[r] += M[r, 3]
    vc = vc.reshape(9, n_tri)
    K64 = np.asarray(K, dtype=np.float64)
    table = scratch.get("table", (13, n_tri), np.float32)
    bbox = scratch.get("bbox", (n_tri, 4), np.int64)
    index = scratch.get("index", (n_tri,), np.int64)
    kept = raster_kernel.setup(
        vc, K64[0, 0], K64[1, 1], K64[0, 2], K64[1, 2], width_px, height_px, NEAR_M, False, table, bbox, index
    )
    size = width_px * height_px
    depth = np.full(size, np.inf, np.float32)
    winner = scratch.get("winner", (size,), np.int64)
    winner.fill(-1)
    table = np.ascontiguousarray(table[:, :kept])
    if kept:
        camera = np.zeros(kept, np.int64)
        raster_kernel.depth_test(table, bbox[:kept], camera, width_px, height_px, NEAR_M, depth, winner)
    source = index[:kept] if triangles is None else triangles[index[:kept]]
    rgb = np.empty((size, 3), np.uint8)
    ids = np.empty(size, np.int32)
    K_inv = np.linalg.inv(K64).astype(np.float32)
    uncovered = render_kernel.shade_world(
        depth, winner, table, source, packed.attributes, packed.material, packed.object_id,
        packed.texture_index, packed.texels, packed.texture_info, T[:3, :3].astype(np.float32),
        K_inv, lighting_row(lighting), haze_distance_m, np.asarray(sky.horizon_rgb, np.float32), width_px, rgb, ids,
    )  # fmt: skip
    if uncovered:
        R_world_camera = np.ascontiguousarray(T[:3, :3].T, np.float32)
        render_kernel.paint_sky(winner, K_inv, R_world_camera, sky.clouds, sky.table(), width_px, rgb)
    return FrameImages(
        rgb=rgb.reshape(height_px, width_px, 3),
        depth_m=depth.reshape(height_px, width_px),
        object_id=ids.reshape(height_px, width_px),
    )
