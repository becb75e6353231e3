"""Each agent's camera view (paper §III-A, DESIGN §4 steps 3-5): the recorded frame warped to the agent's pose with
every other car inserted, lit like the scene and harmonized, rendered only in the policy's region of interest.

One `ViewSynthesizer.render` call produces B views:
1. the agent's full pose from its associated recorded frame, T_world_agent = T_world_vehicle[frame] @ planar(q_long,
   q_lat, q_rot) (keeps the recorded height, pitch and roll), and its camera T_world_agent @ T_vehicle_camera;
2. eq. 2: `warp.forward_warp` of the recorded RGB-D frame straight into the region of interest at the policy's
   resolution (the world's intrinsics scaled by out / roi); what it leaves empty (side wedges off the recorded path,
   disocclusions) is filled from the neighbouring recorded frames warped into the holes' box and merged by depth, and
   what no frame saw is inpainted (`fill.py`): the policy never sees black;
3. every other car, placed on the ground of the viewer's recorded frame the same way, rasterized (`raster.py`, back
   faces culled, full or light level of detail by projected size) in the same region and composited with a per-pixel
   depth test against the warped depth, so occlusion works both ways; lit by an ambient light equal to the scene's
   mean colour and a directional light from the viewpoint at infinity (`shading.Lighting`), over a soft contact
   shadow darkening the ground under each car (`shading.contact_shadow_`); on a monochrome camera (detected from the
   frames) the cars are drawn in luma;
4. harmonization of the inserted cars under their mask (`harmonize.py`);
5. the camera's look on the cars (`camera_look.py`): their edges blended with the background, the recorded frames'
   blur and noise (estimated once from a few of the world's frames).

Speed: recorded frames are turned into torch tensors once and kept in a small cache (so the warp's per-source cache
hits while an agent stays near a frame), vehicles are packed once per model and level of detail, a view with one car
renders it from the car's own frame (several cars are moved into the camera's with `PackedScene.transformed` and
merged), cars outside the region's frustum are skipped before rasterization, and all views with cars are rasterized
in one call. On CPU the raster is compiled end to end (`raster_kernel.py`), and compositing and the statistical
harmonization run view by view in place on the uint8 views (a compiled loop and OpenCV); on a GPU both stay batched
torch operations.

The batched path (the default on a GPU, `batched=True` anywhere): every recorded frame is put on the device once, all
B views are warped in one `forward_warp` call (its torch path), their holes filled together (`fill.pull_push_fill`
instead of OpenCV's inpainting; neighbouring frames are not used), the cars placed for all views at once and drawn in
one call (`Rasterizer.render_instances`: every model's geometry packed once, unpainted, each car with its own paint,
so an episode's repainted car is not packed again), and the contact shadows of all cars drawn in one call
(`shading.contact_shadows_batched`): no per-view work on the device.
"""

from __future__ import annotations

import hashlib
import inspect
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np
import pydantic
import torch

from drivesim.sim import raster_kernel
from drivesim.sim.camera_look import CameraLook, apply_camera_look_, look_of_frames
from drivesim.sim.cpu_threads import governed_threads
from drivesim.sim.fill import FillStats, fill_wedges_from_neighbours, inpaint_holes, pull_push_fill, widen_frame
from drivesim.sim.frame_cache import FrameLayout, PreparedFrames, open_prepared_frames
from drivesim.sim.geometry import invert, scale_intrinsics
from drivesim.sim.harmonize import Harmonizer, StatisticalHarmonizer, make_harmonizer
from drivesim.sim.raster import PackedScene, Rasterizer, RenderResult, composite, material_row, merge_scenes
from drivesim.sim.shading import contact_shadow_, contact_shadows_batched
from drivesim.sim.warp import KernelWarp, WarpResult, forward_warp, rendered_region
from drivesim.sim.world import World, relative_pose

__all__ = [
    "CarPlacement", "ViewBatch", "ViewConfig", "ViewSynthesizer", "fit_roi", "frames_are_monochrome",
    "planar_transforms",
]  # fmt: skip

TIMING_KEYS = ("warp", "raster", "composite", "lighting", "harmonize")
_FRAME_CACHE_SIZE = 2048  # recorded frames kept as tensors (about 0.17 MB each at the default view)
# Of a world read from its prepared frames on disk (a frame read there costs tens of microseconds), fewer are kept: the
# depth of each is the process's own memory.
_BACKED_FRAME_CACHE_SIZE = 512
_NARROW_CACHE_SIZE = 8  # frames kept before widening (a frame's widening reads the few around it)
_MODEL_CACHE_SIZE = 256  # packed vehicle models kept (about 0.5 MB each; every episode's car is a new repaint)
_PAINT_CACHE_SIZE = 65536  # the batched path's (geometry slot, paint) of models seen lately (a few hundred bytes each)
_WARP_MARGIN_PX = 3
_LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601 luma weights, as cv2.COLOR_RGB2GRAY
_MONOCHROME_SAMPLES = 8  # frames looked at to tell a gray camera
_MONOCHROME_TOLERANCE = 2  # grey levels of channel difference a gray camera's frames may show (compression)


