"""The synthetic world: a procedural road scene from a seed, and the ground-truth renderer for any camera pose.

    world = SynthWorld.from_seed(0)
    rgb, depth_m = world.render(T_world_camera, world.camera.K, world.camera.width_px, world.camera.height_px)

`world.road` is the centreline and `world.path` the right lane centre (the reference path a car drives); both are
`RoadPath`s in the world's ENU frame (x east, y north, z up; the road starts at the origin heading east).
Surfaces carry semantic object ids (`SEMANTIC_IDS`), readable with `render_full`. The meshes that grow with the road
are made a stretch at a time as a camera comes near (`render.CellCulling`), every random draw taken in the order of
the whole build, so a seed keeps its world however long its road.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from drivesim.pipeline.memory import release_freed_memory
from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, invert, pose_2d
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.raster import Lighting
from drivesim.sim.vehicles import GROUP_NAMES, VehicleShape, build_vehicle_meshes
from drivesim.stages.synth import textures
from drivesim.stages.synth.config import CameraConfig, SynthConfig, SynthWorldConfig
from drivesim.stages.synth.primitives import MeshBuffer, box, icosphere, prism, quad_faces
from drivesim.stages.synth.render import CellCulling, Piece, Scratch, Sky, Source, render_packed
from drivesim.stages.synth.road import RoadPath, build_centreline
from drivesim.stages.synth.scenery import (
    CURB_TOP_WIDTH_M,
    Building,
    Layout,
    place_scenery,
    road_half_width_m,
    sidewalk_outer_m,
)

SEMANTIC_IDS = {"road": 0, "sidewalk": 1, "ground": 2, "building": 3, "vegetation": 4, "car": 5}
ROAD_STATION_M = 1.5
PARKED_CAR_HEIGHT_M = 1.45
GROUND_TILE_M = 10.0
FAR_TILE_M = 100.0
FAR_EXTENT_M = 1500.0
LAWN_CHUNK_TILES = 20_000
GROUND_Z_M = -0.03
FACADE_ATLAS_WIDTH_PX = 1024
BUILDING_GROUP_M = 160.0  # buildings share a facade atlas within squares of this size
# a world of up to this many triangles is held whole (as a world made whole: its frames are those to the bit); a
# larger one a stretch at a time (its packings' origin differs, so a few pixels on edges differ, see the notebook)
WHOLE_WORLD_TRIANGLES = 600_000

SUN_DIR_WORLD = np.array([0.45, -0.55, 0.70])  # towards the sun: south-east, about 44 degrees up
SKY_ZENITH_RGB = np.array([0.33, 0.52, 0.80], np.float32)
SKY_HORIZON_RGB = np.array([0.78, 0.85, 0.92], np.float32)
HAZE_DISTANCE_M = 700.0
CLOUD_HEIGHT_M = 1500.0
CLOUD_TILE_M = 16000.0
CLOUD_RGB = np.array([0.96, 0.96, 0.97], np.float32)


@dataclass(frozen=True)
class SynthCamera:
    """A pinhole camera on the vehicle: intrinsics, image size and mount (T_vehicle_camera: optical -> vehicle)."""

    K: np.ndarray
    width_px: int
    height_px: int
    T_vehicle_camera: np.ndarray

    @property
    def height_m(self) -> float:
        """Optical centre above the ground (vehicle origin is on the ground)."""
        return float(self.T_vehicle_camera[2, 3])

    @classmethod
    def from_config(cls, cfg: CameraConfig) -> SynthCamera:
        """The camera described by `cfg`."""
        K = intrinsics_from_hfov(cfg.width_px, cfg.height_px, np.deg2rad(cfg.hfov_deg))
        T = camera_mount(cfg.forward_m, 0.0, cfg.height_m, pitch_down_rad=np.deg2rad(cfg.pitch_down_deg))
        return cls(K=K, width_px=cfg.width_px, height_px=cfg.height_px, T_vehicle_camera=T)


class SynthWorld:
    """A procedural road world, deterministic for a seed; renders ground-truth colour and depth from any pose.

    :param seed: the world's seed.
    :param config: road and scenery settings.
    :param camera: the default camera (from `SynthConfig.camera`).
    """

    def __init__(self, seed: int, config: SynthWorldConfig, camera: SynthCamera) -> None:
        self.seed = int(seed)
        self.config = config
        self.camera = camera
        world_rng, texture_rng, sky_rng = (
            np.random.default_rng(s) for s in np.random.SeedSequence([self.seed, 1]).spawn(3)
        )
        self.road: RoadPath = build_centreline(config.road, world_rng)
        self.path: RoadPath = self.road.offset(-0.5 * config.road.lane_width_m)
        self.layout: Layout = place_scenery(self.road, config.road, config.scenery, world_rng)
        # the building groups' facade atlases are made when the camera comes near (`CellCulling`), not here
        # the meshes that grow with the road are made a stretch at a time as the camera comes near (`CellCulling`)
        self._sources, self._facades = _build_sources(self.road, self.layout, config, texture_rng)
        self._culling = CellCulling(self._sources, self._facades, WHOLE_WORLD_TRIANGLES)
        release_freed_memory()  # the pieces' temporaries: a long road's build would keep them resident all along
        self._scratch = Scratch()
        self._sky = Sky(_cloud_cover(sky_rng), SKY_ZENITH_RGB, SKY_HORIZON_RGB, CLOUD_RGB, CLOUD_HEIGHT_M, CLOUD_TILE_M)

    @classmethod
    def from_seed(cls, seed: int, cfg: SynthConfig | SynthWorldConfig | None = None) -> SynthWorld:
        """The world of `seed` with the settings of `cfg` (defaults when None)."""
        synth = cfg if isinstance(cfg, SynthConfig) else SynthConfig()
        world_cfg = cfg if isinstance(cfg, SynthWorldConfig) else synth.world
        return cls(seed, world_cfg, SynthCamera.from_config(synth.camera))

    @classmethod
    def from_sidecar(cls, path: Path | str) -> SynthWorld:
        """Rebuild the world of a recording from its `<recording>.world.json` sidecar."""
        data = json.loads(Path(path).read_text())
        cfg = SynthConfig.model_validate(data["config"])
        return cls(data["seed"], cfg.world, SynthCamera.from_config(cfg.camera))

    @property
    def triangle_count(self) -> int:
        """Triangles in the world."""
        return sum(self._culling.triangle_counts)

    @property
    def meshes(self) -> list[Mesh]:
        """Every surface of the world as world-frame meshes, textures included (made on each call: a long road's
        meshes and facades take hundreds of MB)."""
        return self._culling.whole_meshes()

    def lighting(self, T_world_camera: np.ndarray) -> Lighting:
        """Sun and sky light for a camera at `T_world_camera`."""
        sun = SUN_DIR_WORLD / np.linalg.norm(SUN_DIR_WORLD)
        return Lighting(
            ambient_rgb=np.array([0.56, 0.58, 0.62]),
            light_dir_cam=T_world_camera[:3, :3].T @ (-sun),
            light_rgb=np.array([0.62, 0.58, 0.50]),
        )

    def render_full(
        self, T_world_camera: np.ndarray, K: np.ndarray, width_px: int, height_px: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8, depth along the optical axis (H, W) float32 m (+inf = sky) and semantic object
        ids (H, W) int32 (`SEMANTIC_IDS`, -1 = sky) seen by a camera at `T_world_camera` (optical frame -> world)."""
        T_world_camera = np.asarray(T_world_camera, float)
        packed, triangles = self._culling.scene(T_world_camera[:2, 3], self.config.scenery.view_distance_m)
        frame = render_packed(
            packed, triangles, invert(T_world_camera), K, int(width_px), int(height_px), self.lighting(T_world_camera),
            HAZE_DISTANCE_M, self._sky, self._scratch,
        )  # fmt: skip
        return frame.rgb, frame.depth_m, frame.object_id

    def render(
        self, T_world_camera: np.ndarray, K: np.ndarray, width_px: int, height_px: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth colour (H, W, 3) uint8 and depth (H, W) float32 metres along the optical axis (+inf = sky)
        for a camera at `T_world_camera` (4x4, optical frame -> world) with intrinsics `K`."""
        rgb, depth, _ = self.render_full(T_world_camera, K, width_px, height_px)
        return rgb, depth


def _cloud_cover(rng: np.random.Generator) -> np.ndarray:
    """(N, N) cloud opacity in [0, 1] on a periodic tile of the cloud layer (CLOUD_TILE_M across)."""
    n = 512
    c = textures.periodic_noise(rng, n, n, 14.0) + 0.45 * textures.periodic_noise(rng, n, n, 3.0)
    return np.clip((c - 0.55) * 0.9, 0.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- meshes
# The meshes that grow with the road are made a stretch at a time (`Piece`s, made when a camera comes near): every
# random draw is taken up front, in the order of the whole build, so that a seed keeps its world.
STRETCH_M = 160.0  # a piece holds this much road (the road's ribbons) or a square of this size (the rest)
KEY_STRIDE = 1 << 16  # face keys of objects (trees, cars): object index * KEY_STRIDE + the face's index in the object


def _build_sources(
    road: RoadPath, layout: Layout, cfg: SynthWorldConfig, rng: np.random.Generator
) -> tuple[list[Source], dict[int, Callable[[], np.ndarray]]]:
    """The world's meshes, whole or in pieces, and for those whose texture is made on demand (the building groups'
    facade atlases: the mesh has its uv but no texture) the function that makes it, by index in the list."""
    road_cfg = cfg.road
    sources: list[Source] = [
        _road_pieces(road, road_cfg, rng),
        *_sidewalk_pieces(road, road_cfg, rng),
        *_ground_sources(road, cfg, rng),
    ]
    facades: dict[int, Callable[[], np.ndarray]] = {}
    for mesh, make_atlas in _building_meshes(layout):
        if mesh.triangle_count:
            facades[len(sources)] = make_atlas
            sources.append(mesh)
    sources += [*_tree_pieces(layout, rng), *_car_pieces(layout)]
    return sources, facades


@dataclass(frozen=True)
class _Look:
    """How a piece's MeshBuffer becomes a mesh (`MeshBuffer.build`'s arguments)."""

    material: Material
    object_id: int
    texture_rgb: np.ndarray | None = None
    smooth: bool = False
    coloured: bool = False

    def __call__(self, buf: MeshBuffer) -> Mesh:
        """The mesh of `buf`."""
        return buf.build(self.material, self.object_id, self.texture_rgb, smooth=self.smooth, coloured=self.coloured)


def _by_square(xy_m: np.ndarray) -> list[np.ndarray]:
    """Indices of the points `xy_m` (N, 2) grouped by STRETCH_M squares, increasing within each group."""
    if not len(xy_m):
        return []
    ij = np.floor(np.asarray(xy_m, float) / STRETCH_M).astype(np.int64)
    key = ij[:, 0] * 1_000_003 + ij[:, 1]
    order = np.argsort(key, kind="stable")
    _, starts = np.unique(key[order], return_index=True)
    return np.split(order, starts[1:])


def _stations(period_m: float, periods: range) -> np.ndarray:
    """Arc lengths of the texture periods `periods`, each split into ROAD_STATION_M steps: (P, n+1)."""
    steps = int(round(period_m / ROAD_STATION_M))
    return np.arange(periods.start, periods.stop)[:, None] * period_m + np.linspace(0.0, period_m, steps + 1)[None, :]


def _ribbon(
    road: RoadPath,
    period_m: float,
    lat_left_m: float,
    lat_right_m: float,
    z_left_m: float,
    z_right_m: float,
    periods: range,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A strip between two offsets of the centreline over the texture periods `periods`, one period per piece (so
    uv stay in [0, 1]); faces from 0."""
    st = _stations(period_m, periods)
    P, n = st.shape
    pts, _, normals = road.frames(st.ravel())
    left = pts + lat_left_m * normals
    right = pts + lat_right_m * normals
    verts = np.empty((P * n * 2, 3))
    verts[0::2, :2], verts[0::2, 2] = left, z_left_m
    verts[1::2, :2], verts[1::2, 2] = right, z_right_m
    v_along = np.tile(np.linspace(0.0, 1.0, n), P)
    uv = np.empty((P * n * 2, 2))
    uv[0::2] = np.column_stack([np.zeros(P * n), v_along])
    uv[1::2] = np.column_stack([np.ones(P * n), v_along])
    per = quad_faces(n - 1)
    faces = np.concatenate([per + p * 2 * n for p in range(P)])
    return verts, faces, uv


