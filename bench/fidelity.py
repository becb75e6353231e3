"""Depth and view-synthesis fidelity against ground truth, on a drive through the synthetic world.

The bench renders a drive (frames, ground-truth depth, poses) with `SynthWorld`, estimates depth with the `plane`
and `mvs` methods, and measures:
- depth: AbsRel = mean |d - d*| / d* and delta1 = share of pixels with max(d/d*, d*/d) < 1.25, over pixels whose
  ground-truth depth is finite and below max_depth_m, on the frames that have every matching neighbour;
- view synthesis (paper eq. 2): each evaluated frame is forward-warped with its depth into a camera moved sideways
  (lateral offsets) or turned (yaw offsets) from where it was recorded, and compared with the ground-truth render
  from that pose: PSNR and SSIM over the pixels the warp fills, and the filled fraction. Warping with the
  ground-truth depth gives the upper bound (what remains is disocclusion and resampling, not depth error).
Positive lateral offsets move the camera to the left (vehicle +y), positive yaw turns it left.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from skimage.metrics import structural_similarity

from drivesim.pipeline.errors import ConfigError
from drivesim.sim.geometry import invert, pose_2d, scale_intrinsics
from drivesim.sim.warp import forward_warp
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth
from drivesim.stages.synth.config import DriveConfig, SynthConfig
from drivesim.stages.synth.drive import Trajectory, arc_length_at
from drivesim.stages.synth.world import SynthWorld

DEPTH_SOURCES = ("plane", "mvs", "ground_truth")


@dataclass
class SyntheticDrive:
    """Frames rendered along the lane with their ground truth: rgb (N, H, W, 3) uint8, depth_m (N, H, W) float32
    (inf = sky), T_world_camera (N, 4, 4), T_world_vehicle (N, 4, 4), K (3, 3), T_vehicle_camera (4, 4)."""

    world: SynthWorld
    rgb: np.ndarray
    depth_m: np.ndarray
    T_world_camera: np.ndarray
    T_world_vehicle: np.ndarray
    K: np.ndarray
    T_vehicle_camera: np.ndarray

    @property
    def size(self) -> tuple[int, int]:
        """(width_px, height_px) of the frames."""
        return self.rgb.shape[2], self.rgb.shape[1]


def render_drive(
    seed: int, n_frames: int, width_px: int, height_px: int, progress: Callable[[int], None] | None = None
) -> SyntheticDrive:
    """A drive of `n_frames` at the synthetic camera's frame rate through the world of `seed`, at the given size."""
    world = SynthWorld.from_seed(seed)
    camera = world.camera
    K = scale_intrinsics(camera.K, width_px / camera.width_px, height_px / camera.height_px)
    rate_hz = SynthConfig().camera.rate_hz
    drive_cfg = DriveConfig(duration_s=max(1.0, n_frames / rate_hz))
    needed_m = float(arc_length_at(drive_cfg, drive_cfg.duration_s))
    if needed_m > world.path.length_m:
        raise ConfigError(
            f"{n_frames} frames need {needed_m:.0f} m of road but the synthetic lane is"
            f" {world.path.length_m:.0f} m long;"
            " ask for fewer frames"
        )
    trajectory = Trajectory(world.path, drive_cfg)
    rgb = np.empty((n_frames, height_px, width_px, 3), np.uint8)
    depth = np.empty((n_frames, height_px, width_px), np.float32)
    T_wv = np.stack([trajectory.vehicle_pose(i / rate_hz) for i in range(n_frames)])
    T_wc = T_wv @ camera.T_vehicle_camera
    for i in range(n_frames):
        rgb[i], depth[i] = world.render(T_wc[i], K, width_px, height_px)
        if progress is not None:
            progress(1)
    return SyntheticDrive(world, rgb, depth, T_wc, T_wv, K, camera.T_vehicle_camera)


def depth_metrics(depth_m: np.ndarray, gt_depth_m: np.ndarray, max_depth_m: float) -> dict[str, float]:
    """AbsRel and delta<1.25 of `depth_m` against `gt_depth_m` over pixels with finite ground truth < max_depth_m."""
    valid = np.isfinite(gt_depth_m) & (gt_depth_m < max_depth_m) & (gt_depth_m > 0)
    d = np.maximum(depth_m[valid].astype(np.float64), 1e-6)
    g = gt_depth_m[valid].astype(np.float64)
    ratio = np.maximum(d / g, g / d)
    return {
        "abs_rel": float(np.mean(np.abs(d - g) / g)),
        "delta1": float(np.mean(ratio < 1.25)),
        "pixels": int(valid.sum()),
    }