class ViewConfig(pydantic.BaseModel):
    """What each agent sees and how it is rendered."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)

    roi_px: tuple[int, int, int, int] = (0, 72, 320, 128)
    """(x0, y0, w, h) region of the world's image the policy sees (px of a 320 x 200 image); shrunk about its bottom
    centre to fit a smaller world image."""
    out_width_px: int = pydantic.Field(160, gt=0)
    """Width of the policy's image (px); the region of interest is scaled to it."""
    out_height_px: int = pydantic.Field(64, gt=0)
    """Height of the policy's image (px)."""
    lighting: bool = True
    """Light inserted cars with the scene's mean colour and a directional light; off: their unlit base colour."""
    harmonization: bool = True
    """Harmonize inserted cars toward their surroundings (with `harmonizer`)."""
    harmonizer: Literal["statistical", "learned"] = "statistical"
    """statistical: the car's colour statistics moved toward its surroundings'; learned: a small network trained on
    the synthetic world's true look of inserted cars (sim/models/harmonizer.onnx)."""
    directional_gain: float = pydantic.Field(0.8, ge=0.0)
    """Directional light colour as a multiple of the scene's mean colour (unitless)."""
    light_elevation_deg: float = pydantic.Field(0.0, ge=0.0, le=90.0)
    """Elevation of the directional light (deg): 0 = from the viewpoint, 90 = from overhead."""
    full_detail_min_px: float = pydantic.Field(80.0, ge=0.0)
    """Projected car size (largest dimension, px of the policy's image) from which the full mesh is drawn instead of
    the light one."""
    max_car_distance_m: float = pydantic.Field(120.0, gt=0.0)
    """Cars farther than this from the camera (m, along the optical axis) are not drawn."""
    fill_holes: bool = True
    """Fill 1-2 px cracks of the warp (never larger disocclusions)."""
    fill_frames: tuple[int, ...] = ()
    """Neighbouring recorded frames (index offsets) warped into the side wedges the view's own frame leaves empty, in
    this order, at every view; () = none."""
    source_margin: float = pydantic.Field(0.25, ge=0.0, le=1.0)
    """Margin added left and right of every recorded frame, filled once from `margin_frames` (fraction of the
    frame's width; 0: none)."""
    margin_frames: tuple[int, ...] = (-1, -2, -3, 1)
    """Neighbouring recorded frames (index offsets) that fill the margins, in this order; each fills only what the
    ones before it left."""
    inpaint: bool = True
    """Inpaint (a pull-push fill) what no frame saw, so the policy never sees black; off: such pixels stay black."""
    contact_shadow: float = pydantic.Field(0.6, ge=0.0, le=1.0)
    """Darkening of the ground under an inserted car (fraction of its colour removed, fading out 0.5 m outside the
    footprint); 0 = no shadow."""
    camera_look: bool = True
    """Give inserted cars the camera's look: edges blended with the background, the frames' blur and noise (estimated
    from the world's frames); off: hard edges, noiseless faces."""
    monochrome: bool | None = None
    """Whether the camera is monochrome (inserted cars drawn in gray); None: detected from the world's frames (equal
    R, G and B)."""
    render_threads: int = pydantic.Field(1, ge=1, le=16)
    """Most CPU threads one view's warp, inpainting and car shading are split over (1: one thread); fewer when other
    processes keep the cores busy."""
    source_downsample: bool = True
    """Warp from recorded frames reduced by the integer factor nearest (not above) roi / out size (colour averaged,
    nearest depth kept); off: at the world's resolution."""

    @pydantic.field_validator("roi_px")
    @classmethod
    def _positive_roi(cls, roi: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        x0, y0, w, h = roi
        if x0 < 0 or y0 < 0 or w <= 0 or h <= 0:
            raise ValueError(f"roi_px {roi}: x0, y0 must be >= 0 and w, h > 0")
        return roi


@dataclass
class CarPlacement:
    """One other car seen in a view: a library model at a world pose (centre of its footprint on the ground).

    :param model: a `vehicle_library.VehicleModel` (anything with `full`, `light` mesh lists and `length_m`,
        `width_m`, `height_m`). :param x_m, y_m: world position. :param yaw_rad: world heading.
    Views report one mask of all inserted cars, so a placement carries no id.
    """

    model: Any
    x_m: float
    y_m: float
    yaw_rad: float


@dataclass
class ViewBatch:
    """B rendered views.

    :param rgb: (B, out_h, out_w, 3) uint8. :param car_mask: (B, out_h, out_w) bool, where an inserted car is visible.
    :param timings_ms: time spent in this call per part: "warp", "raster", "composite", "lighting", "harmonize".
    """

    rgb: np.ndarray
    car_mask: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)


def planar_transforms(q_long_m: np.ndarray, q_lat_m: np.ndarray, q_rot_rad: np.ndarray) -> np.ndarray:
    """(B, 4, 4) transforms of a planar offset (forward, left, heading) in a vehicle frame."""
    q_long, q_lat, q_rot = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (q_long_m, q_lat_m, q_rot_rad))
    T = np.zeros((len(q_long), 4, 4))
    c, s = np.cos(q_rot), np.sin(q_rot)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3] = q_long, q_lat
    return T


def fit_roi(roi_px: tuple[int, int, int, int], width_px: int, height_px: int) -> tuple[float, float, float, float]:
    """The region `roi_px` (x0, y0, w, h) inside a width x height image: as is when it fits, else shrunk about its
    bottom centre with its aspect ratio kept, then moved inside the image (fractional pixels allowed)."""
    x0, y0, w, h = (float(v) for v in roi_px)
    scale = min(1.0, width_px / w, height_px / h)
    if scale == 1.0 and x0 + w <= width_px and y0 + h <= height_px:
        return x0, y0, w, h
    centre_x, bottom = x0 + 0.5 * w, min(y0 + h, float(height_px))
    w, h = w * scale, h * scale
    x0 = min(max(centre_x - 0.5 * w, 0.0), width_px - w)
    y0 = min(max(bottom - h, 0.0), height_px - h)
    return x0, y0, w, h