@dataclass(frozen=True)
class _Strip:
    """One ribbon of a mesh of ribbons: offsets and heights (`_ribbon`), u running right to left, a colour (None:
    textured)."""

    lat_left_m: float
    lat_right_m: float
    z_left_m: float
    z_right_m: float
    flip_u: bool = False
    rgb: np.ndarray | None = None


def _ribbon_pieces(road: RoadPath, period_m: float, strips: list[_Strip], look: _Look) -> list[Callable[[], Piece]]:
    """A mesh of the ribbons `strips` (one after the other, each along the whole road) in pieces of STRETCH_M."""
    n_periods = int(road.length_m // period_m)
    step = max(1, int(STRETCH_M // period_m))
    return [
        functools.partial(_ribbon_piece, road, period_m, strips, look, range(p, min(p + step, n_periods)))
        for p in range(0, n_periods, step)
    ]


def _ribbon_piece(road: RoadPath, period_m: float, strips: list[_Strip], look: _Look, periods: range) -> Piece:
    """The texture periods `periods` of every ribbon of `strips`."""
    n_periods = int(road.length_m // period_m)
    buf = MeshBuffer()
    keys, vertex_keys = [], []
    for r, strip in enumerate(strips):
        v, f, uv = _ribbon(
            road, period_m, strip.lat_left_m, strip.lat_right_m, strip.z_left_m, strip.z_right_m, periods
        )
        if strip.flip_u:
            uv[:, 0] = 1.0 - uv[:, 0]
        faces_per_period = len(f) // len(periods)
        keys.append((r * n_periods + periods.start) * faces_per_period + np.arange(len(f)))
        vertex_keys.append((r * n_periods + periods.start) * (len(v) // len(periods)) + np.arange(len(v)))
        buf.add(v, f, uv=uv if strip.rgb is None else None, rgb=strip.rgb)
    return Piece(look(buf), np.concatenate(keys), np.concatenate(vertex_keys))


def _road_pieces(road: RoadPath, road_cfg, rng: np.random.Generator) -> list[Callable[[], Piece]]:
    half = road_half_width_m(road_cfg)
    tex = textures.asphalt_texture(rng, textures.RoadLayout(road_cfg.lane_width_m, half, road_cfg.edge_lines))
    mat = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.05, 0.05, 0.05), shininess=16.0, roughness=0.8)
    look = _Look(mat, SEMANTIC_IDS["road"], texture_rgb=tex)
    return _ribbon_pieces(road, textures.DASH_PERIOD_M, [_Strip(half, -half, 0.0, 0.0)], look)


def _sidewalk_pieces(road: RoadPath, road_cfg, rng: np.random.Generator) -> list[list[Callable[[], Piece]]]:
    """The sidewalks (textured) and the curbs (coloured), each in pieces."""
    half = road_half_width_m(road_cfg)
    h = road_cfg.curb_height_m
    outer = sidewalk_outer_m(road_cfg)
    period = 3.0
    paving = textures.paving_texture(rng, road_cfg.sidewalk_width_m, period)
    curb_rgb = np.array([0.72, 0.72, 0.70])
    walks, curbs = [], []
    for side in (1.0, -1.0):
        a, b = side * (half + CURB_TOP_WIDTH_M), side * outer
        walks.append(_Strip(max(a, b), min(a, b), h, h, flip_u=side < 0))
        # curb face (road -> curb top), curb top, and the outer face down to the ground
        for lat0, lat1, z0, z1, shade in (
            (side * half, side * half, 0.0, h, 0.85),
            (side * half, side * (half + CURB_TOP_WIDTH_M), h, h, 1.0),
            (side * outer, side * outer, h, GROUND_Z_M, 0.8),
        ):
            curbs.append(_Strip(lat0, lat1, z0, z1, rgb=curb_rgb * shade))
    walk_mat = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.03, 0.03, 0.03), roughness=0.9)
    curb_mat = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.03, 0.03, 0.03), roughness=0.9)
    return [
        _ribbon_pieces(road, period, walks, _Look(walk_mat, SEMANTIC_IDS["sidewalk"], texture_rgb=paving)),
        _ribbon_pieces(road, period, curbs, _Look(curb_mat, SEMANTIC_IDS["sidewalk"], coloured=True)),
    ]


