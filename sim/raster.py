"""Batched triangle rasterizer in torch (CPU and CUDA, same code): colour, metric depth, object ids and normals.

Conventions: camera optical frame (x right, y down, z forward); pixel (row r, column c) has its centre at image
coordinates (u, v) = (c, r), the convention of `geometry.scale_intrinsics`. Depth is z along the optical axis (m).

How it works (DESIGN §4):
- Homogeneous rasterization (Olano & Greer 1997): for a triangle with camera-frame vertices P0, P1, P2 and the ray
  d = K^-1 [u, v, 1] of a pixel, the weights w = [P0 P1 P2]^-1 d are linear in (u, v) ("edge functions"); the pixel is
  inside when all w_i >= 0, its depth is 1 / sum(w) and w / sum(w) are its perspective-correct barycentrics. This
  needs no clipping: triangles crossing the near plane or passing behind the camera (huge ground triangles) are
  drawn exactly; only their screen bounding box is computed from the polygon clipped at z = near.
- Small triangles (bbox up to 64 px: most of a vehicle mesh) are expanded into their exact (triangle, pixel) pairs;
  larger ones into 8 x 8 pixel tiles, culled per tile against the edge functions and evaluated as dense blocks.
  All pairs are evaluated at once (chunked) and the nearest one wins through `scatter_reduce(amin)` of a packed
  int64 key: float32 depth bits (monotonic for positive floats) << 32 | triangle index. One gather pass then
  recomputes the winner's barycentrics per pixel, interpolates its attributes and shades it (`shading.py`).
- CPU speed notes (torch 2.x): 1-D `index_select` per table row beats 2-D gathers several times over, so per-triangle
  tables are channel-major; `torch.where` and length-3 reductions are slow and avoided in the hot paths; broadcasts
  keep the long axis innermost.
- On CPU (`use_kernel`, the default there) the same formulas run as compiled loops (`raster_kernel.py`): set-up,
  depth test and shading for untextured scenes such as vehicles, the depth test for textured ones; the torch path
  below is what a GPU runs.
- Static geometry is packed once into a `PackedScene` (per-triangle vertex attributes on the device); the rasterizer
  caches the packing of the mesh lists it is given, so rendering the same world from many poses does not re-pack.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from drivesim.sim.cpu_threads import parallel_slot
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.shading import Lighting, dot3, normalize3, shade_blinn_phong

__all__ = [
    "Lighting",
    "PackedScene",
    "Rasterizer",
    "RenderResult",
    "composite",
    "merge_scenes",
    "pack_meshes",
    "render_meshes",
    "roi_intrinsics",
]

_EMPTY_KEY = torch.iinfo(torch.int64).max
# Keys from here up carry an infinite depth: pairs outside their triangle get one, so nothing masks their keys.
_UNCOVERED_KEY = 0x7F800000 << 32

_LOW32 = 0xFFFFFFFF
# (triangle, pixel) pairs evaluated per chunk: bounds the working memory (about 100 bytes per pair) to ~100 MB.
_PAIRS_PER_CHUNK = 1 << 20
_PACK_CACHE_SIZE = 16
_SMALL_AREA_PX = 64
_ONE_CALL_GATHER = 1 << 16
_TILE_PX = 8
_NO_OWNER = np.zeros(0, dtype=np.int64)  # the kernel's owner for one scene seen by every camera


@dataclass
class RenderResult:
    """What one render call produces for B cameras.

    :param rgb: (B, H, W, 3) float32 shaded colour in [0, 1] (background colour where nothing).
    :param depth_m: (B, H, W) float32 z along the optical axis, +inf where nothing.
    :param object_id: (B, H, W) int32 `Mesh.object_id` of the visible surface, -1 where nothing.
    :param normal_cam: (B, H, W, 3) float32 unit surface normal in the camera frame facing the camera, 0 where nothing.
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    object_id: torch.Tensor
    normal_cam: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool: True where a surface was drawn."""
        return self.object_id >= 0


@dataclass
class PackedScene:
    """Triangle soup of a mesh list, ready on a device. Vertices are stored relative to `origin_m` (float64, world)
    so that float32 keeps millimetre precision for worlds far from the ENU origin.

    Per-triangle tensors (T triangles), channel-major (per-row 1-D gathers are the fast way to read tables on CPU):
    `vertex_components` (3 xyz, 3 corners, T) positions; `attribute_table` (24, T), row 8 * corner + k for the
    attributes k: world-frame normal (3), vertex colour x diffuse colour (3), uv (2); `material` (7, T): specular
    rgb, shininess, metalness, roughness, unlit (0/1); `texture_index` (T,) int64 (-1 none); `object_id` (T,) int32.
    Textures are one flat texel table `texels` (N,) int32 (RGB8 + a zero byte, as laid out in memory) with
    `texture_info` (3, X) int32 (offset, width, height). `vertices_m` and `vertex_attributes` are (T, 3, 3) and
    (T, 3, 8) views of the same data.
    """

    origin_m: np.ndarray
    vertex_components: torch.Tensor
    attribute_table: torch.Tensor
    material: torch.Tensor
    texture_index: torch.Tensor
    object_id: torch.Tensor
    texels: torch.Tensor
    texture_info: torch.Tensor

    @property
    def triangle_count(self) -> int:
        """Number of triangles."""
        return int(self.vertex_components.shape[2])

    @property
    def device(self) -> torch.device:
        """Where the tensors live."""
        return self.vertex_components.device

    @property
    def vertices_m(self) -> torch.Tensor:
        """(T, 3, 3) vertex positions relative to `origin_m` (a view)."""
        return self.vertex_components.permute(2, 1, 0)

    @property
    def vertex_attributes(self) -> torch.Tensor:
        """(T, 3, 8) per-corner attributes (a view of `attribute_table`)."""
        return self.attribute_table.T.reshape(-1, 3, 8)

    @property
    def textured(self) -> bool:
        """Whether any triangle samples a texture."""
        return self.texture_info.shape[1] > 0

    def transformed(self, T_world_object: np.ndarray, object_id: int | None = None) -> PackedScene:
        """This scene moved by a rigid 4x4 transform (and optionally relabelled `object_id`), in torch: the fast way
        to place a packed vehicle at a new pose every step (textures, materials and colours are shared, not copied).
        """
        T = np.asarray(T_world_object, dtype=np.float64)
        R = torch.as_tensor(T[:3, :3], dtype=torch.float32, device=self.device)
        n = self.triangle_count
        components = (R @ self.vertex_components.reshape(3, 3 * n)).reshape(3, 3, n)
        table = self.attribute_table.clone()
        for corner in range(3):
            rows = slice(8 * corner, 8 * corner + 3)
            table[rows] = R @ self.attribute_table[rows]
        ids = self.object_id if object_id is None else torch.full_like(self.object_id, int(object_id))
        return PackedScene(
            origin_m=T[:3, :3] @ self.origin_m + T[:3, 3],
            vertex_components=components,
            attribute_table=table,
            material=self.material,
            texture_index=self.texture_index,
            object_id=ids,
            texels=self.texels,
            texture_info=self.texture_info,
        )


def material_row(material: Material) -> np.ndarray:
    """(7,) float: specular rgb, shininess, metalness, roughness, unlit (0/1): a `PackedScene.material` column."""
    return np.array(
        [
            *material.specular_rgb,
            material.shininess,
            material.metalness,
            material.roughness,
            1.0 if material.unlit else 0.0,
        ],
        dtype=np.float32,
    )


def pack_meshes(meshes: list[Mesh], device: str | torch.device = "cpu") -> PackedScene:
    """Pack world-frame meshes into one `PackedScene` on `device` (do this once for static geometry)."""
    vertices, attributes, materials, tex_index, obj_ids = [], [], [], [], []
    texels: list[np.ndarray] = []
    texture_info: list[list[int]] = []
    texel_offset = 0
    all_v = [np.asarray(m.vertices_m) for m in meshes if len(m.faces)]
    origin = np.mean(np.concatenate(all_v), axis=0).astype(np.float64) if all_v else np.zeros(3)
    for mesh in meshes:
        faces = np.asarray(mesh.faces, dtype=np.int64)
        n_faces = len(faces)
        if n_faces == 0:
            continue
        v = (np.asarray(mesh.vertices_m, dtype=np.float64) - origin).astype(np.float32)[faces]
        vertices.append(v)
        attr = np.zeros((n_faces, 3, 8), dtype=np.float32)
        if mesh.normals is not None:
            attr[..., 0:3] = np.asarray(mesh.normals, dtype=np.float32)[faces]
        else:
            face_n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            attr[..., 0:3] = (face_n / np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-20))[:, None]
        diffuse = np.asarray(mesh.material.diffuse_rgb, dtype=np.float32)
        attr[..., 3:6] = (
            diffuse if mesh.vertex_rgb is None else np.asarray(mesh.vertex_rgb, np.float32)[faces] * diffuse
        )
        if mesh.uv is not None and mesh.texture_rgb is not None:
            attr[..., 6:8] = np.asarray(mesh.uv, dtype=np.float32)[faces]
            tex = np.asarray(mesh.texture_rgb)
            rgb8 = tex.reshape(-1, 3).astype(np.int32)
            texels.append(rgb8[:, 0] | (rgb8[:, 1] << 8) | (rgb8[:, 2] << 16))
            texture_info.append([texel_offset, tex.shape[1], tex.shape[0]])
            texel_offset += tex.shape[0] * tex.shape[1]
            tex_index.append(np.full(n_faces, len(texture_info) - 1, dtype=np.int64))
        else:
            tex_index.append(np.full(n_faces, -1, dtype=np.int64))
        attributes.append(attr)
        materials.append(np.broadcast_to(material_row(mesh.material)[:, None], (7, n_faces)))
        obj_ids.append(np.full(n_faces, mesh.object_id, dtype=np.int32))

    def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: type) -> torch.Tensor:
        arr = np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)
        return torch.as_tensor(np.ascontiguousarray(arr, dtype=dtype), device=device)

    return PackedScene(
        origin_m=origin,
        vertex_components=cat(vertices, (0, 3, 3), np.float32).permute(2, 1, 0).contiguous(),
        attribute_table=cat(attributes, (0, 3, 8), np.float32).reshape(-1, 24).T.contiguous(),
        material=torch.as_tensor(
            np.ascontiguousarray(np.concatenate(materials, axis=1) if materials else np.zeros((7, 0)), np.float32),
            device=device,
        ),
        texture_index=cat(tex_index, (0,), np.int64),
        object_id=cat(obj_ids, (0,), np.int32),
        texels=cat(texels, (1,), np.int32),
        texture_info=torch.tensor(
            np.array(texture_info).T if texture_info else np.zeros((3, 0)), dtype=torch.int32, device=device
        ),
    )


_GEOMETRY_FIELDS = ("vertices_m", "faces", "vertex_rgb", "uv", "texture_rgb", "normals")


def repainted_pack(packed: PackedScene, packed_meshes: list[Mesh], meshes: list[Mesh]) -> PackedScene | None:
    """`pack_meshes(meshes)` made from `packed` = pack_meshes(packed_meshes) when `meshes` are the same geometry (the
    same array objects, the same object ids) with other materials, as a repainted vehicle model's are: only the
    repainted meshes' diffuse colours and material columns are rewritten (an episode's car is a new repaint, and
    packing it whole cost about 0.5 ms per level of detail). None when the geometry differs."""
    if len(packed_meshes) != len(meshes):
        return None
    for a, b in zip(packed_meshes, meshes, strict=True):
        if a is not b and (
            a.object_id != b.object_id or any(getattr(a, f) is not getattr(b, f) for f in _GEOMETRY_FIELDS)
        ):
            return None
    attributes, material = packed.attribute_table.clone(), packed.material.clone()
    first = 0
    for a, b in zip(packed_meshes, meshes, strict=True):
        faces = np.asarray(b.faces, dtype=np.int64)
        end = first + len(faces)
        if a is not b and a.material is not b.material and len(faces):
            diffuse = np.asarray(b.material.diffuse_rgb, dtype=np.float32)
            corner_rgb = np.broadcast_to(
                diffuse if b.vertex_rgb is None else np.asarray(b.vertex_rgb, np.float32)[faces] * diffuse,
                (len(faces), 3, 3),
            )
            for corner in range(3):
                rows = slice(8 * corner + 3, 8 * corner + 6)
                attributes[rows, first:end] = torch.as_tensor(np.ascontiguousarray(corner_rgb[:, corner].T))
            material[:, first:end] = torch.as_tensor(material_row(b.material))[:, None]
        first = end
    return replace(packed, attribute_table=attributes, material=material)


def merge_scenes(scenes: list[PackedScene]) -> PackedScene:
    """One PackedScene with the triangles of all `scenes` (e.g. several placed vehicles seen by one camera)."""
    if len(scenes) == 1:
        return scenes[0]
    origin = scenes[0].origin_m
    merged, _ = _concat_scenes(scenes)
    shifts = [torch.as_tensor(s.origin_m - origin, dtype=torch.float32, device=s.device) for s in scenes]
    merged.origin_m = origin
    merged.vertex_components = torch.cat(
        [s.vertex_components + shift[:, None, None] for s, shift in zip(scenes, shifts, strict=True)], dim=2
    )
    return merged


def _concat_scenes(scenes: list[PackedScene]) -> tuple[PackedScene, torch.Tensor]:
    """All triangles of `scenes` in one scene, and the scene index of each triangle. Vertices keep their own scene's
    origin: callers transform each part to the camera frame before concatenating."""
    texel_offset = 0
    texture_offset = 0
    tex_idx, tex_info = [], []
    for s in scenes:
        tex_idx.append(torch.where(s.texture_index >= 0, s.texture_index + texture_offset, s.texture_index))
        info = s.texture_info.clone()
        info[0] += texel_offset
        tex_info.append(info)
        texel_offset += s.texels.shape[0]
        texture_offset += s.texture_info.shape[1]
    owner = torch.cat(
        [torch.full((s.triangle_count,), i, dtype=torch.int64, device=s.device) for i, s in enumerate(scenes)]
    )
    merged = PackedScene(
        origin_m=np.zeros(3),
        vertex_components=torch.cat([s.vertex_components for s in scenes], dim=2),
        attribute_table=torch.cat([s.attribute_table for s in scenes], dim=1),
        material=torch.cat([s.material for s in scenes], dim=1),
        texture_index=torch.cat(tex_idx),
        object_id=torch.cat([s.object_id for s in scenes]),
        texels=torch.cat([s.texels for s in scenes]),
        texture_info=torch.cat(tex_info, dim=1),
    )
    return merged, owner


def _take(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """table[:, index] for a 2-D table. Large gathers go one 1-D index_select per row: several times faster on CPU
    than a 2-D gather; small ones in one call, where the per-call cost dominates."""
    if index.numel() * table.shape[0] <= _ONE_CALL_GATHER:
        return table.index_select(1, index)
    out = torch.empty((table.shape[0], index.numel()), dtype=table.dtype, device=table.device)
    for i in range(table.shape[0]):
        torch.index_select(table[i], 0, index, out=out[i])
    return out


def _as_poses(T_camera_world: np.ndarray | torch.Tensor) -> np.ndarray:
    T = T_camera_world.detach().cpu().numpy() if isinstance(T_camera_world, torch.Tensor) else T_camera_world
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_camera_world must be (4, 4) or (B, 4, 4), got {T.shape}")
    return T


def _translation(origin_m: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = origin_m
    return T


class Rasterizer:
    """Renders world-frame meshes seen from B pinhole cameras into (B, H, W) images.

    :param width_px: image width. :param height_px: image height.
    :param device: torch device for all tensors ("cpu", "cuda").
    :param near_m: nearest drawn depth; surfaces closer than this are cut (exactly, not whole triangles).
    :param cull_back_faces: skip triangles seen from behind. Only for closed meshes with faces
        counter-clockwise seen from outside (the `Mesh` convention), such as vehicles: about halves their cost.
        Off by default: open surfaces (ground, facades) are drawn from both sides.
    :param use_kernel: on CPU, run the compiled kernels (raster_kernel.py, same result): the whole render for
        untextured scenes (vehicles), the depth test for textured ones; False: the torch path, which is what runs on
        a GPU.
    """

    def __init__(
        self,
        width_px: int,
        height_px: int,
        device: str | torch.device = "cpu",
        near_m: float = 0.05,
        cull_back_faces: bool = False,
        use_kernel: bool = True,
    ):
        self.width_px = int(width_px)
        self.height_px = int(height_px)
        self.device = torch.device(device)
        self.near_m = float(near_m)
        self.cull_back_faces = bool(cull_back_faces)
        self.use_kernel = bool(use_kernel) and self.device.type == "cpu"
        self._pack_cache: list[tuple[list[Mesh], PackedScene]] = []
        # (scene ids, scenes, concatenated scene, first triangles, counts, paint flags) of the last library
        self._library_cache: tuple | None = None
        self._intrinsics_cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ packing
    def pack(self, meshes: list[Mesh | PackedScene] | PackedScene) -> PackedScene:
        """The packed form of `meshes`, from a small identity-keyed cache (meshes are treated as immutable)."""
        if isinstance(meshes, PackedScene):
            return meshes
        if any(isinstance(m, PackedScene) for m in meshes):
            return merge_scenes([m if isinstance(m, PackedScene) else self.pack([m]) for m in meshes])
        for cached_meshes, packed in self._pack_cache:
            if len(cached_meshes) == len(meshes) and all(a is b for a, b in zip(cached_meshes, meshes, strict=True)):
                return packed
        for cached_meshes, cached in reversed(self._pack_cache):  # a repaint of a packed model: new materials only
            packed = repainted_pack(cached, cached_meshes, meshes)
            if packed is not None:
                break
        else:
            packed = pack_meshes(meshes, self.device)
        self._pack_cache.append((list(meshes), packed))
        if len(self._pack_cache) > _PACK_CACHE_SIZE:
            self._pack_cache.pop(0)
        return packed

    # ------------------------------------------------------------------ render
    def render(
        self,
        meshes: list[Mesh] | list[list[Mesh]] | PackedScene | list[PackedScene],
        T_camera_world: np.ndarray | torch.Tensor,
        K: np.ndarray,
        lighting: Lighting | list[Lighting] | np.ndarray | None = None,
        background_rgb: tuple[float, float, float] | np.ndarray | None = None,
    ) -> RenderResult:
        """Render meshes from B cameras.

        :param meshes: world-frame meshes seen by every camera (list[Mesh] or a PackedScene), or one list per camera
            (list[list[Mesh | PackedScene]] / list[PackedScene] of length B) so one call renders B different scenes.
            Moving objects: pack them once in their own frame and place them with `PackedScene.transformed`.
        :param T_camera_world: (4, 4) or (B, 4, 4) world -> camera optical frame.
        :param K: (3, 3) intrinsics shared by all cameras, pixel centres at integer coordinates.
        :param lighting: one Lighting for all cameras, one per camera, or None for the default.
        :param background_rgb: colour where nothing is drawn (default black).
        """
        T = _as_poses(T_camera_world)
        B = T.shape[0]
        scene, owner, v_cam = self._candidates(meshes, T)
        K_t = torch.as_tensor(np.asarray(K, dtype=np.float64), device=self.device)
        R_cam_world = torch.as_tensor(T[:, :3, :3], dtype=torch.float32, device=self.device)
        return self._rasterize(scene, v_cam, owner, B, K_t, R_cam_world, lighting, background_rgb)

    def draw_into(
        self,
        scenes: list[PackedScene],
        T_camera_scene: np.ndarray,
        K: np.ndarray,
        lighting: np.ndarray,
        rgb: np.ndarray,
        depth_m: np.ndarray,
        front: np.ndarray,
        view_of_camera: np.ndarray,
        gray: bool,
        threads: int = 1,
    ) -> None:
        """`render` of untextured `scenes` (one per camera, at poses T_camera_scene (B, 4, 4)) composited straight into
        uint8 views on the compiled CPU path: camera b draws over view rgb[view_of_camera[b]] (V, h, w, 3) where it is
        nearer than depth_m (V, h, w), and marks there front (V, h, w) bool; with `gray`, in its luma. The pixels
        `render` then `raster_kernel.composite_uint8` give, without the full-size images in between; with `threads`
        > 1 the shading's rows are shared out among that many threads (the same pixels)."""
        from drivesim.sim import raster_kernel  # numba compiles (or loads its cache) on first import

        if not self.use_kernel or any(scene.textured for scene in scenes):
            raise ValueError("draw_into needs the compiled CPU path and untextured scenes: use render")
        T = _as_poses(T_camera_scene)
        scene, owner, v_cam = self._candidates(list(scenes), T)
        N = v_cam.shape[2]
        intrinsics, K_inv = self._intrinsics_of(K)
        inputs = (
            np.ascontiguousarray(v_cam.reshape(9, N).numpy()), intrinsics, self.near_m, self.cull_back_faces,
            _NO_OWNER if owner is None else owner.numpy(), max(scene.triangle_count, 1),
            scene.attribute_table.numpy(), scene.material.numpy(), np.ascontiguousarray(T[:, :3, :3], np.float32),
            K_inv, _lighting_table(lighting, T.shape[0]), np.asarray(view_of_camera, dtype=np.int64), rgb, depth_m,
            front, gray,
        )  # fmt: skip
        with parallel_slot(int(threads)) as granted:
            if granted > 1:
                raster_kernel.draw_untextured_into_bands(granted, *inputs)
            else:
                raster_kernel.draw_untextured_into(*inputs)

    def _intrinsics_of(self, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(fx, fy, cx, cy) float64 and K^-1 float32 of intrinsics K, kept for the last K (a view draws with one)."""
        K_np = np.asarray(K, dtype=np.float64)
        key = K_np.tobytes()
        if self._intrinsics_cache is None or self._intrinsics_cache[0] != key:
            intrinsics = np.array([K_np[0, 0], K_np[1, 1], K_np[0, 2], K_np[1, 2]])
            self._intrinsics_cache = (key, intrinsics, np.linalg.inv(K_np).astype(np.float32))
        return self._intrinsics_cache[1], self._intrinsics_cache[2]

    def _candidates(
        self, meshes: list[Mesh] | list[list[Mesh]] | PackedScene | list[PackedScene], T: np.ndarray
    ) -> tuple[PackedScene, torch.Tensor | None, torch.Tensor]:
        """The packed scene `render` rasterizes for `meshes` seen from poses T (B, 4, 4), the camera of each of its
        candidate triangles (None: one scene seen by every camera) and their camera-frame vertices (`_to_camera`)."""
        B = T.shape[0]
        per_camera = isinstance(meshes, list) and len(meshes) > 0 and not isinstance(meshes[0], Mesh)
        if per_camera and all(m is meshes[0] for m in meshes):  # the same scene for every camera: one packing
            meshes, per_camera = meshes[0], False
        if not per_camera:
            scene = self.pack(meshes)
            return scene, None, self._to_camera(scene, T)
        if len(meshes) != B:
            raise ValueError(f"got {len(meshes)} per-camera mesh lists for {B} cameras")
        scenes = [self.pack(m) for m in meshes]
        cam_vertices = [self._to_camera(s, T[b : b + 1]) for b, s in enumerate(scenes)]
        scene, owner = _concat_scenes(scenes)
        return scene, owner, torch.cat(cam_vertices, dim=2)

    def render_instances(
        self,
        scenes: list[PackedScene],
        scene_of_camera: np.ndarray,
        T_camera_scene: np.ndarray,
        K: np.ndarray,
        lighting: Lighting | list[Lighting] | np.ndarray | None = None,
        paint: tuple[list[np.ndarray], np.ndarray] | None = None,
    ) -> RenderResult:
        """B cameras, camera b seeing one instance of `scenes[scene_of_camera[b]]` at pose T_camera_scene[b] (B, 4, 4)
        (a library of vehicle models seen by many agents): the scenes are packed together once (again only when the
        list changes) and each camera's triangles are gathered from them, so one call renders any mix of models with
        no copy of a mesh per camera. The compiled CPU path renders them as `render` with one scene per camera.

        :param lighting: as `render`, or a (B, 9) table of ambient, light direction and light colour per camera.
        :param paint: each camera's own paint of its instance: (per scene a (T,) bool mask of the triangles painted,
            (B, 10) diffuse rgb and `material_row` per camera). A painted triangle's colour is its packed colour
            (pack the paint's triangles with a white diffuse) times the camera's diffuse, its material the camera's.
            Not on the compiled CPU path (it raises).
        """
        scene_of_camera = np.asarray(scene_of_camera, dtype=np.int64)
        if self.use_kernel:
            if paint is not None:
                raise ValueError("per-camera paint needs the torch path (use_kernel=False)")
            return self.render([scenes[i] for i in scene_of_camera], T_camera_scene, K, lighting)
        library, first, count = self._library(scenes, None if paint is None else paint[0])
        dev = self.device
        T = _as_poses(T_camera_scene)
        B = T.shape[0]
        # As `_to_camera`, in the same order of float operations: T @ translation(origin of the camera's scene).
        M = T @ np.stack([_translation(scenes[i].origin_m) for i in range(len(scenes))])[scene_of_camera]
        M = torch.as_tensor(M[:, :3, :], dtype=torch.float32, device=dev)
        which = torch.as_tensor(scene_of_camera, device=dev)
        per_camera = count.index_select(0, which)
        total = int(per_camera.sum())
        camera = torch.repeat_interleave(torch.arange(B, device=dev), per_camera, output_size=total)
        start = (per_camera.cumsum(0) - per_camera).index_select(0, camera)
        triangle = first.index_select(0, which).index_select(0, camera) + torch.arange(total, device=dev) - start
        X, Y, Z = library.vertex_components.index_select(2, triangle)  # each (3 corners, total)
        M_c = M.index_select(0, camera)  # (total, 3, 4)
        v_cam = torch.empty((3, 3, total), dtype=torch.float32, device=dev)
        for c in range(3):
            torch.mul(X, M_c[:, c, 0], out=v_cam[c])
            v_cam[c].add_(M_c[:, c, 3]).addcmul_(Y, M_c[:, c, 1]).addcmul_(Z, M_c[:, c, 2])
        K_t = torch.as_tensor(np.asarray(K, dtype=np.float64), device=dev)
        R_cam_scene = torch.as_tensor(T[:, :3, :3], dtype=torch.float32, device=dev)
        instance_paint = None
        if paint is not None:
            rows = torch.as_tensor(np.asarray(paint[1], dtype=np.float32).T.copy(), device=dev)  # (10, B)
            instance_paint = (self._library_cache[5], rows)
        return self._rasterize(
            library, v_cam, camera, B, K_t, R_cam_scene, lighting, None, source=triangle, paint=instance_paint
        )

    def _library(
        self, scenes: list[PackedScene], paint_masks: list[np.ndarray] | None
    ) -> tuple[PackedScene, torch.Tensor, torch.Tensor]:
        """`scenes` concatenated (each keeps its own origin), and each one's first triangle and triangle count; the
        paint masks concatenated are kept with them."""
        key = tuple(id(scene) for scene in scenes)
        if self._library_cache is None or self._library_cache[0] != key:
            merged, _ = _concat_scenes(scenes)
            count = torch.tensor([scene.triangle_count for scene in scenes], dtype=torch.int64, device=self.device)
            masks = None
            if paint_masks is not None:
                masks = torch.as_tensor(np.concatenate(paint_masks).astype(bool), device=self.device)
            self._library_cache = (key, list(scenes), merged, count.cumsum(0) - count, count, masks)
        return self._library_cache[2], self._library_cache[3], self._library_cache[4]

    def _to_camera(self, scene: PackedScene, T: np.ndarray) -> torch.Tensor:
        """Camera-frame vertices of `scene` seen from poses T (B, 4, 4), component-major: (3 xyz, 3 corners, B * T)
        with candidate n = camera * T + triangle (contiguous rows make the per-triangle setup fast)."""
        B, n_tri = T.shape[0], scene.triangle_count
        if self.use_kernel:  # CPU: one numpy matrix product, without torch's per-op costs
            M_np = (T @ _translation(scene.origin_m))[:, :3, :].astype(np.float32)  # (B, 3, 4)
            V = scene.vertex_components.numpy().reshape(3, 3 * n_tri)
            cam = M_np[:, :, :3] @ V + M_np[:, :, 3:]  # (B, 3 xyz, 3 corners * T)
            return torch.from_numpy(cam.reshape(B, 3, 3, n_tri).transpose(1, 2, 0, 3).reshape(3, 3, B * n_tri))
        T_cam_scene = torch.as_tensor((T @ _translation(scene.origin_m))[:, :3, :], dtype=torch.float32)
        M = T_cam_scene.to(self.device)[:, :, :, None]  # (B, 3, 4, 1): broadcasts over (corner, B, T)
        X, Y, Z = scene.vertex_components[:, :, None, :]  # each (3 corners, 1, T)
        out = torch.empty((3, 3, B, n_tri), dtype=torch.float32, device=self.device)
        for c in range(3):
            torch.mul(X, M[:, c, 0], out=out[c])
            out[c].add_(M[:, c, 3]).addcmul_(Y, M[:, c, 1]).addcmul_(Z, M[:, c, 2])
        return out.reshape(3, 3, B * n_tri)

    # ------------------------------------------------------------------ core
    def _setup(self, vc: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per candidate triangle, from camera-frame vertices vc (3 xyz, 3 corners, N): the kept candidates' indices
        (n,), a column table (13, n) = bbox width, edge coefficients (9) re-based at the bbox corner, |det|, corner
        x0, y0, and their inclusive pixel bboxes (n, 4) = x0, y0, x1, y1.

        Edge coefficients: w_i(u, v) = c_i . K^-1 [u, v, 1] with c_0 = P1 x P2, c_1 = P2 x P0, c_2 = P0 x P1, signed so
        that inside means all w_i >= 0; then depth = |det| / sum(w) with det = P0 . (P1 x P2).
        """
        W, H, near = self.width_px, self.height_px, self.near_m
        fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        N = vc.shape[2]
        zs = vc[2]
        n_front = (zs >= near).sum(0)
        zc = zs.clamp_min(near)
        u = (vc[0] / zc).mul_(fx).add_(cx)
        v = (vc[1] / zc).mul_(fy).add_(cy)
        lo = torch.stack(
            [torch.minimum(torch.minimum(u[0], u[1]), u[2]), torch.minimum(torch.minimum(v[0], v[1]), v[2])]
        )
        hi = torch.stack(
            [torch.maximum(torch.maximum(u[0], u[1]), u[2]), torch.maximum(torch.maximum(v[0], v[1]), v[2])]
        )
        crossing = ((n_front > 0) & (n_front < 3)).nonzero().squeeze(1)
        if crossing.numel():
            # Bbox of the polygon clipped at z = near: vertices in front plus edge/plane intersections.
            p = vc[:, :, crossing].permute(2, 1, 0)  # (n, corner, xyz)
            z = p[..., 2]
            pts, ok = [p[:, i] for i in range(3)], [z[:, i] >= near for i in range(3)]
            for i, j in ((0, 1), (1, 2), (2, 0)):
                zi, zj = z[:, i], z[:, j]
                cut = (zi - near) * (zj - near) < 0
                s = ((near - zi) / torch.where(cut, zj - zi, torch.ones_like(zi))).clamp(0, 1)
                pts.append(p[:, i] + s[:, None] * (p[:, j] - p[:, i]))
                ok.append(cut)
            pts_t, ok_t = torch.stack(pts, 1), torch.stack(ok, 1)
            zp = pts_t[..., 2].clamp_min(near)
            puv = torch.stack([fx * pts_t[..., 0] / zp + cx, fy * pts_t[..., 1] / zp + cy], -1)  # (n, 6, 2)
            inf = torch.tensor(float("inf"), device=vc.device)
            lo[:, crossing] = torch.where(ok_t[..., None], puv, inf).amin(1).T
            hi[:, crossing] = torch.where(ok_t[..., None], puv, -inf).amax(1).T
        lo = lo.clamp_(-1, W + H).ceil_().clamp_min_(0)
        hi = hi.clamp_(-1, W + H).floor_()
        hi[0].clamp_max_(W - 1)
        hi[1].clamp_max_(H - 1)
        keep = (n_front > 0) & (hi[0] >= lo[0]) & (hi[1] >= lo[1])
        idx = keep.nonzero().squeeze(1)
        if idx.numel() < N:
            vc, lo, hi = _take(vc.reshape(9, N), idx).reshape(3, 3, -1), _take(lo, idx), _take(hi, idx)
        (x0, x1, x2), (y0, y1, y2), (z0, z1, z2) = vc

        def cross(a1: torch.Tensor, a2: torch.Tensor, b1: torch.Tensor, b2: torch.Tensor) -> torch.Tensor:
            return torch.addcmul(a1 * b2, a2, b1, value=-1.0)  # a1 b2 - a2 b1: one component of a cross product

        cx0, cy0, cz0 = cross(y1, z1, y2, z2), cross(z1, x1, z2, x2), cross(x1, y1, x2, y2)  # P1 x P2
        cx1, cy1, cz1 = cross(y2, z2, y0, z0), cross(z2, x2, z0, x0), cross(x2, y2, x0, y0)  # P2 x P0
        cx2, cy2, cz2 = cross(y0, z0, y1, z1), cross(z0, x0, z1, x1), cross(x0, y0, x1, y1)  # P0 x P1
        det = torch.addcmul(torch.addcmul(x0 * cx0, y0, cy0), z0, cz0)
        sign = torch.sign(det)
        abs_det = det.abs()
        scale = (x0.abs() + y0.abs() + z0.abs() + x1.abs() + y1.abs() + z1.abs() + x2.abs() + y2.abs() + z2.abs()) / 3
        good = abs_det > 1e-9 * scale**3  # triangles seen exactly edge-on (or degenerate) cover nothing
        if self.cull_back_faces:
            # det = P0 . (P1 x P2) = -(face normal . (camera - P0)): negative when the front (CCW) side faces us.
            good &= det < 0
        cols = [(hi[0] - lo[0] + 1)]
        for ex, ey, ez in ((cx0, cy0, cz0), (cx1, cy1, cz1), (cx2, cy2, cz2)):
            a = ex * (sign / fx)
            b = ey * (sign / fy)
            c = torch.addcmul(torch.addcmul(ez * sign, a, lo[0] - cx), b, lo[1] - cy)  # w at the bbox corner
            cols += [a, b, c]
        cols += [abs_det, lo[0], lo[1]]
        table = torch.stack(cols, 0)
        bbox = torch.cat([lo, hi]).T.to(torch.int64)
        if not bool(good.all()):
            sel = good.nonzero().squeeze(1)
            idx, table, bbox = idx[sel], _take(table, sel), bbox[sel]
        return idx, table, bbox

    def _rasterize(
        self,
        scene: PackedScene,
        vc: torch.Tensor,
        owner: torch.Tensor | None,
        B: int,
        K: torch.Tensor,
        R_cam_world: torch.Tensor,
        lighting: Lighting | list[Lighting] | np.ndarray | None,
        background_rgb: tuple[float, float, float] | np.ndarray | None,
        source: torch.Tensor | None = None,
        paint: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> RenderResult:
        """Depth test and shading of the candidates `vc`: with `owner`, candidate n is seen by camera owner[n] and is
        triangle `source[n]` of the scene (n itself when source is None); without, triangle n % T of camera n // T."""
        W, H, dev = self.width_px, self.height_px, self.device
        if self.use_kernel and not scene.textured:
            return self._rasterize_kernel(scene, vc, owner, B, K, R_cam_world, lighting, background_rgb)
        idx, cols, bbox = self._setup(vc, K)
        if owner is None:  # shared scene: candidate n is triangle n % T seen by camera n // T
            T_count = max(scene.triangle_count, 1)
            tri_camera = idx // T_count
            tri_source = idx - tri_camera * T_count
        else:
            tri_camera, tri_source = owner[idx], (idx if source is None else source[idx])
        bw = bbox[:, 2] - bbox[:, 0] + 1
        bh = bbox[:, 3] - bbox[:, 1] + 1
        if self.use_kernel:
            zbuf = self._depth_test_kernel(cols, bbox, tri_camera, B)
            return self._resolve(zbuf, scene, cols, tri_camera, tri_source, B, K, R_cam_world, lighting, background_rgb)
        resolve_paint = {"paint": paint} if paint is not None else {}
        base_pix = tri_camera * (H * W) + bbox[:, 1] * W + bbox[:, 0]
        # Slack after the image: padded tile pixels past the last row land there instead of being clamped.
        zbuf = torch.full((B * H * W + _TILE_PX * (W + 1),), _EMPTY_KEY, dtype=torch.int64, device=dev)

        # Small triangles (most of a vehicle mesh) are expanded into their exact (triangle, pixel) pairs; larger ones
        # are covered by 8 x 8 tiles, culled per tile and evaluated as dense blocks without per-pixel gathers.
        area = bw * bh
        small = area <= _SMALL_AREA_PX
        members = small.nonzero().squeeze(1)
        if members.numel():
            rows = _take(cols, members).T.contiguous()
            self._raster_pairs(zbuf, rows, base_pix.index_select(0, members), area.index_select(0, members), members)
        members = (~small).nonzero().squeeze(1)
        if members.numel():
            self._raster_tiles(zbuf, cols, bw, bh, base_pix, members, _TILE_PX, _TILE_PX)
        return self._resolve(
            zbuf, scene, cols, tri_camera, tri_source, B, K, R_cam_world, lighting, background_rgb, **resolve_paint
        )

    def _rasterize_kernel(
        self,
        scene: PackedScene,
        vc: torch.Tensor,
        owner: torch.Tensor | None,
        B: int,
        K: torch.Tensor,
        R_cam_world: torch.Tensor,
        lighting: Lighting | list[Lighting] | np.ndarray | None,
        background_rgb: tuple[float, float, float] | np.ndarray | None,
    ) -> RenderResult:
        """The whole render of an untextured scene in the compiled CPU kernels (set-up, depth test, shading): the
        torch path's formulas without its per-call costs, which dominate for a car of a few hundred triangles."""
        from drivesim.sim import raster_kernel  # numba compiles (or loads its cache) on first import

        W, H = self.width_px, self.height_px
        N = vc.shape[2]
        K_np = K.cpu().numpy()
        size = B * H * W
        rgb = np.empty((size, 3), dtype=np.float32)
        depth_out = np.empty(size, dtype=np.float32)
        object_id = np.empty(size, dtype=np.int32)
        normal = np.empty((size, 3), dtype=np.float32)
        bg = np.zeros(3, dtype=np.float32) if background_rgb is None else np.asarray(background_rgb, np.float32)
        raster_kernel.render_untextured(
            np.ascontiguousarray(vc.reshape(9, N).numpy()),
            np.array([K_np[0, 0], K_np[1, 1], K_np[0, 2], K_np[1, 2]]), W, H, self.near_m, self.cull_back_faces,
            _NO_OWNER if owner is None else owner.numpy(), max(scene.triangle_count, 1),
            scene.attribute_table.numpy(), scene.material.numpy(), scene.object_id.numpy(),
            np.ascontiguousarray(R_cam_world.numpy()), np.linalg.inv(K_np).astype(np.float32),
            _lighting_table(lighting, B), bg, rgb, depth_out, object_id, normal,
        )  # fmt: skip
        return RenderResult(
            rgb=torch.from_numpy(rgb.reshape(B, H, W, 3)),
            depth_m=torch.from_numpy(depth_out.reshape(B, H, W)),
            object_id=torch.from_numpy(object_id.reshape(B, H, W)),
            normal_cam=torch.from_numpy(normal.reshape(B, H, W, 3)),
        )

    def _depth_test_kernel(
        self, cols: torch.Tensor, bbox: torch.Tensor, tri_camera: torch.Tensor, B: int
    ) -> torch.Tensor:
        """The z-buffer of packed keys (as the torch path makes it) from the compiled CPU depth test."""
        from drivesim.sim import raster_kernel  # numba compiles (or loads its cache) on first import

        size = B * self.height_px * self.width_px
        depth = np.full(size, np.inf, dtype=np.float32)
        winner = np.full(size, -1, dtype=np.int64)
        raster_kernel.depth_test(
            np.ascontiguousarray(cols.numpy()),
            np.ascontiguousarray(bbox.numpy()),
            np.ascontiguousarray(tri_camera.numpy()),
            self.width_px,
            self.height_px,
            self.near_m,
            depth,
            winner,
        )
        keys = np.full(size, _EMPTY_KEY, dtype=np.int64)
        covered = winner >= 0
        keys[covered] = (depth[covered].view(np.int32).astype(np.int64) << 32) | winner[covered]
        return torch.from_numpy(keys)

    def _raster_pairs(
        self, zbuf: torch.Tensor, rows: torch.Tensor, base_pix: torch.Tensor, counts: torch.Tensor, ids: torch.Tensor
    ) -> None:
        """Depth-test every (triangle, pixel-in-bbox) pair of small triangles: rows (m, 13) of the column table,
        their first pixel index, bbox areas and triangle ids (what the z-buffer key stores)."""
        ends = counts.cumsum(0)
        n, start = int(counts.numel()), 0
        while start < n:
            base = int(ends[start - 1]) if start > 0 else 0
            stop = int(torch.searchsorted(ends, base + _PAIRS_PER_CHUNK, right=True))
            stop = min(max(stop, start + 1), n)
            self._raster_pair_chunk(zbuf, rows[start:stop], base_pix[start:stop], counts[start:stop], ids[start:stop])
            start = stop

    def _raster_pair_chunk(
        self, zbuf: torch.Tensor, rows: torch.Tensor, base_pix: torch.Tensor, counts: torch.Tensor, ids: torch.Tensor
    ) -> None:
        dev = self.device
        total = int(counts.sum())
        first = (counts.cumsum(0) - counts).to(torch.float32)
        tri = torch.repeat_interleave(torch.arange(counts.numel(), device=dev), counts, output_size=total)
        r = rows.index_select(0, tri)  # rows of a small table: cheap, cache-resident gathers
        local = torch.arange(total, dtype=torch.float32, device=dev) - first.index_select(0, tri)
        bw = r[:, 0]
        yo = torch.floor((local + 0.5) / bw)
        xo = local - yo * bw
        w0 = torch.addcmul(torch.addcmul(r[:, 3], r[:, 1], xo), r[:, 2], yo)
        w1 = torch.addcmul(torch.addcmul(r[:, 6], r[:, 4], xo), r[:, 5], yo)
        w2 = torch.addcmul(torch.addcmul(r[:, 9], r[:, 7], xo), r[:, 8], yo)
        ssum = w0 + w1 + w2
        # all w_i >= 0 (inside), sum > 0 (in front), depth = |det| / sum >= near
        inside = (torch.minimum(torch.minimum(w0, w1), w2) >= 0) & (ssum > 0) & (ssum * self.near_m <= r[:, 10])
        sel = inside.nonzero().squeeze(1)
        depth = r[:, 10].index_select(0, sel) / ssum.index_select(0, sel)
        local_tri = tri.index_select(0, sel)
        key = (depth.view(torch.int32).to(torch.int64) << 32) | ids.index_select(0, local_tri)
        offset = yo.index_select(0, sel) * self.width_px + xo.index_select(0, sel)
        pix = base_pix.index_select(0, local_tri) + offset.to(torch.int64)
        zbuf.scatter_reduce_(0, pix, key, reduce="amin")

    def _raster_tiles(
        self,
        zbuf: torch.Tensor,
        cols: torch.Tensor,
        bw: torch.Tensor,
        bh: torch.Tensor,
        base_pix: torch.Tensor,
        members: torch.Tensor,
        tile_w: int,
        tile_h: int,
    ) -> None:
        """Depth-test triangles `members`, covering each bbox with tile_w x tile_h tiles evaluated as dense blocks."""
        dev, W = self.device, self.width_px
        ntx = (bw.index_select(0, members) + tile_w - 1) // tile_w
        nty = (bh.index_select(0, members) + tile_h - 1) // tile_h
        n_tiles = ntx * nty
        total = int(n_tiles.sum())
        if total == members.numel():  # one tile per triangle
            tri = members
            ox = oy = None
        else:
            owner = torch.repeat_interleave(torch.arange(members.numel(), device=dev), n_tiles, output_size=total)
            local = torch.arange(total, device=dev) - (n_tiles.cumsum(0) - n_tiles).index_select(0, owner)
            ntx_t = ntx.index_select(0, owner)
            ty = local // ntx_t
            ox, oy = (local - ty * ntx_t) * tile_w, ty * tile_h
            tri = members.index_select(0, owner)
        g = _take(cols, tri)  # (13, tiles)
        coef = g[1:10].clone()  # a0 b0 c0 a1 b1 c1 a2 b2 c2 at the tile origin
        rw, rh = bw.index_select(0, tri), bh.index_select(0, tri)  # pixels of the bbox from the tile origin on
        pix0 = base_pix.index_select(0, tri)
        if ox is not None:
            oxf, oyf = ox.to(torch.float32), oy.to(torch.float32)
            for i in range(3):
                coef[3 * i + 2] += coef[3 * i] * oxf + coef[3 * i + 1] * oyf
            # Drop tiles entirely outside one edge (the edge function's maximum over the tile is negative).
            keep = torch.ones_like(oxf, dtype=torch.bool)
            for i in range(3):
                a, b, c = coef[3 * i], coef[3 * i + 1], coef[3 * i + 2]
                keep &= c + a.clamp_min(0) * (tile_w - 1) + b.clamp_min(0) * (tile_h - 1) >= 0
            sel = keep.nonzero().squeeze(1)
            coef, g, tri = _take(coef, sel), _take(g, sel), tri.index_select(0, sel)
            ox, oy = ox.index_select(0, sel), oy.index_select(0, sel)
            rw, rh = rw.index_select(0, sel) - ox, rh.index_select(0, sel) - oy
            pix0 = pix0.index_select(0, sel) + oy * W + ox
        # Pixel-in-tile-major layout (tile_h * tile_w, tiles): broadcasting keeps the long axis innermost, where
        # torch's CPU kernels vectorise.
        per_chunk = max(1, _PAIRS_PER_CHUNK // (tile_w * tile_h))
        yi, xi = torch.meshgrid(
            torch.arange(tile_h, device=dev), torch.arange(tile_w, device=dev), indexing="ij"
        )  # fmt: skip
        xi, yi = xi.reshape(-1, 1), yi.reshape(-1, 1)
        xs, ys = xi.to(torch.float32), yi.to(torch.float32)
        offsets = yi * W + xi
        for s in range(0, tri.numel(), per_chunk):
            e = slice(s, s + per_chunk)
            c = coef[:, e]
            w0 = torch.addcmul(torch.addcmul(c[2], c[0], xs), c[1], ys)
            w1 = torch.addcmul(torch.addcmul(c[5], c[3], xs), c[4], ys)
            w2 = torch.addcmul(torch.addcmul(c[8], c[6], xs), c[7], ys)
            ssum = w0 + w1 + w2
            abs_det = g[10, e]
            room = torch.addcmul(abs_det, ssum, torch.tensor(-self.near_m))  # |det| - near sum(w) >= 0: depth >= near
            # Inside the triangle (all w_i >= 0), beyond the near plane and inside the bbox.
            inside = torch.minimum(torch.minimum(w0, w1), torch.minimum(w2, room)) >= 0
            inside &= (xi < rw[e]) & (yi < rh[e])
            # Pairs outside get depth |det| / 0 = +inf, a key at or above _UNCOVERED_KEY: cheaper than masking keys.
            # abs(): sum(w) is negative outside (or -0.0), and |det| / -0.0 = -inf would sort first.
            depth = abs_det / (ssum * inside).abs_()
            key = ((depth.view(torch.int32).to(torch.int64) << 32) | tri[e]).reshape(-1)
            zbuf.scatter_reduce_(0, (pix0[e] + offsets).reshape(-1), key, reduce="amin")

    def _resolve(
        self,
        zbuf: torch.Tensor,
        scene: PackedScene,
        table: torch.Tensor,
        tri_camera: torch.Tensor,
        tri_source: torch.Tensor,
        B: int,
        K: torch.Tensor,
        R_cam_world: torch.Tensor,
        lighting: Lighting | list[Lighting] | np.ndarray | None,
        background_rgb: tuple[float, float, float] | np.ndarray | None,
        paint: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> RenderResult:
        """Per covered pixel: the winner's perspective-correct barycentrics, attributes and shading. Vectors are kept
        channel-major, (3, P), so that every op runs over long contiguous rows. `paint`: (per scene triangle, whether
        it takes its camera's paint; (10, B) each camera's diffuse rgb and material row), see `render_instances`."""
        W, H, dev = self.width_px, self.height_px, self.device
        HW = H * W
        bg = (
            torch.zeros(3)
            if background_rgb is None
            else torch.as_tensor(np.asarray(background_rgb), dtype=torch.float32)
        )
        rgb = bg.to(dev)[:, None].expand(3, B * HW).clone()
        depth_out = torch.full((B * HW,), float("inf"), device=dev)
        object_id = torch.full((B * HW,), -1, dtype=torch.int32, device=dev)
        normal_out = torch.zeros((3, B * HW), device=dev)

        pix = (zbuf[: B * HW] < _UNCOVERED_KEY).nonzero().squeeze(1)  # sorted: each camera's pixels are one block
        key = zbuf.index_select(0, pix)
        cand = key & _LOW32
        depth = (key >> 32).to(torch.int32).view(torch.float32)
        row = pix // W  # = camera * H + y
        xf = (pix - row * W).to(torch.float32)
        yf = (row % H).to(torch.float32) if B > 1 else row.to(torch.float32)
        e = _take(table, cand)
        xo = xf - e[11]
        yo = yf - e[12]
        w0 = torch.addcmul(torch.addcmul(e[3], e[1], xo), e[2], yo)
        w1 = torch.addcmul(torch.addcmul(e[6], e[4], xo), e[5], yo)
        w2 = torch.addcmul(torch.addcmul(e[9], e[7], xo), e[8], yo)
        inv_sum = 1.0 / (w0 + w1 + w2)
        src = tri_source.index_select(0, cand)
        a = _take(scene.attribute_table, src)  # (24, P): corner-major, 8 attributes per corner
        attr = torch.addcmul(torch.addcmul(a[0:8] * (w0 * inv_sum), a[8:16], w1 * inv_sum), a[16:24], w2 * inv_sum)

        normal_cam, to_viewer = _camera_normals(attr[0:3], R_cam_world, K, row // H if B > 1 else None, xf, yf)
        base = _textured_base(scene, src, attr) if scene.textured else attr[3:6]
        mat = _take(scene.material, src)
        if paint is not None:
            base, mat = _painted(base, mat, src, row // H, paint)
        amb, ldir, lrgb = _lighting_tensors(lighting, B, dev)
        if B > 1:
            cam = row // H
            amb, ldir, lrgb = _take(amb.T, cam), _take(ldir.T, cam), _take(lrgb.T, cam)
        else:
            amb, ldir, lrgb = amb[0, :, None], ldir[0, :, None], lrgb[0, :, None]
        shaded = shade_blinn_phong(
            base, normal_cam, to_viewer, mat[0:3], mat[3], mat[4], mat[5], mat[6], amb, ldir, lrgb
        )
        for c in range(3):
            rgb[c].index_copy_(0, pix, shaded[c])
            normal_out[c].index_copy_(0, pix, normal_cam[c])
        depth_out.index_copy_(0, pix, depth)
        object_id.index_copy_(0, pix, scene.object_id.index_select(0, src))
        return RenderResult(
            rgb=rgb.T.reshape(B, H, W, 3).contiguous(),
            depth_m=depth_out.reshape(B, H, W),
            object_id=object_id.reshape(B, H, W),
            normal_cam=normal_out.T.reshape(B, H, W, 3).contiguous(),
        )


def _camera_normals(
    normal_world: torch.Tensor,
    R_cam_world: torch.Tensor,
    K: torch.Tensor,
    camera: torch.Tensor | None,
    xf: torch.Tensor,
    yf: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(normal, to viewer), (3, P) each in the camera frame at pixels (xf, yf), the normal turned to face the viewer
    (two-sided). `camera`: each pixel's camera (None for one camera)."""
    if camera is None:
        normal_cam = R_cam_world[0] @ normal_world
    else:  # each pixel's camera rotation, gathered (no per-camera loop: thousands of cameras on a GPU)
        R_pixel = R_cam_world.index_select(0, camera)  # (P, 3, 3)
        normal_cam = torch.einsum("pij,jp->ip", R_pixel, normal_world)
    K_inv = torch.as_tensor(np.linalg.inv(K.cpu().numpy()), dtype=torch.float32, device=normal_world.device)
    ray = torch.addcmul(torch.addcmul(K_inv[:, 2:3], K_inv[:, 0:1], xf), K_inv[:, 1:2], yf)
    to_viewer = normalize3(-ray)
    normal_cam = normalize3(normal_cam)
    facing = (dot3(normal_cam, to_viewer) >= 0).to(torch.float32).mul_(2.0).sub_(1.0)  # +1 or -1: two-sided
    normal_cam *= facing
    return normal_cam, to_viewer


def _textured_base(scene: PackedScene, src: torch.Tensor, attr: torch.Tensor) -> torch.Tensor:
    """The (3, P) base colour of the pixels of triangles `src`: the interpolated colour times the texture, on the
    textured triangles."""
    base = attr[3:6]
    tex_id = scene.texture_index.index_select(0, src)
    textured = (tex_id >= 0).nonzero().squeeze(1)
    if textured.numel() == tex_id.numel():
        base = base * _sample_bilinear(scene.texels, _take(scene.texture_info, tex_id), attr[6], attr[7])
    elif textured.numel():
        info = _take(scene.texture_info, tex_id.index_select(0, textured))
        uv = _take(attr[6:8], textured)
        texture = _sample_bilinear(scene.texels, info, uv[0], uv[1])
        base = base.clone()
        for c in range(3):
            base[c].index_copy_(0, textured, base[c].index_select(0, textured) * texture[c])
    return base


def _painted(
    base: torch.Tensor,
    mat: torch.Tensor,
    src: torch.Tensor,
    cam: torch.Tensor,
    paint: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Base colour (3, P) and material (7, P) of covered pixels with each painted triangle's pixels in its camera's
    paint: colour times the paint's diffuse, the paint's material row."""
    flags, rows = paint
    painted = flags.index_select(0, src).nonzero().squeeze(1)
    if painted.numel() == 0:
        return base, mat
    r = _take(rows, cam.index_select(0, painted))  # (10, n)
    base, mat = base.clone(), mat.clone()
    for c in range(3):
        base[c].index_copy_(0, painted, base[c].index_select(0, painted) * r[c])
    for k in range(7):
        mat[k].index_copy_(0, painted, r[3 + k])
    return base, mat


def _lighting_table(lighting: Lighting | list[Lighting] | np.ndarray | None, B: int) -> np.ndarray:
    """(B, 9) float32: ambient, unit light direction and light colour of each camera (a table is taken as it is)."""
    if isinstance(lighting, np.ndarray):
        if lighting.shape != (B, 9):
            raise ValueError(f"a lighting table must be ({B}, 9), got {lighting.shape}")
        return lighting.astype(np.float32)
    if lighting is None:
        lighting = Lighting()
    lights = lighting if isinstance(lighting, list) else [lighting] * B
    if len(lights) != B:
        raise ValueError(f"got {len(lights)} lightings for {B} cameras")
    table = np.zeros((B, 9), dtype=np.float32)
    for b, light in enumerate(lights):
        direction = np.asarray(light.light_dir_cam, dtype=np.float64)
        table[b, 0:3] = light.ambient_rgb
        table[b, 3:6] = direction / max(np.linalg.norm(direction), 1e-12)
        table[b, 6:9] = light.light_rgb
    return table


def _lighting_tensors(
    lighting: Lighting | list[Lighting] | np.ndarray | None, B: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, 3) ambient, unit light direction and light colour."""
    t = torch.as_tensor(_lighting_table(lighting, B), device=device)
    return t[:, 0:3], t[:, 3:6], t[:, 6:9]


def _sample_bilinear(texels: torch.Tensor, info: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear texture lookup with clamp-to-edge (OpenGL's GL_LINEAR, texel centres at ((i + 0.5) / width, ...)).

    :param texels: (N,) int32 packed RGB8 texel table. :param info: (3, P) int32 offset, width, height of each pixel's
    texture. :param u, v: (P,) texture coordinates. :returns: (3, P) colour in [0, 1].
    """
    offset, tw, th = info[0], info[1], info[2]
    x = u * tw - 0.5
    y = v * th - 0.5
    x0 = x.floor()
    y0 = y.floor()
    fx = x - x0
    fy = y - y0
    x0 = x0.to(torch.int32)
    y0 = y0.to(torch.int32)
    w_max, h_max = tw - 1, th - 1
    xa, xb = torch.minimum(x0.clamp_min(0), w_max), torch.minimum((x0 + 1).clamp_min(0), w_max)
    ya = torch.addcmul(offset, torch.minimum(y0.clamp_min(0), h_max), tw)
    yb = torch.addcmul(offset, torch.minimum((y0 + 1).clamp_min(0), h_max), tw)

    def fetch(index: torch.Tensor) -> torch.Tensor:  # (4, P) float in [0, 255]: r, g, b and an unused byte
        # Byte order: r is the low byte, first in memory on little-endian machines (x86, ARM, CUDA devices).
        packed = texels.index_select(0, index)
        return packed.view(torch.uint8).reshape(-1, 4).T.to(torch.float32)

    top = torch.lerp(fetch(ya + xa), fetch(ya + xb), fx)
    bottom = torch.lerp(fetch(yb + xa), fetch(yb + xb), fx)
    return torch.lerp(top[0:3], bottom[0:3], fy).mul_(1.0 / 255.0)


def roi_intrinsics(K: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray:
    """Intrinsics of the (x0, y0, w, h) region of an image as an image of its own: render a region of interest with
    `Rasterizer(w, h).render(..., roi_intrinsics(K, roi))`; it matches `forward_warp(..., roi=roi)` pixel for pixel."""
    x0, y0, _, _ = roi
    K_roi = np.array(K, dtype=np.float64, copy=True)
    K_roi[0, 2] -= x0
    K_roi[1, 2] -= y0
    return K_roi


def composite(
    rgb: torch.Tensor, depth_m: torch.Tensor, render: RenderResult
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rendered meshes (vehicles) inserted into a view (a warped frame) with a per-pixel depth test, so occlusion
    works both ways (DESIGN §4 step 4): the view covers a mesh only where it is nearer by more than
    `raster_kernel.OCCLUDER_MIN_GAP` of the mesh's depth.

    :param rgb: (B, H, W, 3) uint8 or float [0, 1] view. :param depth_m: (B, H, W) its depth (+inf: sky or empty).
    :param render: the same cameras' RenderResult.
    :returns: composited rgb (dtype of `rgb`), depth (B, H, W), and the (B, H, W) bool mask of pixels where the
        rendered meshes are in front (for harmonization and the collision reward).
    """
    from drivesim.sim.raster_kernel import OCCLUDER_MIN_GAP

    front = torch.isfinite(render.depth_m) & (render.depth_m * (1.0 - OCCLUDER_MIN_GAP) <= depth_m)
    mesh_rgb = render.rgb
    if rgb.dtype == torch.uint8:
        mesh_rgb = (mesh_rgb * 255.0 + 0.5).to(torch.uint8)
    out_rgb = torch.where(front[..., None], mesh_rgb.to(rgb.dtype), rgb)
    return out_rgb, torch.minimum(render.depth_m, depth_m), front


def render_meshes(
    meshes: list[Mesh],
    T_camera_world: np.ndarray | torch.Tensor,
    K: np.ndarray,
    width_px: int,
    height_px: int,
    lighting: Lighting | None = None,
    background_rgb: tuple[float, float, float] | None = None,
    device: str | torch.device = "cpu",
) -> RenderResult:
    """One-shot convenience: build a Rasterizer and render (use a Rasterizer to benefit from packing caches)."""
    return Rasterizer(width_px, height_px, device).render(meshes, T_camera_world, K, lighting, background_rgb)


def through_body_count(car_depth_m: np.ndarray, world_depth_m: np.ndarray, car_shown: np.ndarray) -> int:
    """Background pixels drawn through a car body: pixels where the car's own depth buffer car_depth_m (..., H, W)
    (+inf where no car) has the car and the world's depth world_depth_m there is not nearer by more than
    `raster_kernel.OCCLUDER_MIN_GAP` of the car's depth (the car stands in front of it), yet the output shows the world
    (car_shown False)."""
    from drivesim.sim.raster_kernel import OCCLUDER_MIN_GAP

    car = np.isfinite(car_depth_m)
    world_behind = car_depth_m * (1.0 - OCCLUDER_MIN_GAP) <= world_depth_m
    return int(np.count_nonzero(car & world_behind & ~np.asarray(car_shown, dtype=bool)))