class ViewSynthesizer:
    """Renders agents' camera views in a world (module docstring).

    :param world: the loaded world. :param config: the view settings.
    :param device: torch device ("cpu", "cuda"). :param harmonizer: default the one `config.harmonizer` names.
    :param batched: render all views in one batch of torch operations (module docstring); None: on any device but
        the CPU, and only without `fill_frames` (neighbouring frames are filled view by view).
    """

    def __init__(
        self,
        world: World,
        config: ViewConfig | None = None,
        device: str = "cpu",
        harmonizer: Harmonizer | None = None,
        batched: bool | None = None,
    ):
        self.world = world
        self.config = config = config or ViewConfig()
        self.device = torch.device(device)
        if batched and config.fill_frames:
            raise ValueError("the batched views fill no holes from neighbouring frames: set fill_frames to ()")
        self.batched = batched if batched is not None else self.device.type != "cpu" and not config.fill_frames
        self._stack: tuple[torch.Tensor, torch.Tensor, np.ndarray] | None = None
        self._geometries: list[tuple[PackedScene, np.ndarray]] = []
        self._geometry_slot: dict[tuple, int] = {}
        self._geometry_meshes: list[list[Any]] = []
        self._geometry_of: OrderedDict[tuple[int, bool], tuple[Any, int, np.ndarray]] = OrderedDict()
        self.harmonizer = harmonizer if harmonizer is not None else make_harmonizer(config.harmonizer)
        self.roi_px = x0, y0, w, h = fit_roi(config.roi_px, world.width_px, world.height_px)
        sx, sy = config.out_width_px / w, config.out_height_px / h
        # The region of interest is rendered as an image of its own: intrinsics scaled to the policy's resolution,
        # principal point shifted by the region's (scaled) corner. Fractional corners are fine.
        K_scaled = scale_intrinsics(world.K, sx, sy)
        self.K_view = K_scaled.copy()
        self.K_view[0, 2] -= x0 * sx
        self.K_view[1, 2] -= y0 * sy
        factor = max(1, int(np.floor(min(w / config.out_width_px, h / config.out_height_px) + 1e-9)))
        self.source_factor = factor if config.source_downsample else 1
        self._K_frame = scale_intrinsics(
            np.asarray(world.K, dtype=np.float64), 1 / self.source_factor, 1 / self.source_factor
        )
        self.margin_px = round(config.source_margin * (world.width_px // self.source_factor))
        self.K_src = self._K_frame.copy()  # the widened frames' intrinsics (`_frame_arrays`)
        self.K_src[0, 2] += self.margin_px
        self.T_vehicle_camera = np.asarray(world.T_vehicle_camera, dtype=np.float64)
        self.T_camera_vehicle = invert(self.T_vehicle_camera)
        self._T_world_vehicle = np.asarray(world.path["T_world_vehicle"], dtype=np.float64)
        self._T_world_camera = np.asarray(world.path["T_world_camera"], dtype=np.float64)
        self._path_x = np.asarray(world.path["x_m"], dtype=np.float64)
        self._path_y = np.asarray(world.path["y_m"], dtype=np.float64)
        self._path_yaw = np.asarray(world.path["yaw_rad"], dtype=np.float64)
        self.rasterizer = Rasterizer(config.out_width_px, config.out_height_px, self.device, cull_back_faces=True)
        self._frames: OrderedDict[int, tuple[torch.Tensor, torch.Tensor, np.ndarray]] = OrderedDict()
        self._narrow: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
        self._packed: dict[int, tuple[Any, PackedScene, PackedScene]] = {}
        self._frustum_normals = self._frustum_planes()
        self._light_direction: tuple[float | None, np.ndarray] = (None, np.zeros(3))  # (elevation deg, unit vector)
        self.monochrome = config.monochrome if config.monochrome is not None else frames_are_monochrome(world.frames)
        self.camera_look = CameraLook()
        """The recorded frames' blur (at the view's scale) and noise, given to inserted cars (`camera_look.py`)."""
        if config.camera_look:
            self.camera_look = look_of_frames(
                world.frames, self.source_factor, float(self.K_view[0, 0] / self._K_frame[0, 0])
            )  # fmt: skip
        self.fill_stats = FillStats()
        """Where the pixels of every view rendered so far came from (own frame, neighbours, inpainting)."""
        self._min_depth: dict[int, float] = {}  # each prepared frame's smallest finite depth (the warp's window)
        self._kernel_warp: KernelWarp | None = None
        if not self.batched and self.device.type == "cpu":
            src_size = (
                world.height_px // self.source_factor,
                world.width_px // self.source_factor + 2 * self.margin_px,
            )
            self._kernel_warp = _view_kernel_warp(self.K_src, src_size, self.K_view, config)
        long_world = world.frame_count > _FRAME_CACHE_SIZE
        self._prepared: PreparedFrames | None = self._open_prepared_frames() if long_world else None
        """Every frame's prepared form stored beside the world (`frame_cache.py`): a frame the memory cache does not
        hold is read from it instead of prepared again; None for a world the memory cache holds whole (no disk
        spent), an in-memory world or a folder that cannot be written."""
        if not self.batched and world.frame_count <= _FRAME_CACHE_SIZE:
            # Every frame taken into the memory cache now, not at its first view: an episode meets a new frame at nearly
            # every step, so lazily each view paid it until all frames had been seen (10 % of a car-drawn overtake
            # step, measured); the cache would hold them all in the end anyway.
            for index in range(world.frame_count):
                self._frame(index)

    # ------------------------------------------------------------------ caches
    def _frame(self, index: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """Recorded frame `index` as (rgb (H, W, 3) uint8, depth (H, W) float32) tensors and its mean colour in [0, 1];
        the same tensor objects while cached, so the warp's per-source cache hits."""
        entry = self._frames.get(index)
        if entry is not None:
            self._frames.move_to_end(index)
            return entry
        rgb_np, depth_np, mean_rgb, self._min_depth[index] = self._prepared_arrays(index)
        # float16 depth from the prepared frames widened here: torch's conversion is ten times numpy's
        depth = torch.from_numpy(depth_np).to(self.device, torch.float32)
        entry = (torch.from_numpy(rgb_np).to(self.device), depth, mean_rgb)
        self._frames[index] = entry
        limit = _FRAME_CACHE_SIZE if self._prepared is None else min(_FRAME_CACHE_SIZE, _BACKED_FRAME_CACHE_SIZE)
        if len(self._frames) > limit:
            self._frames.popitem(last=False)
        return entry

    def _frame_stack(self) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """Every recorded frame as `_frame` prepares it, stacked on the device (N, H, W, 3) uint8 and (N, H, W)
        float32, and their mean colours (N, 3): made once, for the batched path."""
        if self._stack is None:
            arrays = [self._prepared_arrays(i) for i in range(self.world.frame_count)]
            rgb = torch.from_numpy(np.stack([a[0] for a in arrays])).to(self.device)
            depth = torch.from_numpy(np.stack([a[1] for a in arrays]).astype(np.float32)).to(self.device)
            self._stack = (rgb, depth, np.stack([a[2] for a in arrays]))
        return self._stack

    def _prepared_arrays(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Recorded frame `index` as `_frame_arrays` prepares it (rgb uint8, depth float32 or its float16 record,
        mean colour) with its smallest finite depth (m): views of the prepared frames beside the world when there
        are, else new arrays prepared now."""
        if self._prepared is not None:
            return self._prepared.read(index)
        rgb_np, depth_np, mean_rgb = self._frame_arrays(index)
        depth_np = np.array(depth_np, dtype=np.float32, copy=True)
        finite = depth_np[(depth_np > 0) & np.isfinite(depth_np)]
        return np.array(rgb_np, copy=True), depth_np, mean_rgb, float(finite.min()) if finite.size else float("inf")

    def _open_prepared_frames(self) -> PreparedFrames | None:
        """The prepared frames of this view's settings beside the world, built now if no process has built them
        (`frame_cache.open_prepared_frames`: keyed by what shapes a prepared frame, so a stale one is never read)."""
        world, f = self.world, self.source_factor
        code = "".join(inspect.getsource(fn) for fn in (widen_frame, *_PREPARING_METHODS))
        recipe = {
            "source_factor": f, "margin_px": self.margin_px, "margin_frames": list(self.config.margin_frames),
            "K_frame": self._K_frame.tolist(), "code_sha256": hashlib.sha256(code.encode()).hexdigest(),
        }  # fmt: skip
        digest = hashlib.sha256()
        for array in (world.frames[0], world.frames[-1], world.depth_m[0], world.depth_m[-1], self._T_world_camera):
            digest.update(np.ascontiguousarray(array).tobytes())
        sample = {"frame_count": world.frame_count, "size_px": [world.width_px, world.height_px]}
        sample["arrays_sha256"] = digest.hexdigest()
        layout = FrameLayout(world.height_px // f, world.width_px // f, self.margin_px)

        def prepare(index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            rgb, depth, mean_rgb = self._frame_arrays(index)
            return rgb, np.asarray(depth, dtype=np.float32), mean_rgb

        return open_prepared_frames(world.root, world.frame_count, recipe, sample, layout, prepare)

    def _frame_arrays(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Recorded frame `index` as the warp reads it: at the source resolution, widened by `margin_px` on each side
        from the frames `ViewConfig.margin_frames` (intrinsics `K_src`); (rgb (H, W, 3) uint8, depth (H, W) float32)
        arrays and the frame's own mean colour in [0, 1]."""
        rgb, depth, mean_rgb = self._narrow_arrays(index)
        if self.margin_px == 0:
            return rgb, _float16_precision(depth), mean_rgb
        T_camera_world = invert(self._T_world_camera[index])
        neighbours = [
            (*self._narrow_arrays(index + offset)[:2], T_camera_world @ self._T_world_camera[index + offset])
            for offset in self.config.margin_frames
            if 0 <= index + offset < self.world.frame_count
        ]
        wide = widen_frame(rgb, depth, self._K_frame, self.margin_px, neighbours)
        return wide.rgb, _float16_precision(wide.depth_m), mean_rgb

    def _narrow_arrays(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Recorded frame `index` at the warp's source resolution, not widened: (rgb (H, W, 3) uint8, depth (H, W)
        float32) arrays and its mean colour in [0, 1]. The last few are kept: widening a frame reads its neighbours."""
        entry = self._narrow.get(index)
        if entry is not None:
            self._narrow.move_to_end(index)
        else:
            entry = self._narrow[index] = self._source_arrays(index)
            if len(self._narrow) > _NARROW_CACHE_SIZE:
                self._narrow.popitem(last=False)
        return entry

    def _source_arrays(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Recorded frame `index` reduced to the warp's source resolution (`ViewConfig.source_downsample`)."""
        rgb_np = np.ascontiguousarray(self.world.frames[index])
        mean_rgb = np.asarray(cv2.mean(rgb_np)[:3]) / 255.0
        depth_np = np.asarray(self.world.depth_m[index], dtype=np.float32)
        f = self.source_factor
        if f > 1:
            H, W = depth_np.shape
            H, W = H - H % f, W - W % f
            # For an integer factor INTER_AREA is the block mean (rounded), on the CPU's vector units.
            rgb_np = cv2.resize(rgb_np[:H, :W], (W // f, H // f), interpolation=cv2.INTER_AREA)
            # Nearest surface per block (no-data pixels, <= 0 or NaN, must not win: they become +inf first); a block
            # of no data only stays no data (0), a block of sky only stays sky (+inf).
            d = depth_np[:H, :W].copy()
            sky_px = np.isposinf(d)
            d[~(d > 0)] = np.inf
            # f^2 strided views combined element-wise: much faster than a reduction over reshaped block axes.
            pooled, sky = d[0::f, 0::f].copy(), sky_px[0::f, 0::f].copy()
            for dy in range(f):
                for dx in range(f):
                    np.minimum(pooled, d[dy::f, dx::f], out=pooled)
                    np.logical_or(sky, sky_px[dy::f, dx::f], out=sky)
            pooled[np.isposinf(pooled) & ~sky] = 0.0
            depth_np = pooled
        return rgb_np, depth_np, mean_rgb

    def _model_scenes(self, model: Any) -> tuple[PackedScene, PackedScene]:
        """(full, light) packed meshes of a vehicle model in its own frame, packed once per model object."""
        entry = self._packed.get(id(model))
        if entry is None or entry[0] is not model:
            full = self.rasterizer.pack(list(model.full)) if not isinstance(model.full, PackedScene) else model.full
            light_meshes = getattr(model, "light", None)
            light = full if not light_meshes else self.rasterizer.pack(list(light_meshes))
            entry = (model, full, light)
            self._packed[id(model)] = entry  # holds the model, so its id stays unique
            if len(self._packed) > _MODEL_CACHE_SIZE:  # every episode's car is a new (repainted) model
                self._packed.pop(next(iter(self._packed)))
        else:
            self._packed[id(model)] = self._packed.pop(id(model))  # most recently used last
        return entry[1], entry[2]

    def _frustum_planes(self) -> np.ndarray:
        """(4, 3) inward normals of the side planes of the view's frustum (through the optical centre)."""
        w, h = self.config.out_width_px, self.config.out_height_px
        corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]])
        rays = corners @ np.linalg.inv(self.K_view).T
        normals = np.cross(rays, np.roll(rays, -1, axis=0))  # clockwise on screen = inward with y down
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)

    # ------------------------------------------------------------------ poses
    def camera_poses(
        self, frame_index: np.ndarray, x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(T_world_vehicle, T_world_camera) of B agents, each on the ground of its associated recorded frame."""
        f = np.asarray(frame_index, dtype=np.int64)
        q_lat, q_long, q_rot = relative_pose(
            np.asarray(x_m, float), np.asarray(y_m, float), np.asarray(yaw_rad, float),
            self._path_x[f], self._path_y[f], self._path_yaw[f],
        )  # fmt: skip
        T_world_vehicle = self._T_world_vehicle[f] @ planar_transforms(q_long, q_lat, q_rot)
        return T_world_vehicle, T_world_vehicle @ self.T_vehicle_camera

    def _visible(self, T_camera_car: np.ndarray, model: Any) -> bool:
        """Whether a car's bounding sphere reaches into the view's frustum (and is not too far)."""
        half_height = 0.5 * float(model.height_m)
        centre = T_camera_car[:3, :3] @ np.array([0.0, 0.0, half_height]) + T_camera_car[:3, 3]
        radius = 0.5 * float(np.sqrt(model.length_m**2 + model.width_m**2 + model.height_m**2))
        if centre[2] + radius < self.rasterizer.near_m or centre[2] - radius > self.config.max_car_distance_m:
            return False
        return bool((self._frustum_normals @ centre > -radius).all())

    # ------------------------------------------------------------------ render
    def render(
        self,
        frame_index: np.ndarray,
        x_m: np.ndarray,
        y_m: np.ndarray,
        yaw_rad: np.ndarray,
        cars: list[list[CarPlacement]],
    ) -> ViewBatch:
        """B views: agent b at world pose (x_m[b], y_m[b], yaw_rad[b]) associated with recorded frame frame_index[b],
        seeing the cars `cars[b]`."""
        cfg = self.config
        timings = dict.fromkeys(TIMING_KEYS, 0.0)
        frame_index = np.atleast_1d(np.asarray(frame_index, dtype=np.int64))
        B = len(frame_index)
        if len(cars) != B:
            raise ValueError(f"got {len(cars)} car lists for {B} views")
        if (frame_index < 0).any() or (frame_index >= self.world.frame_count).any():
            raise ValueError(f"frame_index must be in [0, {self.world.frame_count}), got {frame_index.tolist()}")
        _, T_world_camera = self.camera_poses(frame_index, x_m, y_m, yaw_rad)
        T_camera_world = invert(T_world_camera)

        start = time.perf_counter()
        if self.batched:
            rgb_out, depth_out = self._warp_batched(frame_index, T_camera_world)
        else:
            rgb_views, depth_views = [], []
            for b in range(B):
                rgb, depth = self._view_warp(int(frame_index[b]), T_camera_world[b])
                rgb_views.append(rgb)
                depth_views.append(depth)
            if B == 1:  # one view (an env's step): a leading axis on the warp's own arrays, no copy
                rgb_out, depth_out = rgb_views[0].unsqueeze(0), depth_views[0].unsqueeze(0)
            else:
                rgb_out, depth_out = torch.stack(rgb_views), torch.stack(depth_views)
        timings["warp"] = 1e3 * (time.perf_counter() - start)

        start = time.perf_counter()
        if self.batched:
            placed_per_view = self._placed_cars_batched(frame_index, T_camera_world, cars)
        else:
            placed_per_view = [self._placed_cars(b, int(frame_index[b]), T_camera_world[b], cars[b]) for b in range(B)]
        viewers = [b for b, placed in enumerate(placed_per_view) if placed]
        shadows = [(b, T, model) for b in viewers for model, T, _ in placed_per_view[b]]
        lights = self._lighting_table(frame_index[viewers])
        timings["lighting"] = 1e3 * (time.perf_counter() - start)
        if shadows and cfg.contact_shadow > 0:
            start = time.perf_counter()
            rgb_out = self._contact_shadows(rgb_out, depth_out, shadows)
            timings["composite"] += 1e3 * (time.perf_counter() - start)
        if not viewers:
            car_mask = np.zeros((B, cfg.out_height_px, cfg.out_width_px), dtype=bool)
            return ViewBatch(rgb=rgb_out.cpu().numpy(), car_mask=car_mask, timings_ms=timings)
        start = time.perf_counter()
        placed_viewers = [placed_per_view[b] for b in viewers]
        if self.batched and not self.rasterizer.use_kernel:
            drawn = self._raster_instances(placed_viewers, lights)
        else:
            scenes, poses = self._scenes_and_poses(placed_viewers)
            if not self.batched and self.rasterizer.use_kernel and not any(scene.textured for scene in scenes):
                rgb, car_mask = self._draw_cpu(rgb_out, depth_out, scenes, poses, lights, viewers)
                timings["raster"] = 1e3 * (time.perf_counter() - start)  # the composite included
                self._harmonize_cpu(rgb, car_mask, viewers, timings)
                self._apply_camera_look(rgb, car_mask, viewers, timings)
                return ViewBatch(rgb=rgb, car_mask=car_mask, timings_ms=timings)
            drawn = self.rasterizer.render(scenes, poses, self.K_view, lighting=lights)
        timings["raster"] = 1e3 * (time.perf_counter() - start)
        insert = self._insert_torch if self.batched or self.device.type != "cpu" else self._insert_cpu
        rgb, car_mask = insert(rgb_out, depth_out, drawn, viewers, timings)
        self._apply_camera_look(rgb, car_mask, viewers, timings)
        return ViewBatch(rgb=rgb, car_mask=car_mask, timings_ms=timings)

    def _apply_camera_look(self, rgb: np.ndarray, car_mask: np.ndarray, viewers: list[int], timings: dict) -> None:
        """The camera's look (`ViewConfig.camera_look`) on the composited cars of the uint8 views, in place; its time
        counts as compositing."""
        if not self.config.camera_look:
            return
        start = time.perf_counter()
        for b in viewers:
            apply_camera_look_(rgb[b], car_mask[b], self.camera_look)
        timings["composite"] += 1e3 * (time.perf_counter() - start)

    def _draw_cpu(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        scenes: list[PackedScene],
        poses: np.ndarray,
        lights: np.ndarray,
        viewers: list[int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """The views' cars rasterized and composited straight into the warped views in one compiled call
        (`Rasterizer.draw_into`: the pixels of `_raster_scenes` then `_insert_cpu`'s composite, without the full-size
        float images between them): the views (B, h, w, 3) uint8 and where a car is in front (B, h, w) bool."""
        rgb_np, depth_np = rgb.numpy(), depth.numpy()
        car_mask = np.zeros(depth_np.shape, dtype=bool)
        gray = bool(self.monochrome)  # a gray camera's world: the car in gray too, in the same pass
        with governed_threads(self.config.render_threads, "car") as threads:  # 1 while no core is free
            self.rasterizer.draw_into(
                scenes, poses, self.K_view, lights, rgb_np, depth_np, car_mask, viewers, gray, threads
            )
        return rgb_np, car_mask

    def _insert_cpu(
        self, rgb: torch.Tensor, depth: torch.Tensor, drawn: RenderResult, viewers: list[int], timings: dict
    ) -> tuple[np.ndarray, np.ndarray]:
        """Composite (per-pixel depth test, compiled) and harmonize the drawn cars into the views, view by view: at
        the policy's few thousand pixels, per-call costs are what matters, and a compiled loop's and OpenCV's are the
        lowest."""
        start = time.perf_counter()
        rgb_np, depth_np = rgb.numpy(), depth.numpy()
        car_mask = np.zeros(depth_np.shape, dtype=bool)
        car_rgb, car_depth = drawn.rgb.numpy(), drawn.depth_m.numpy()
        gray = bool(self.monochrome)  # a gray camera's world: the car in gray too, in the same pass
        for i, b in enumerate(viewers):
            raster_kernel.composite_uint8(rgb_np[b], depth_np[b], car_rgb[i], car_depth[i], car_mask[b], gray)
        timings["composite"] += 1e3 * (time.perf_counter() - start)
        self._harmonize_cpu(rgb_np, car_mask, viewers, timings)
        return rgb_np, car_mask

    def _harmonize_cpu(self, rgb: np.ndarray, car_mask: np.ndarray, viewers: list[int], timings: dict) -> None:
        """Harmonize the cars composited into the uint8 views rgb (B, h, w, 3) (where car_mask), in place."""
        if not self.config.harmonization:
            return
        start = time.perf_counter()
        in_place = getattr(self.harmonizer, "harmonize_view_uint8_", None)
        if in_place is not None:
            for b in viewers:
                in_place(rgb[b], car_mask[b])
        else:
            index = torch.as_tensor(viewers)
            mask = torch.from_numpy(car_mask).index_select(0, index)
            views = torch.from_numpy(rgb).index_select(0, index)
            harmonized = self.harmonizer(views.to(torch.float32) / 255.0, mask)
            rgb[viewers] = _harmonized_uint8(views, harmonized, mask).numpy()
        if self.monochrome and not isinstance(self.harmonizer, StatisticalHarmonizer):
            # a gray car stays gray under the statistical transfer (equal channels, equal gains); other harmonizers
            # may tint it, which a gray camera cannot show
            for b in viewers:
                _gray_car_(rgb[b], car_mask[b])
        timings["harmonize"] = 1e3 * (time.perf_counter() - start)

    def _insert_torch(
        self, rgb: torch.Tensor, depth: torch.Tensor, drawn: RenderResult, viewers: list[int], timings: dict
    ) -> tuple[np.ndarray, np.ndarray]:
        """Composite and harmonize the drawn cars into the views as batched torch operations (the GPU path)."""
        B, h, w = depth.shape
        start = time.perf_counter()
        index = torch.as_tensor(viewers, device=self.device)
        rgb_c, _, front = composite(rgb.index_select(0, index), depth.index_select(0, index), drawn)
        if self.monochrome:
            luma = torch.tensor(_LUMA, device=rgb_c.device)
            gray = (rgb_c.to(torch.float32) @ luma + 0.5).clamp_(0, 255).to(torch.uint8)
            rgb_c = torch.where(front[..., None], gray[..., None].expand_as(rgb_c), rgb_c)
        timings["composite"] += 1e3 * (time.perf_counter() - start)
        if self.config.harmonization and bool(front.any()):
            start = time.perf_counter()
            harmonized = self.harmonizer(rgb_c.to(torch.float32) / 255.0, front)
            rgb_c = _harmonized_uint8(rgb_c, harmonized, front)
            if self.monochrome and not isinstance(self.harmonizer, StatisticalHarmonizer):  # as `_harmonize_cpu`
                gray = (rgb_c.to(torch.float32) @ luma + 0.5).clamp_(0, 255).to(torch.uint8)
                rgb_c = torch.where(front[..., None], gray[..., None].expand_as(rgb_c), rgb_c)
            timings["harmonize"] = 1e3 * (time.perf_counter() - start)
        car_mask = torch.zeros((B, h, w), dtype=torch.bool, device=self.device).index_copy(0, index, front)
        return rgb.index_copy(0, index, rgb_c).cpu().numpy(), car_mask.cpu().numpy()

    def _placed_cars_batched(
        self, frame_index: np.ndarray, T_camera_world: np.ndarray, cars: list[list[CarPlacement]]
    ) -> list[list[tuple[Any, np.ndarray, bool]]]:
        """`_placed_cars` of every view, its poses, visibility and level of detail computed for all cars at once."""
        placed: list[list[tuple[Any, np.ndarray, bool]]] = [[] for _ in cars]
        view = np.array([b for b, view_cars in enumerate(cars) for _ in view_cars], dtype=np.int64)
        if view.size == 0:
            return placed
        flat = [car for view_cars in cars for car in view_cars]
        x, y, yaw = (np.array([getattr(c, k) for c in flat], dtype=np.float64) for k in ("x_m", "y_m", "yaw_rad"))
        size = np.array([[c.model.length_m, c.model.width_m, c.model.height_m] for c in flat], dtype=np.float64)
        f = frame_index[view]
        q_lat, q_long, q_rot = relative_pose(x, y, yaw, self._path_x[f], self._path_y[f], self._path_yaw[f])
        T = T_camera_world[view] @ self._T_world_vehicle[f] @ planar_transforms(q_long, q_lat, q_rot)
        # As `_visible`: the bounding sphere against the near plane, the distance limit and the frustum's sides.
        centre = T[:, :3, 2] * (0.5 * size[:, 2:3]) + T[:, :3, 3]
        radius = 0.5 * np.linalg.norm(size, axis=1)
        visible = (centre[:, 2] + radius >= self.rasterizer.near_m) & (
            centre[:, 2] - radius <= self.config.max_car_distance_m
        )
        visible &= (centre @ self._frustum_normals.T > -radius[:, None]).all(axis=1)
        size_px = float(self.K_view[0, 0]) * np.maximum(size[:, 0], size[:, 2]) / np.maximum(T[:, 2, 3], 0.1)
        full_detail = size_px >= self.config.full_detail_min_px
        for i in np.flatnonzero(visible):
            placed[view[i]].append((flat[i].model, T[i], bool(full_detail[i])))
        return placed

    def _raster_scenes(self, placed_per_view: list[list[tuple]], lights: np.ndarray) -> RenderResult:
        """The cars of views that show any, each view's (model, T_camera_car, full detail) list, in one raster call
        (`_scenes_and_poses`)."""
        scenes, poses = self._scenes_and_poses(placed_per_view)
        return self.rasterizer.render(scenes, poses, self.K_view, lighting=lights)

    def _scenes_and_poses(self, placed_per_view: list[list[tuple]]) -> tuple[list[PackedScene], np.ndarray]:
        """Each view's cars (its (model, T_camera_car, full detail) list) as one packed scene and its pose in the
        camera: a view of one car renders its packed model from the car's own frame, several cars are moved into the
        camera's frame and merged."""
        scenes, poses = [], []
        for placed in placed_per_view:
            packed = [self._model_scenes(model)[0 if full else 1] for model, _, full in placed]
            if len(placed) == 1:  # one car: rendered from its own frame, no copy of its mesh moved into the camera's
                scenes.append(packed[0])
                poses.append(placed[0][1])
            else:
                moved = [scene.transformed(T) for scene, (_, T, _) in zip(packed, placed, strict=True)]
                scenes.append(merge_scenes(moved))
                poses.append(np.eye(4))
        return scenes, np.stack(poses)

    def _raster_instances(self, placed_per_view: list[list[tuple]], lights: np.ndarray) -> RenderResult:
        """`_raster_scenes` for the batched torch path: views of one car in one `render_instances` call over the
        library of the models' unpainted geometry, each with its own paint (a repainted car is not packed again);
        views of several cars through `_raster_scenes`."""
        one = [i for i, placed in enumerate(placed_per_view) if len(placed) == 1]
        several = [i for i, placed in enumerate(placed_per_view) if len(placed) > 1]
        parts = []
        if one:
            slots, paints = zip(*(self._geometry(*placed_per_view[i][0][::2]) for i in one), strict=True)
            poses = np.stack([placed_per_view[i][0][1] for i in one])
            masks = [mask for _, mask in self._geometries]
            drawn = self.rasterizer.render_instances(
                [scene for scene, _ in self._geometries], np.array(slots), poses, self.K_view, lights[one],
                paint=(masks, np.stack(paints)),
            )  # fmt: skip
            parts.append((one, drawn))
        if several:
            parts.append((several, self._raster_scenes([placed_per_view[i] for i in several], lights[several])))
        if len(parts) == 1:
            return parts[0][1]
        out = {}
        for name in ("rgb", "depth_m", "object_id", "normal_cam"):
            first = getattr(parts[0][1], name)
            out[name] = torch.empty((len(placed_per_view), *first.shape[1:]), dtype=first.dtype, device=first.device)
            for members, result in parts:
                out[name].index_copy_(0, torch.as_tensor(members, device=first.device), getattr(result, name))
        return RenderResult(**out)

    def _geometry(self, model: Any, full: bool) -> tuple[int, np.ndarray]:
        """The slot of a model's geometry at a level of detail in the batched path's library (packed once per shape,
        its paint group white), and the model's paint: (10,) diffuse rgb and material row (`raster._material_row`);
        repainted copies of a model share its meshes' vertex arrays, hence its slot."""
        known = self._geometry_of.get((id(model), full))
        if known is not None and known[0] is model:
            self._geometry_of.move_to_end((id(model), full))
            return known[1], known[2]
        meshes = list(model.full if full or not getattr(model, "light", None) else model.light)
        key = tuple((id(m.vertices_m), id(m.faces)) for m in meshes)
        group = getattr(model, "paint_group", None)
        slot = self._geometry_slot.get(key)
        if slot is None:
            white = [
                replace(m, material=replace(m.material, diffuse_rgb=(1.0, 1.0, 1.0))) if k == group else m
                for k, m in enumerate(meshes)
            ]
            mask = np.concatenate([np.full(len(m.faces), k == group) for k, m in enumerate(meshes) if len(m.faces)])
            slot = self._geometry_slot[key] = len(self._geometries)
            self._geometries.append((self.rasterizer.pack(white), mask))
            self._geometry_meshes.append(meshes)  # held, so that the ids of the key stay unique
        paint = np.zeros(10, dtype=np.float32)
        if group is not None:
            material = meshes[group].material
            paint = np.concatenate([np.asarray(material.diffuse_rgb, np.float32), material_row(material)])
        self._geometry_of[(id(model), full)] = (model, slot, paint)  # held, so that its id stays unique
        if len(self._geometry_of) > _PAINT_CACHE_SIZE:
            self._geometry_of.popitem(last=False)
        return slot, paint

    def _lighting_table(self, frame_index: np.ndarray) -> np.ndarray:
        """(n, 9) lighting of views from recorded frames `frame_index` (`_lighting`, for all at once)."""
        n = len(frame_index)
        if not self.config.lighting:
            return np.tile(np.array([1, 1, 1, 0, 0, 1, 0, 0, 0], dtype=np.float32), (n, 1))
        if self.batched:
            mean_rgb = self._frame_stack()[2][frame_index]
        else:
            mean_rgb = np.array([self._frame(int(f))[2] for f in frame_index], dtype=np.float64).reshape(-1, 3)
        elevation_deg = self.config.light_elevation_deg
        if self._light_direction[0] != elevation_deg:  # made once per elevation: a few microseconds a step
            elevation_rad = np.deg2rad(elevation_deg)
            self._light_direction = (elevation_deg, np.array([0.0, np.sin(elevation_rad), np.cos(elevation_rad)]))
        table = np.empty((n, 9), dtype=np.float32)
        table[:, :3] = mean_rgb
        table[:, 3:6] = self._light_direction[1]
        table[:, 6:] = self.config.directional_gain * mean_rgb
        return table

    def _warp_batched(self, frame_index: np.ndarray, T_camera_world: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """All B views' warps (B, h, w, 3) uint8 and depths (B, h, w) in one call from the device's frame stack, holes
        filled by `pull_push_fill` (counted in `fill_stats` as inpainted)."""
        rgb_all, depth_all, _ = self._frame_stack()
        T_dst_src = T_camera_world @ self._T_world_camera[frame_index]
        warped = _warp(rgb_all, depth_all, self.K_src, T_dst_src, self.K_view, self.config, source_index=frame_index)
        total, seen = warped.valid.numel(), int(warped.valid.sum())
        if not self.config.inpaint:
            self.fill_stats.add(FillStats(total_px=total, frame_px=seen))
            return warped.rgb, warped.depth_m
        self.fill_stats.add(FillStats(total_px=total, frame_px=seen, inpainted_px=total - seen))
        return pull_push_fill(warped.rgb, warped.valid), warped.depth_m

    def _view_warp(self, frame: int, T_camera_world: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """One view of recorded frame `frame` from camera pose T_camera_world: the frame warped, its holes filled
        (`_fill`), as (h, w, 3) uint8 and (h, w) float32 depth tensors on the device. On the CPU through the view's
        `KernelWarp` (its constants made once), elsewhere through `forward_warp`'s torch path."""
        rgb, depth, _ = self._frame(frame)
        T_dst_src = T_camera_world @ self._T_world_camera[frame]
        if self._kernel_warp is not None:
            with governed_threads(self.config.render_threads, "warp") as threads:
                rgb_np, depth_np, valid = self._kernel_warp(
                    rgb.numpy(), depth.numpy(), self._min_depth[frame], T_dst_src, threads
                )  # fmt: skip
        else:
            warped = _warp(rgb, depth, self.K_src, T_dst_src, self.K_view, self.config)
            rgb_np, depth_np = warped.rgb.cpu().numpy().copy(), warped.depth_m.cpu().numpy().copy()
            valid = warped.valid.cpu().numpy()
        self._fill(frame, T_camera_world, rgb_np, depth_np, valid)
        return torch.from_numpy(rgb_np).to(self.device), torch.from_numpy(depth_np).to(self.device)

    def _fill(
        self, frame: int, T_camera_world: np.ndarray, rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray
    ) -> None:
        """Fill a view's holes (`valid` False) in its warp `rgb`, `depth` in place: from the neighbouring frames
        (`ViewConfig.fill_frames`), then by inpainting (`ViewConfig.inpaint`); the pixel counts go to `fill_stats`
        (module `sim/fill.py`)."""
        if valid.all():
            self.fill_stats.add(FillStats(total_px=valid.size, frame_px=valid.size))
            return
        stats = FillStats(total_px=valid.size, frame_px=int(np.count_nonzero(valid)))
        if not (self.config.fill_frames or self.config.inpaint):
            self.fill_stats.add(stats)
            return

        def neighbour_warp(offset: int, box: tuple[int, int, int, int]) -> tuple[np.ndarray, ...] | None:
            neighbour = frame + offset
            if not 0 <= neighbour < self.world.frame_count:
                return None
            n_rgb, n_depth, _ = self._frame(neighbour)
            other = _warp(
                n_rgb, n_depth, self.K_src, T_camera_world @ self._T_world_camera[neighbour], self.K_view,
                self.config, box,
            )  # fmt: skip
            return other.rgb.numpy(), other.depth_m.numpy(), other.valid.numpy()

        filled, stats.neighbour_px = fill_wedges_from_neighbours(
            rgb, depth, valid, self.config.fill_frames, neighbour_warp
        )
        if self.config.inpaint:
            with governed_threads(self.config.render_threads, "inpaint") as threads:
                stats.inpainted_px = inpaint_holes(rgb, ~valid & ~filled, threads)
        self.fill_stats.add(stats)

    def _contact_shadows(self, rgb: torch.Tensor, depth: torch.Tensor, shadows: list[tuple]) -> torch.Tensor:
        """The warped views with a soft shadow on the ground under each inserted car, `shadows` holding (view,
        T_camera_car, model) per car (before the cars are composited, so a car covers its own shadow's middle)."""
        if self.batched:
            return contact_shadows_batched(
                rgb, depth, self.K_view, torch.as_tensor([b for b, _, _ in shadows], device=self.device),
                torch.as_tensor(np.stack([T for _, T, _ in shadows]), device=self.device),
                torch.as_tensor([[float(m.length_m), float(m.width_m)] for _, _, m in shadows], device=self.device),
                self.config.contact_shadow,
            )  # fmt: skip
        rgb_np = rgb.cpu().numpy()
        depth_np = depth.cpu().numpy()
        for b, T_camera_car, model in shadows:
            contact_shadow_(
                rgb_np[b], depth_np[b], self.K_view, T_camera_car, float(model.length_m), float(model.width_m),
                self.config.contact_shadow,
            )  # fmt: skip
        return rgb if rgb.device.type == "cpu" else torch.from_numpy(rgb_np).to(rgb.device)

    def _placed_cars(
        self, b: int, frame: int, T_camera_world: np.ndarray, cars: list[CarPlacement]
    ) -> list[tuple[Any, np.ndarray, bool]]:
        """The visible cars of view b: each car's model, its pose in the camera frame, T_camera_car, and whether its
        projected size asks for the full level of detail (else the light one)."""
        if not cars:
            return []
        x = np.array([c.x_m for c in cars], dtype=np.float64)
        y = np.array([c.y_m for c in cars], dtype=np.float64)
        yaw = np.array([c.yaw_rad for c in cars], dtype=np.float64)
        q_lat, q_long, q_rot = relative_pose(x, y, yaw, self._path_x[frame], self._path_y[frame], self._path_yaw[frame])
        T_camera_car = T_camera_world @ self._T_world_vehicle[frame] @ planar_transforms(q_long, q_lat, q_rot)
        placed = []
        fx = float(self.K_view[0, 0])
        for car, T in zip(cars, T_camera_car, strict=True):
            if not self._visible(T, car.model):
                continue
            size_px = fx * max(float(car.model.length_m), float(car.model.height_m)) / max(float(T[2, 3]), 0.1)
            placed.append((car.model, T, size_px >= self.config.full_detail_min_px))
        return placed


def _float16_precision(depth_m: np.ndarray) -> np.ndarray:
    """`depth_m` rounded to float16 and back (float32): a prepared frame's depth is what the frame cache stores at half
    the bytes, whether it is read from there or prepared in memory (at most 1/2048 relative: under 2.5 cm at 50 m)."""
    return np.asarray(depth_m, dtype=np.float16).astype(np.float32)


# The code that shapes a prepared frame: its source text is part of the prepared frames' key (`frame_cache.py`).
_PREPARING_METHODS = (
    ViewSynthesizer._frame_arrays, ViewSynthesizer._narrow_arrays, ViewSynthesizer._source_arrays, _float16_precision
)  # fmt: skip


def frames_are_monochrome(frames: np.ndarray) -> bool:
    """Whether recorded frames (N, h, w, 3) uint8 come from a gray camera: R, G and B equal (within a couple of grey
    levels) in every one of a few frames sampled across the drive."""
    n = len(frames)
    if n == 0:
        return False
    for i in np.unique(np.linspace(0, n - 1, _MONOCHROME_SAMPLES).round().astype(int)):
        frame = np.asarray(frames[i], dtype=np.int16)
        if np.abs(frame[..., 0] - frame[..., 1]).max() > _MONOCHROME_TOLERANCE:
            return False
        if np.abs(frame[..., 2] - frame[..., 1]).max() > _MONOCHROME_TOLERANCE:
            return False
    return True


def _harmonized_uint8(rgb: torch.Tensor, harmonized: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """uint8 views taking a harmonizer's float output [0, 1] under `mask`."""
    return torch.where(mask[..., None], (harmonized * 255.0 + 0.5).clamp_(0, 255).to(torch.uint8), rgb)


def _view_destination(K_view: np.ndarray, cfg: ViewConfig) -> tuple[np.ndarray, int, int, tuple[int, int, int, int]]:
    """The destination `_warp` warps a view into: the view as the region of a slightly larger image (a margin of
    _WARP_MARGIN_PX on every side), as (K_dst, width, height, roi (x0, y0, w, h))."""
    m = _WARP_MARGIN_PX
    K_dst = K_view.copy()
    K_dst[0, 2] += m
    K_dst[1, 2] += m
    w, h = cfg.out_width_px, cfg.out_height_px
    return K_dst, w + 2 * m + 1, h + 2 * m + 1, (m, m, w, h)


def _view_kernel_warp(K_src: np.ndarray, src_size: tuple[int, int], K_view: np.ndarray, cfg: ViewConfig) -> KernelWarp:
    """`_warp` of a whole view on the CPU as a `KernelWarp` (the same destination, its constants made once)."""
    K_dst, width, height, roi = _view_destination(K_view, cfg)
    rendered = rendered_region(width, height, roi, cfg.fill_holes)
    partial = rendered[2:] != (width, height)
    return KernelWarp(K_src, src_size, K_dst, rendered, roi, cfg.fill_holes, partial, bands=cfg.render_threads)


def _warp(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    K_src: np.ndarray,
    T_dst_src: np.ndarray,
    K_view: np.ndarray,
    cfg: ViewConfig,
    box: tuple[int, int, int, int] | None = None,
    source_index: np.ndarray | None = None,
) -> WarpResult:
    """One recorded frame warped into one view (the frame's tensors are cached, so its source constants are too), or
    into the box (x0, y0, w, h) of the view only.

    The view is passed as the region of a slightly larger destination image (a margin of _WARP_MARGIN_PX on every
    side): hole filling then sees the pixels just outside the view, and the warp only transforms the source pixels
    that can land in it. With `source_index` (the batched path) rgb / depth hold N frames and T_dst_src (B, 4, 4) one
    pose per view, warped by the torch path."""
    K_dst, width, height, (m, _, w, h) = _view_destination(K_view, cfg)
    x0, y0, bw, bh = box if box is not None else (0, 0, w, h)
    return forward_warp(
        rgb, depth, K_src, T_dst_src, K_dst, width, height, roi=(m + x0, m + y0, bw, bh),
        fill_holes=cfg.fill_holes, source_index=source_index, use_kernel=source_index is None,
    )  # fmt: skip


def _gray_car_(rgb: np.ndarray, mask: np.ndarray) -> None:
    """Redraw the car under `mask` (h, w) bool in its luma (`_LUMA`, OpenCV's rounding), in place in the uint8 view
    `rgb` (h, w, 3): OpenCV on the car's box, a few microseconds."""
    left, top, width, height = cv2.boundingRect(mask.view(np.uint8))
    if width == 0:
        return
    box = rgb[top : top + height, left : left + width]
    gray = cv2.cvtColor(cv2.cvtColor(box, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
    cv2.copyTo(gray, mask[top : top + height, left : left + width].view(np.uint8), box)