def _lawn_box(road: RoadPath, cfg: SynthWorldConfig) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 (m) of the 10 m lawn grid: the road's bounding box plus `ground_margin_m`, on the grid."""
    margin = cfg.scenery.ground_margin_m
    x0 = np.floor((road.x_m.min() - margin) / GROUND_TILE_M) * GROUND_TILE_M
    x1 = np.ceil((road.x_m.max() + margin) / GROUND_TILE_M) * GROUND_TILE_M
    y0 = np.floor((road.y_m.min() - margin) / GROUND_TILE_M) * GROUND_TILE_M
    y1 = np.ceil((road.y_m.max() + margin) / GROUND_TILE_M) * GROUND_TILE_M
    return float(x0), float(x1), float(y0), float(y1)


def _sub_offsets() -> np.ndarray:
    """(16, 2) corners of the 2.5 m sub-tiles in a 10 m tile, row by row."""
    sub = GROUND_TILE_M / 4
    return np.stack(np.meshgrid(np.arange(4) * sub, np.arange(4) * sub), -1).reshape(-1, 2)


@dataclass(frozen=True)
class _LawnGrid:
    """The 10 m lawn grid over the road's bounding box plus `ground_margin_m`, tile by tile in row order (y rows of
    x): each tile's texture turn (quarter turns), and for tiles near the road (split into 2.5 m sub-tiles) which
    sub-tiles are shown (bit k: sub-tile k of `_sub_offsets`; those entirely under the road and sidewalks are not)."""

    xs_m: np.ndarray
    ys_m: np.ndarray
    turns: np.ndarray
    near: np.ndarray
    shown: np.ndarray