def image_metrics(synth: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """PSNR (dB) and SSIM of a synthesized uint8 image against the truth over `valid` pixels, and the filled share."""
    a = synth.astype(np.float64)
    b = truth.astype(np.float64)
    mse = float(np.mean((a[valid] - b[valid]) ** 2)) if valid.any() else float("nan")
    psnr = 10.0 * np.log10(255.0**2 / max(mse, 1e-10))
    _, ssim_map = structural_similarity(truth, synth, channel_axis=2, data_range=255, full=True)
    ssim = float(ssim_map.mean(axis=-1)[valid].mean()) if valid.any() else float("nan")
    return {"psnr_db": float(psnr), "ssim": ssim, "filled_fraction": float(valid.mean())}


@dataclass
class ViewOffset:
    """A novel camera pose relative to a recorded one: lateral (m, + left) and yaw (deg, + left)."""

    lateral_m: float = 0.0
    yaw_deg: float = 0.0

    @property
    def name(self) -> str:
        """Short label, e.g. 'lat +1.0 m' or 'yaw -5 deg'."""
        if self.yaw_deg == 0.0:
            return f"lat {self.lateral_m:+.1f} m"
        return (
            f"yaw {self.yaw_deg:+.0f} deg"
            if self.lateral_m == 0.0
            else f"lat {self.lateral_m:+.1f} m yaw {self.yaw_deg:+.0f}"
        )


DEFAULT_OFFSETS = (
    ViewOffset(lateral_m=0.5),
    ViewOffset(lateral_m=1.0),
    ViewOffset(lateral_m=1.5),
    ViewOffset(yaw_deg=-5.0),
    ViewOffset(yaw_deg=5.0),
)


@dataclass
class FidelityResult:
    """What the fidelity bench measured (all JSON-friendly)."""

    seed: int
    frames: int
    width_px: int
    height_px: int
    evaluated_frames: list[int]
    depth: dict[str, dict[str, float]]
    """method -> depth metrics (plane, mvs)."""
    views: list[dict[str, Any]]
    """one row per (offset, depth source): offset, source, psnr_db, ssim, filled_fraction (means over frames)."""
    depth_seconds: dict[str, float]
    mvs_summary: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The result as plain JSON data."""
        return asdict(self)

    def view(self, offset_name: str, source: str) -> dict[str, Any]:
        """The row of one offset and depth source."""
        for row in self.views:
            if row["offset"] == offset_name and row["source"] == source:
                return row
        raise KeyError((offset_name, source))


def _warp(drive: SyntheticDrive, i: int, depth_m: np.ndarray, T_world_target: np.ndarray):
    w, h = drive.size
    T_dst_src = invert(T_world_target) @ drive.T_world_camera[i]
    result = forward_warp(torch.from_numpy(drive.rgb[i]), torch.from_numpy(depth_m), drive.K, T_dst_src, drive.K, w, h)
    return result.rgb.numpy(), result.valid.numpy()


def run_fidelity(
    seed: int = 0,
    n_frames: int = 24,
    width_px: int = 320,
    height_px: int = 200,
    mvs_config: DepthConfig | None = None,
    offsets: tuple[ViewOffset, ...] = DEFAULT_OFFSETS,
    n_view_frames: int = 4,
    figure_path: Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> FidelityResult:
    """Render a synthetic drive, estimate its depth with `plane` and `mvs`, and measure depth and novel-view fidelity.

    :param mvs_config: the depth config for `mvs` (its method is forced to mvs); `plane` uses the same max_depth_m.
    :param n_view_frames: frames (evenly spread over the evaluated ones) whose views are synthesized and rendered.
    :param figure_path: where to save the side-by-side PNG (ground truth, plane, mvs, GT-depth warp at 1.0 m).
    :param progress: called with (phase, done, total).
    """
    mvs_cfg = (mvs_config or DepthConfig()).model_copy(update={"method": "mvs"})
    plane_cfg = DepthConfig(method="plane", max_depth_m=mvs_cfg.max_depth_m)

    def report(phase: str, total: int) -> Callable[[int], None]:
        done = [0]

        def step(k: int) -> None:
            done[0] += k
            if progress is not None:
                progress(phase, done[0], total)

        return step

    drive = render_drive(seed, n_frames, width_px, height_px, report("render drive", n_frames))
    estimates: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}
    summaries: dict[str, dict[str, Any]] = {}
    for name, cfg in (("plane", plane_cfg), ("mvs", mvs_cfg)):
        out = np.empty(drive.depth_m.shape, np.float32)
        args = (drive.rgb, drive.K, drive.T_world_camera, drive.T_vehicle_camera, None, cfg, out)
        summaries[name] = estimate_depth(*args, report(f"depth {name}", n_frames))
        estimates[name] = out
        seconds[name] = summaries[name]["seconds"]
    estimates["ground_truth"] = drive.depth_m

    # Frames with every matching neighbour (the ends of a short drive lack some).
    lo = max(0, -min(mvs_cfg.mvs.neighbour_offsets))
    hi = n_frames - max(0, max(mvs_cfg.mvs.neighbour_offsets))
    evaluated = list(range(lo, hi)) if hi > lo else list(range(n_frames))
    depth = {
        name: depth_metrics(estimates[name][evaluated], drive.depth_m[evaluated], mvs_cfg.max_depth_m)
        for name in ("plane", "mvs")
    }
    view_frames = sorted(
        {evaluated[int(k)] for k in np.linspace(0, len(evaluated) - 1, min(n_view_frames, len(evaluated)))}
    )
    figure_frame = view_frames[len(view_frames) // 2]
    step = report("novel views", len(view_frames) * len(offsets))
    views, figure_row = _view_metrics(drive, estimates, view_frames, offsets, figure_frame, step)
    if figure_path is not None and figure_row:
        save_figure(figure_path, figure_row, {k: v[figure_frame] for k, v in estimates.items()}, mvs_cfg.max_depth_m)
    return FidelityResult(
        seed=seed,
        frames=n_frames,
        width_px=width_px,
        height_px=height_px,
        evaluated_frames=evaluated,
        depth=depth,
        views=views,
        depth_seconds=seconds,
        mvs_summary=summaries["mvs"],
    )


def _view_metrics(
    drive: SyntheticDrive,
    estimates: dict[str, np.ndarray],
    view_frames: list[int],
    offsets: tuple[ViewOffset, ...],
    figure_frame: int,
    step: Callable[[int], None],
) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Novel views of `view_frames` at each offset, warped with each depth source and scored against the world's
    render there: (per offset and source the mean PSNR, SSIM and filled fraction, the figure's row of views)."""
    sums: dict[tuple[str, str], list[dict[str, float]]] = {}
    figure_row: dict[str, np.ndarray] = {}
    height_px, width_px = drive.depth_m.shape[1:3]
    for i in view_frames:
        for offset in offsets:
            T_target_vehicle = drive.T_world_vehicle[i] @ pose_2d(0.0, offset.lateral_m, np.deg2rad(offset.yaw_deg))
            T_world_target = T_target_vehicle @ drive.T_vehicle_camera
            truth, _ = drive.world.render(T_world_target, drive.K, width_px, height_px)
            for source in DEPTH_SOURCES:
                synth, valid = _warp(drive, i, estimates[source][i], T_world_target)
                sums.setdefault((offset.name, source), []).append(image_metrics(synth, truth, valid))
                if i == figure_frame and offset.lateral_m == 1.0 and offset.yaw_deg == 0.0:
                    figure_row[source] = synth
                    figure_row["truth"] = truth
            step(1)
    views = [
        {
            "offset": off,
            "source": source,
            **{k: float(np.mean([r[k] for r in rows])) for k in ("psnr_db", "ssim", "filled_fraction")},
        }
        for (off, source), rows in sums.items()
    ]
    return views, figure_row


def colour_depth(depth_m: np.ndarray, max_depth_m: float, near_m: float = 2.0) -> np.ndarray:
    """A depth map as an RGB image (turbo colour map on inverse depth: near warm, far and sky dark)."""
    inv = np.clip(near_m / np.clip(np.nan_to_num(depth_m, posinf=max_depth_m), near_m, max_depth_m), 0.0, 1.0)
    return cv2.applyColorMap((inv * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]


def save_figure(path: Path, views: dict[str, np.ndarray], depths: dict[str, np.ndarray], max_depth_m: float) -> None:
    """Side-by-side PNG: top the ground-truth novel view and the plane, mvs and GT-depth warps; below the depth maps
    of the source frame (ground truth, plane, mvs) in a colour map and the mvs relative error."""
    h, w = views["truth"].shape[:2]
    top = [views["truth"], views["plane"], views["mvs"], views["ground_truth"]]
    bottom = [colour_depth(depths[k], max_depth_m) for k in ("ground_truth", "plane", "mvs")]
    gt = depths["ground_truth"]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(np.isfinite(gt) & (gt < max_depth_m), np.abs(depths["mvs"] - gt) / gt, 0.0)
    bottom.append(cv2.applyColorMap((np.clip(rel / 0.5, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_JET)[..., ::-1])
    labels_top = ["ground truth (1.0 m left)", "warp: plane depth", "warp: mvs depth", "warp: GT depth"]
    labels_bottom = ["depth: ground truth", "depth: plane", "depth: mvs", "mvs AbsRel (0 blue, >=0.5 red)"]
    rows = []
    for images, labels in ((top, labels_top), (bottom, labels_bottom)):
        tiles = []
        for image, label in zip(images, labels, strict=True):
            tile = np.ascontiguousarray(image[..., ::-1])  # BGR for OpenCV
            cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
        rows.append(np.concatenate(tiles, axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))


@dataclass
class RealDrive:
    """A real drive as the depth methods see it: frames (N, H, W, 3) at the working resolution, K, per-frame
    T_world_camera, T_vehicle_camera, camera_height_m (None: from T_vehicle_camera)."""

    name: str
    frames: np.ndarray
    K: np.ndarray
    T_world_camera: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float | None


def load_real_drive(workspace_dir: Path, name: str = "") -> RealDrive:
    """The trace frames and the fused poses of a workspace that has run `drivesim ingest` and `drivesim preprocess`."""
    from drivesim.stages.ingest.trace import open_trace

    trace = open_trace(workspace_dir / "trace")
    poses = np.load(workspace_dir / "preprocessed" / "poses.npz")
    frames = np.asarray(trace.frames[poses["frame_index"]])
    return RealDrive(name or workspace_dir.name, frames, trace.K, poses["T_world_camera"], trace.T_vehicle_camera,
                     trace.calibration.get("camera_height_m"))  # fmt: skip


def forward_view_rows(
    drive: RealDrive,
    depths: dict[str, np.ndarray],
    gaps: tuple[int, ...] = (2, 5),
    eval_width_px: int = 320,
    step: int = 2,
    skip_ends: int = 3,
) -> list[dict[str, Any]]:
    """Each method's frame i warped to the pose of frame i + gap and compared with that recorded frame (the real
    forward novel view), at the world's resolution (depth shrunk by block minimum, frames by area). Frames within
    `skip_ends` of either end (missing mvs neighbours) are not sources."""
    from drivesim.stages.world.build import resize_depth, resize_frames

    n, H, W = drive.frames.shape[:3]
    ew, eh = eval_width_px, max(1, round(H * eval_width_px / W))
    K = scale_intrinsics(drive.K, ew / W, eh / H)
    small = resize_frames(drive.frames, ew, eh)
    rows = []
    for name, depth in depths.items():
        depth_small = resize_depth(depth, ew, eh, "min")
        for gap in gaps:
            metrics = []
            for i in range(skip_ends, n - gap - skip_ends, step):
                T_dst_src = invert(drive.T_world_camera[i + gap]) @ drive.T_world_camera[i]
                out = forward_warp(
                    torch.from_numpy(small[i]), torch.from_numpy(depth_small[i]), K, T_dst_src, K, ew, eh
                )
                valid = out.valid.numpy().astype(bool).reshape(eh, ew)
                metrics.append(image_metrics(out.rgb.numpy().reshape(eh, ew, 3), small[i + gap], valid))
            rows.append(
                {"drive": drive.name, "depth": name, "gap_frames": gap, "pairs": len(metrics),
                 **{k: float(np.mean([m[k] for m in metrics])) for k in ("psnr_db", "ssim", "filled_fraction")}}
            )  # fmt: skip
    return rows


def real_depths(
    drive: RealDrive, methods: tuple[str, ...], cfg: DepthConfig | None = None
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Depth of every frame of a real drive by each method at the working resolution, and seconds per frame."""
    import time

    base = cfg or DepthConfig()
    depths, seconds = {}, {}
    for method in methods:
        out = np.empty(drive.frames.shape[:3], np.float32)
        start = time.perf_counter()
        estimate_depth(drive.frames, drive.K, drive.T_world_camera, drive.T_vehicle_camera, drive.camera_height_m,
                       base.model_copy(update={"method": method}), out)  # fmt: skip
        seconds[method] = (time.perf_counter() - start) / len(out)
        depths[method] = out
    return depths, seconds