def _lawn_grid(road: RoadPath, cfg: SynthWorldConfig, rng: np.random.Generator) -> _LawnGrid:
    """The lawn grid of `road`, its texture turns drawn from `rng`."""
    x0, x1, y0, y1 = _lawn_box(road, cfg)
    xs, ys = np.arange(x0, x1, GROUND_TILE_M), np.arange(y0, y1, GROUND_TILE_M)
    turns = rng.integers(0, 4, len(xs) * len(ys)).astype(np.int8)  # no visible tiling
    tree = cKDTree(np.column_stack([road.x_m, road.y_m]))
    paved_m = sidewalk_outer_m(cfg.road)
    sub = GROUND_TILE_M / 4
    probe_at = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]]) * sub
    near = np.zeros(len(turns), bool)
    shown = np.zeros(len(turns), np.uint16)
    rows = max(1, LAWN_CHUNK_TILES // max(len(xs), 1))  # a few rows at a time: the working arrays stay small
    for r0 in range(0, len(ys), rows):
        gx, gy = (a.ravel() for a in np.meshgrid(xs, ys[r0 : r0 + rows]))
        at = slice(r0 * len(xs), r0 * len(xs) + len(gx))
        is_near = tree.query(np.column_stack([gx, gy]) + GROUND_TILE_M / 2)[0] < paved_m + GROUND_TILE_M
        corners = np.column_stack([gx[is_near], gy[is_near]])[:, None, :] + _sub_offsets()[None]  # (P, 16, 2)
        probe = corners[:, :, None, :] + probe_at
        hidden = tree.query(probe.reshape(-1, 2))[0].reshape(len(corners), 16, 5).max(-1) < paved_m - 0.05
        near[at] = is_near
        shown[at][is_near] = (~hidden * (1 << np.arange(16))).sum(1)
    return _LawnGrid(xs, ys, turns, near, shown)


def _lawn_piece(grid: _LawnGrid, look: _Look, block: tuple[int, int]) -> Piece:
    """The lawn tiles of the STRETCH_M square `block` (column, row) of the grid; a tile's faces keep their order in
    the whole lawn (the whole tiles in grid order, then the sub-tiles)."""
    per = int(STRETCH_M // GROUND_TILE_M)
    nx = len(grid.xs_m)
    ix = np.arange(block[0] * per, min((block[0] + 1) * per, nx))
    iy = np.arange(block[1] * per, min((block[1] + 1) * per, len(grid.ys_m)))
    g = (iy[:, None] * nx + ix[None, :]).ravel()
    gx, gy = grid.xs_m[g % nx], grid.ys_m[g // nx]
    whole = ~grid.near[g]
    wholes = np.column_stack([gx[whole], gy[whole], np.full(int(whole.sum()), GROUND_TILE_M), gx[whole], gy[whole]])
    split = g[~whole]
    bits = ((grid.shown[split][:, None] >> np.arange(16)) & 1).astype(bool)  # (P, 16)
    parents = np.column_stack([gx[~whole], gy[~whole]])
    corners = parents[:, None, :] + _sub_offsets()[None]
    subs = np.column_stack([
        corners[bits], np.full(int(bits.sum()), GROUND_TILE_M / 4), np.repeat(parents, bits.sum(1), axis=0),
        np.repeat(grid.turns[split], bits.sum(1)),
    ])  # fmt: skip
    tiles = np.concatenate([np.column_stack([wholes, grid.turns[g[whole]]]), subs.reshape(-1, 6)]).astype(float)
    tile_keys = np.concatenate([g[whole], len(grid.turns) + (split[:, None] * 16 + np.arange(16))[bits]])
    buf = MeshBuffer()
    if len(tiles):
        verts, faces, uv = _lawn_quads(tiles)
        buf.add(verts, faces, uv=uv)
    return Piece(
        look(buf), (tile_keys[:, None] * 2 + np.arange(2)).ravel(), (tile_keys[:, None] * 4 + np.arange(4)).ravel()
    )


def _lawn_quads(tiles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (4T, 3), faces (2T, 3) and uv (4T, 2) of (T, 6) lawn tiles (x, y, size, the parent 10 m tile's x, y,
    its quarter turns), faces from 0."""
    n = len(tiles)
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    verts = np.zeros((n, 4, 3))
    verts[:, :, :2] = tiles[:, None, :2] + unit[None] * tiles[:, None, 2:3]
    verts[:, :, 2] = GROUND_Z_M
    # texture coordinates from the position inside the parent 10 m tile, turned by its multiple of 90 degrees
    local = (verts[:, :, :2] - tiles[:, None, 3:5]) / GROUND_TILE_M - 0.5
    angle = tiles[:, 5, None] * (np.pi / 2)
    c, sn = np.cos(angle), np.sin(angle)
    uv = np.stack([c * local[..., 0] - sn * local[..., 1], sn * local[..., 0] + c * local[..., 1]], -1) + 0.5
    uv[..., 1] = 1.0 - uv[..., 1]
    faces = (np.arange(n)[:, None, None] * 4 + np.array([[0, 1, 2], [0, 2, 3]])[None]).reshape(-1, 3)
    return verts.reshape(-1, 3), faces, np.clip(uv, 0.0, 1.0).reshape(-1, 2)


def _ground_sources(road: RoadPath, cfg: SynthWorldConfig, rng: np.random.Generator) -> list[Source]:
    """Textured lawn tiles around the road (`_LawnGrid`, in STRETCH_M squares) and coarse far tiles to the horizon.

    The rasterizer pays for every triangle's screen area, hidden or not, so lawn is not laid under the pavement.
    """
    grid = _lawn_grid(road, cfg, rng)
    grass = textures.grass_texture(rng, GROUND_TILE_M)
    mat = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.02, 0.02, 0.02), roughness=1.0)
    look = _Look(mat, SEMANTIC_IDS["ground"], texture_rgb=grass)
    per = int(STRETCH_M // GROUND_TILE_M)
    blocks = [(bx, by) for by in range(-(-len(grid.ys_m) // per)) for bx in range(-(-len(grid.xs_m) // per))]
    lawn = [functools.partial(_lawn_piece, grid, look, block) for block in blocks]
    return [lawn, _far_mesh(*_lawn_box(road, cfg))]


def _far_mesh(x0: float, x1: float, y0: float, y1: float) -> Mesh:
    """Coarse ground tiles around the lawn box (x0, x1, y0, y1) to FAR_EXTENT_M from its centre."""
    far = MeshBuffer()
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    fx = np.arange(cx - FAR_EXTENT_M, cx + FAR_EXTENT_M, FAR_TILE_M)
    fy = np.arange(cy - FAR_EXTENT_M, cy + FAR_EXTENT_M, FAR_TILE_M)
    for a in fx:
        for b in fy:
            if a + FAR_TILE_M > x0 and a < x1 and b + FAR_TILE_M > y0 and b < y1:
                continue  # inside the lawn
            v = np.array([[a, b, GROUND_Z_M - 0.02], [a + FAR_TILE_M, b, GROUND_Z_M - 0.02]])
            v = np.concatenate([v, v[::-1] + [0, FAR_TILE_M, 0]])
            far.add(v, np.array([[0, 1, 2], [0, 2, 3]]))
    far_mat = Material(diffuse_rgb=(0.36, 0.44, 0.27), specular_rgb=(0.0, 0.0, 0.0), roughness=1.0)
    return far.build(far_mat, SEMANTIC_IDS["ground"])


def _building_meshes(layout: Layout) -> list[tuple[Mesh, Callable[[], np.ndarray]]]:
    """The buildings, one mesh per BUILDING_GROUP_M square of the map (by their centres), each over its own facade
    atlas, with the function that makes the atlas: a camera's view then holds only the facades near it, and only
    those are made, however long the road."""
    groups: dict[tuple[int, int], list[Building]] = {}
    for b in layout.buildings:
        groups.setdefault((int(b.x_m // BUILDING_GROUP_M), int(b.y_m // BUILDING_GROUP_M)), []).append(b)
    return [_building_mesh(buildings) for buildings in groups.values()]


def _facade_atlas(buildings: list[Building]) -> np.ndarray:
    """The facade atlas of a group of buildings (each building's facade from its own seed)."""
    images = []
    for b in buildings:
        brng = np.random.default_rng(b.facade_seed)
        images.append(textures.facade_texture(brng, max(b.length_m, b.depth_m), b.height_m))
    atlas, _ = textures.pack_atlas(images, atlas_width_px=FACADE_ATLAS_WIDTH_PX)
    return atlas


def _building_mesh(buildings: list[Building]) -> tuple[Mesh, Callable[[], np.ndarray]]:
    """Buildings as one mesh over a facade atlas (each building has its own facade), without the atlas, and the
    function that makes it."""
    sizes = [textures.facade_size_px(max(b.length_m, b.depth_m), b.height_m) for b in buildings]
    _, _, rects = textures.atlas_layout(sizes, FACADE_ATLAS_WIDTH_PX)
    buf = MeshBuffer()
    for i, b in enumerate(buildings):
        v, f = box(np.array([b.x_m, b.y_m]), b.yaw_rad, b.length_m, b.depth_m, GROUND_Z_M - 0.1, b.height_m)
        u0, v0, u1, v1 = rects[i]
        facade_w = max(b.length_m, b.depth_m)
        uv = np.zeros((24, 2))
        for side, wall_len in enumerate((b.depth_m, b.length_m, b.depth_m, b.length_m)):
            ue = u0 + (u1 - u0) * wall_len / facade_w
            uv[4 * side : 4 * side + 4] = [[u0, v1], [ue, v1], [ue, v0], [u0, v0]]
        # Only the walls a street-level camera can see: no bottom, no back wall, no roof (every building is taller
        # than a car's camera, so its roof projects behind its own front wall yet would cost rasterization time).
        keep = [k for k in range(4) if k != _back_wall(b)]
        buf.add(v, f[np.concatenate([[2 * k, 2 * k + 1] for k in keep])], uv=uv)
    mat = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.06, 0.06, 0.06), shininess=24.0, roughness=0.7)
    # built with a stand-in texture so that the mesh keeps its uv; the atlas replaces it when it is made
    mesh = buf.build(mat, SEMANTIC_IDS["building"], texture_rgb=np.zeros((1, 1, 3), np.uint8))
    return dataclasses.replace(mesh, texture_rgb=None), functools.partial(_facade_atlas, buildings)


def _back_wall(b: Building) -> int:
    """Index (0 front +x, 1 left +y, 2 back, 3 right) of the building wall that faces away from the road: buildings
    are placed with their x axis along the road, so it is the left wall on the left side, the right one else.
    Leaving it out saves a quarter of the buildings' rasterization and is never seen from the road."""
    return 1 if b.road_side > 0 else 3


def _crown_draws(rng: np.random.Generator, n_vertices: int) -> tuple[np.ndarray, float, np.ndarray, float]:
    """A tree crown's random draws, in the world's order: vertex bumps, vertical stretch, light noise, green tint."""
    bumps = rng.standard_normal(n_vertices)
    stretch = float(rng.uniform(1.0, 1.35))
    noise = rng.standard_normal(n_vertices)
    tint = float(rng.uniform(0.7, 1.2))
    return bumps, stretch, noise, tint


def _tree_pieces(layout: Layout, rng: np.random.Generator) -> list[list[Callable[[], Piece]]]:
    """The trees' crowns and trunks, each in pieces of STRETCH_M squares. Every crown's draws are taken from `rng`
    here, tree after tree (as the whole build took them), and the generator's state before each kept: a piece
    draws its crowns again from those states."""
    n_vertices = len(icosphere(1)[0])
    states = []
    for _ in layout.trees:
        state = rng.bit_generator.state
        states.append((state["state"]["state"], state["has_uint32"], state["uinteger"]))
        _crown_draws(rng, n_vertices)
    inc = rng.bit_generator.state["state"]["inc"]
    groups = _by_square(np.array([[t.x_m, t.y_m] for t in layout.trees]).reshape(-1, 2))
    leaf = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.02, 0.03, 0.02), shininess=8.0, roughness=0.9)
    bark = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.0, 0.0, 0.0), roughness=1.0)
    crowns = _Look(leaf, SEMANTIC_IDS["vegetation"], smooth=True, coloured=True)
    trunks = _Look(bark, SEMANTIC_IDS["vegetation"], smooth=True, coloured=True)
    return [
        [functools.partial(_crown_piece, layout.trees, states, inc, crowns, idx) for idx in groups],
        [functools.partial(_trunk_piece, layout.trees, trunks, idx) for idx in groups],
    ]


def _generator_at(inc: int, state: tuple[int, int, int]) -> np.random.Generator:
    """A PCG64 generator with increment `inc` at the (state, has_uint32, uinteger) `state`."""
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = {
        "bit_generator": "PCG64", "state": {"state": state[0], "inc": inc}, "has_uint32": state[1],
        "uinteger": state[2],
    }  # fmt: skip
    return rng


def _crown_piece(trees: list, states: list[tuple[int, int, int]], inc: int, look: _Look, idx: np.ndarray) -> Piece:
    """The crowns of the trees `idx`, each from its own draws (`states`)."""
    sphere_v, sphere_f = icosphere(1)
    crowns = MeshBuffer()
    for k in idx:
        t = trees[k]
        bumps, stretch, noise, tint = _crown_draws(_generator_at(inc, states[k]), len(sphere_v))
        scale = np.array([1.0, 1.0, stretch]) * t.crown_radius_m
        centre = np.array([t.x_m, t.y_m, t.trunk_height_m + 0.8 * scale[2]])
        cv = sphere_v * (1.0 + 0.16 * bumps)[:, None] * scale + centre
        # darker underneath and inside, lighter on top
        light = 0.7 + 0.35 * (sphere_v[:, 2] + 1) / 2 + 0.08 * noise
        base = np.array([0.24, 0.40, 0.15]) * t.shade * np.array([1.0, 1.0, tint])
        crowns.add(cv, sphere_f, rgb=base[None, :] * light[:, None], normals=sphere_v)
    keys = (np.asarray(idx, np.int64)[:, None] * KEY_STRIDE + np.arange(len(sphere_f))).ravel()
    vertex_keys = (np.asarray(idx, np.int64)[:, None] * KEY_STRIDE + np.arange(len(sphere_v))).ravel()
    return Piece(look(crowns), keys, vertex_keys)


def _trunk_piece(trees: list, look: _Look, idx: np.ndarray) -> Piece:
    """The trunks of the trees `idx`."""
    trunks = MeshBuffer()
    keys, vertex_keys = [], []
    for k in idx:
        t = trees[k]
        v, f, n = prism(
            np.array([t.x_m, t.y_m, t.trunk_height_m / 2]), 0.14 + 0.03 * t.crown_radius_m, t.trunk_height_m + 0.6, 6
        )
        trunks.add(v, f, rgb=np.array([0.38, 0.28, 0.20]) * t.shade, normals=n)
        keys.append(k * KEY_STRIDE + np.arange(len(f)))
        vertex_keys.append(k * KEY_STRIDE + np.arange(len(v)))
    return Piece(look(trunks), np.concatenate(keys), np.concatenate(vertex_keys))


def _car_pieces(layout: Layout) -> list[list[Callable[[], Piece]]]:
    """Parked cars: one mesh per material group (`_ParkedCars`), each in pieces of STRETCH_M squares."""
    if not layout.cars:
        return []
    cars = _ParkedCars(layout.cars)
    groups = _by_square(np.array([[c.x_m, c.y_m] for c in layout.cars]))
    return [[functools.partial(cars.piece, idx, g) for idx in groups] for g in range(len(GROUP_NAMES))]


class _ParkedCars:
    """The parked cars' meshes: sedans from the vehicle builder (`sim.vehicles`) at each car's size and paint colour,
    merged into one mesh per material group (body paint colour per vertex), a stretch at a time. The last few
    stretches' cars are kept: each stretch's pieces of the five groups are made one after another."""

    KEPT = 8

    def __init__(self, cars: list) -> None:
        self.cars = cars
        self._made: dict[tuple[int, ...], list[Mesh]] = {}

    def _meshes(self, idx: np.ndarray) -> list[list[Mesh]]:
        """Per material group, the meshes of the cars `idx` (in the world frame)."""
        key = tuple(int(k) for k in idx)
        if key not in self._made:
            if len(self._made) >= self.KEPT:
                self._made.pop(next(iter(self._made)))
            self._made[key] = [_car_group_meshes(self.cars[k]) for k in idx]
        return [[car[g] for car in self._made[key]] for g in range(len(GROUP_NAMES))]

    def piece(self, idx: np.ndarray, group: int) -> Piece:
        """Material group `group` of the cars `idx`."""
        meshes = self._meshes(idx)[group]
        keys = np.concatenate([k * KEY_STRIDE + np.arange(len(m.faces)) for k, m in zip(idx, meshes, strict=True)])
        vertex_keys = [k * KEY_STRIDE + np.arange(len(m.vertices_m)) for k, m in zip(idx, meshes, strict=True)]
        return Piece(_merged(meshes), keys.astype(np.int64), np.concatenate(vertex_keys).astype(np.int64))


def _car_group_meshes(car) -> list[Mesh]:
    """A parked car's meshes, one per material group, in the world frame."""
    white_paint = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.05, 0.05, 0.05), shininess=96.0, roughness=0.25)
    shape = VehicleShape(
        body_type="sedan", length_m=car.length_m, width_m=car.width_m, height_m=PARKED_CAR_HEIGHT_M,
        hood_fraction=0.28, cabin_fraction=0.5, trunk_fraction=0.22, wheel_radius_m=0.32,
        belt_fraction=0.68, windscreen_rake=1.3, rear_rake=1.1,
    )  # fmt: skip
    meshes = build_vehicle_meshes(shape, white_paint, "light", SEMANTIC_IDS["car"])
    meshes[0].vertex_rgb = np.tile(np.asarray(car.rgb, np.float32), (len(meshes[0].vertices_m), 1))
    T = pose_2d(car.x_m, car.y_m, car.yaw_rad)
    return [mesh.transformed(T) for mesh in meshes]


def _merged(meshes: list[Mesh]) -> Mesh:
    """Meshes of one material (and object id) as one mesh."""
    offsets = np.cumsum([0] + [len(m.vertices_m) for m in meshes[:-1]])
    coloured = all(m.vertex_rgb is not None for m in meshes)
    index_type = np.int32 if offsets[-1] + len(meshes[-1].vertices_m) < 2**31 else np.int64  # half a long road's faces
    return Mesh(
        vertices_m=np.concatenate([m.vertices_m for m in meshes]),
        faces=np.concatenate([(m.faces + o).astype(index_type) for m, o in zip(meshes, offsets, strict=True)]),
        vertex_rgb=np.concatenate([m.vertex_rgb for m in meshes]) if coloured else None,
        material=meshes[0].material,
        object_id=meshes[0].object_id,
    )
