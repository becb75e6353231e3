"""Real lateral-view benchmark on a rectified stereo pair (`drivesim bench stereo`).

A stereo rig records, with each left frame, the real image a camera 0.5 m to the side sees: ground truth for a
lateral novel view. Each left frame is forward-warped with a depth estimate into the right camera (x_right = x_left
- baseline in the left optical frame) and compared with the recorded right image:
- PSNR and SSIM over the pixels the warp fills, and the filled fraction;
- whole-image PSNR with holes counted: unfilled pixels are black, as the policy would see them.
Rows: identity (the left frame taken as the right view: no depth at all), each depth method run on the left frames
alone with the recorded poses (plane, mvs, ...), each built world given (its stored depth), and depth from the true
pair (OpenCV SGBM on left + right: the matcher sees the answer, so it is a reference, not a competitor).

Input: a KITTI odometry stereo folder (image_l/ or image_0/, image_r/ or image_1/, calib.txt with P0 and P1,
poses.txt with T_world_cam0 per frame). Depth is estimated at the working width (640 px, the trace's) and measured
at the evaluation width (320 px, the world's), the depth shrunk by block minimum and the images by area, as
`drivesim build-world` does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from drivesim.bench.fidelity import colour_depth, image_metrics
from drivesim.bench.machine import report_header
from drivesim.pipeline.errors import InputError
from drivesim.sim.fill import WideFrame, fill_wedges_from_neighbours, inpaint_holes, widen_frame
from drivesim.sim.geometry import camera_mount, invert, scale_intrinsics
from drivesim.sim.view import ViewConfig
from drivesim.sim.warp import forward_warp
from drivesim.stages.ingest.kitti import KITTI_CAMERA_HEIGHT_M, parse_calib_file
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth
from drivesim.stages.preprocess.depth_plane import plane_depth
from drivesim.stages.preprocess.depth_stereo import stereo_frame_depth
from drivesim.stages.world.build import resize_depth, resize_frames

IDENTITY = "identity (left as right)"
REFERENCE = "stereo: SGBM on the true pair (reference)"
DEFAULT_METHODS = ("plane", "mvs")
FILL_FRAMES = ViewConfig().fill_frames  # the simulator's default (neighbour frames warped per view; then inpainting)
SOURCE_MARGIN = ViewConfig().source_margin  # the simulator's default margins of each recorded frame (fraction of width)
MARGIN_FRAMES = ViewConfig().margin_frames  # ... and the frames that fill them
_IMAGE_EXT = (".png", ".jpg", ".jpeg")


@dataclass
class StereoDrive:
    """A rectified stereo drive at the working resolution: left, right (N, H, W, 3) uint8, K (3, 3) of both
    cameras, baseline_m (right camera this far to the right), T_world_camera (N, 4, 4) of the left camera,
    T_vehicle_camera (4, 4), camera_height_m, and the image index of each frame."""

    left: np.ndarray
    right: np.ndarray
    K: np.ndarray
    baseline_m: float
    T_world_camera: np.ndarray
    T_vehicle_camera: np.ndarray
    camera_height_m: float
    index: np.ndarray


def _images(folder: Path, names: tuple[str, ...], what: str) -> list[Path]:
    for name in names:
        if (folder / name).is_dir():
            files = sorted(p for p in (folder / name).iterdir() if p.suffix.lower() in _IMAGE_EXT)
            if files:
                return files
    raise InputError(
        f"no {what} images (looked for {', '.join(n + '/' for n in names)}); a stereo folder needs both", folder
    )


def _read(path: Path, size: tuple[int, int]) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError("unreadable image", path)
    return cv2.cvtColor(cv2.resize(image, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)


def read_stereo_folder(folder: Path, width_px: int = 640, max_frames: int | None = None) -> StereoDrive:
    """Read a KITTI odometry stereo folder, frames resized to `width_px` wide (aspect kept)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("not a folder; pass a KITTI odometry stereo folder (image_l/, image_r/, calib.txt)", folder)
    lefts = _images(folder, ("image_l", "image_0"), "left")
    rights = _images(folder, ("image_r", "image_1"), "right")
    if len(lefts) != len(rights):
        raise InputError(f"{len(lefts)} left but {len(rights)} right images; the pairs must be synchronized", folder)
    calib = parse_calib_file(folder / "calib.txt")
    if "P0" not in calib or "P1" not in calib or calib["P1"].size != 12:
        raise InputError("calib.txt needs P0 and P1 (3x4 projection matrices of the left and right cameras)", folder)
    P0, P1 = calib["P0"].reshape(3, 4), calib["P1"].reshape(3, 4)
    baseline_m = float(-(P1[0, 3] - P0[0, 3]) / P1[0, 0])
    if not baseline_m > 0:
        raise InputError(f"calib.txt gives a baseline of {baseline_m:.3f} m; P1 must be the right camera", folder)
    poses_path = folder / "poses.txt"
    if not poses_path.is_file():
        raise InputError("no poses.txt (the left camera's pose per frame); the depth methods need poses", folder)
    rows = np.loadtxt(poses_path, ndmin=2)
    if rows.shape != (len(lefts), 12):
        raise InputError(f"poses.txt has {rows.shape[0]} rows of {rows.shape[1]} for {len(lefts)} frames", folder)
    n = len(lefts) if max_frames is None else min(len(lefts), max_frames)
    source_h, source_w = cv2.imread(str(lefts[0]), cv2.IMREAD_GRAYSCALE).shape
    size = (width_px, max(1, round(source_h * width_px / source_w)))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :] = rows[:n].reshape(-1, 3, 4)
    return StereoDrive(
        left=np.stack([_read(p, size) for p in lefts[:n]]),
        right=np.stack([_read(p, size) for p in rights[:n]]),
        K=scale_intrinsics(P0[:, :3], size[0] / source_w, size[1] / source_h),
        baseline_m=baseline_m,
        T_world_camera=T,
        T_vehicle_camera=camera_mount(0.0, 0.0, KITTI_CAMERA_HEIGHT_M),
        camera_height_m=KITTI_CAMERA_HEIGHT_M,
        index=np.arange(n),
    )


def right_from_left(baseline_m: float) -> np.ndarray:
    """Left optical frame -> right optical frame of a rectified pair (the right camera `baseline_m` to the right)."""
    T = np.eye(4)
    T[0, 3] = -baseline_m
    return T


def warp_to_right(
    left: np.ndarray, depth_m: np.ndarray, K: np.ndarray, baseline_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The left frame (H, W, 3) forward-warped with its depth into the right camera: (image with holes black, filled
    mask)."""
    h, w = depth_m.shape
    out = forward_warp(
        torch.from_numpy(np.ascontiguousarray(left)), torch.from_numpy(np.ascontiguousarray(depth_m, np.float32)), K,
        right_from_left(baseline_m), K, w, h,
    )  # fmt: skip
    valid = out.valid.numpy().astype(bool).reshape(h, w)
    image = np.where(valid[..., None], out.rgb.numpy().reshape(h, w, 3), 0).astype(np.uint8)
    return image, valid


def filled_right_view(
    k: int,
    left: np.ndarray,
    depth_m: np.ndarray,
    T_world_camera: np.ndarray,
    K: np.ndarray,
    baseline_m: float,
    fill_frames: tuple[int, ...] = FILL_FRAMES,
    source_margin: float = SOURCE_MARGIN,
) -> np.ndarray:
    """Left frame k warped into the right camera with its holes filled as the simulator fills the policy's view
    (`sim/fill.py`): every left frame widened by margins of `source_margin` of its width filled from its neighbours
    (`MARGIN_FRAMES`), the neighbouring left frames `fill_frames` warped into the side wedges and merged by depth,
    then inpainted. `left` (N, h, w, 3), `depth_m` (N, h, w), `T_world_camera` (N, 4, 4) of consecutive frames."""
    h, w = depth_m.shape[1:]

    def widened(j: int) -> WideFrame:
        T_camera_world = invert(T_world_camera[j])
        neighbours = [
            (left[j + o], depth_m[j + o], T_camera_world @ T_world_camera[j + o])
            for o in MARGIN_FRAMES
            if 0 <= j + o < len(left)
        ]
        return widen_frame(left[j], depth_m[j], K, round(source_margin * w), neighbours)

    def warp(j: int, box: tuple[int, int, int, int] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        T = right_from_left(baseline_m) @ invert(T_world_camera[k]) @ T_world_camera[j]
        wide = widened(j)
        out = forward_warp(torch.from_numpy(wide.rgb), torch.from_numpy(wide.depth_m), wide.K, T, K, w, h, roi=box)
        return out.rgb.numpy().copy(), out.depth_m.numpy().copy(), out.valid.numpy().astype(bool)

    rgb, depth, valid = warp(k, None)

    def neighbour(offset: int, box: tuple[int, int, int, int]) -> tuple[np.ndarray, ...] | None:
        return warp(k + offset, box) if 0 <= k + offset < len(left) else None

    filled, _ = fill_wedges_from_neighbours(rgb, depth, valid, fill_frames, neighbour)
    hole = ~valid
    inpaint_holes(rgb, hole & ~filled)
    return rgb


def view_metrics(synth: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """PSNR and SSIM over filled pixels, filled fraction, and whole-image PSNR with holes (black) counted."""
    metrics = image_metrics(synth, truth, valid)
    mse_all = float(np.mean((synth.astype(np.float64) - truth.astype(np.float64)) ** 2))
    metrics["psnr_all_db"] = float(10.0 * np.log10(255.0**2 / max(mse_all, 1e-10)))
    return metrics


@dataclass
class StereoRow:
    """One row of the benchmark: means over the evaluated frames, and the per-frame filled PSNR. `psnr_all_filled_db`:
    whole-image PSNR of the view with its holes filled as the policy's view is (neighbour frames, inpainting)."""

    name: str
    psnr_db: float
    ssim: float
    filled_fraction: float
    psnr_all_db: float
    seconds_per_frame: float | None
    psnr_all_filled_db: float | None = None
    per_frame_psnr_db: list[float] = field(default_factory=list)


@dataclass
class StereoResult:
    """What `drivesim bench stereo` measured (JSON-friendly)."""

    folder: str
    frames: list[int]
    working_size_px: list[int]
    eval_size_px: list[int]
    baseline_m: float
    rows: list[StereoRow]
    figure: str = ""
    worst: dict[str, Any] = field(default_factory=dict)
    fill_frames: list[int] = field(default_factory=lambda: list(FILL_FRAMES))
    source_margin: float = SOURCE_MARGIN

    def row(self, name: str) -> StereoRow:
        """The row named `name`."""
        for r in self.rows:
            if r.name == name:
                return r
        raise KeyError(name)

    def to_json(self) -> dict[str, Any]:
        """The result as plain JSON data."""
        return asdict(self)


def _reference_depth(drive: StereoDrive, frames: list[int], max_depth_m: float) -> np.ndarray:
    """Dense SGBM depth of each evaluated left frame from the true pair (N_eval, H, W)."""
    cfg = DepthConfig()
    plane = plane_depth(drive.K, drive.left.shape[2], drive.left.shape[1], drive.T_vehicle_camera,
                        drive.camera_height_m, max_depth_m)  # fmt: skip
    return np.stack(
        [
            stereo_frame_depth(
                drive.left[i], drive.right[i], float(drive.K[0, 0]), drive.baseline_m, plane, max_depth_m, cfg.stereo
            )[0]  # fmt: skip
            for i in frames
        ]
    )


def _method_depth(
    drive: StereoDrive, cfg: DepthConfig, progress: Callable[[int], None] | None
) -> tuple[np.ndarray, float]:
    """Depth of every left frame by one method at the working resolution, and seconds per frame."""
    out = np.empty(drive.left.shape[:3], np.float32)
    start = time.perf_counter()
    estimate_depth(drive.left, drive.K, drive.T_world_camera, drive.T_vehicle_camera, drive.camera_height_m, cfg, out,
                   progress)  # fmt: skip
    return out, (time.perf_counter() - start) / len(out)


def evaluated_frames(n: int, cfg: DepthConfig) -> list[int]:
    """Frames with every mvs neighbour inside the drive (the ends of a short snippet lack some)."""
    offsets = cfg.mvs.neighbour_offsets
    lo, hi = max(0, -min(offsets)), n - max(0, max(offsets))
    return list(range(lo, hi)) if hi > lo else list(range(n))


def run_stereo_bench(
    folder: Path,
    methods: tuple[str, ...] = DEFAULT_METHODS,
    worlds: tuple[Path, ...] = (),
    width_px: int = 640,
    eval_width_px: int = 320,
    depth_config: DepthConfig | None = None,
    figure_path: Path | None = None,
    figure_row: str | None = None,
    progress: Callable[[str], None] | None = None,
    fill_frames: tuple[int, ...] = FILL_FRAMES,
    source_margin: float = SOURCE_MARGIN,
) -> StereoResult:
    """Measure each depth source's warp of the left frames into the right camera against the real right images.

    :param methods: depth methods run on the left frames alone (depth.method values other than stereo and lidar).
    :param worlds: built world folders of this drive; their stored depth is a row each.
    :param depth_config: settings of every method (its `method` is replaced per row).
    :param figure_path: where to save the worst frame of `figure_row` (default: the last method) as a PNG.
    :param fill_frames: the neighbour frames the 'holes filled' column warps per view (default: the simulator's).
    :param source_margin: the margins of each left frame the 'holes filled' column widens it by (as the simulator).
    """
    cfg = depth_config or DepthConfig()
    drive = read_stereo_folder(folder, width_px)
    n, H, W = drive.left.shape[:3]
    frames = evaluated_frames(n, cfg)
    ew, eh = eval_width_px, max(1, round(H * eval_width_px / W))
    K_eval = scale_intrinsics(drive.K, ew / W, eh / H)
    left = resize_frames(drive.left[frames], ew, eh)
    right = resize_frames(drive.right[frames], ew, eh)
    depths: dict[str, np.ndarray] = {}
    seconds: dict[str, float | None] = {}
    for method in methods:
        if progress is not None:
            progress(f"depth: {method}")
        full, seconds[method] = _method_depth(drive, cfg.model_copy(update={"method": method}), None)
        depths[method] = resize_depth(full[frames], ew, eh, "min")
    for world in worlds:
        name, depth = _world_depth(Path(world), frames, (ew, eh))
        depths[name], seconds[name] = depth, None
    if progress is not None:
        progress("depth: SGBM on the true pair")
    start = time.perf_counter()
    depths[REFERENCE] = resize_depth(_reference_depth(drive, frames, cfg.max_depth_m), ew, eh, "min")
    seconds[REFERENCE] = (time.perf_counter() - start) / len(frames)

    rows = [_identity_row(left, right)]
    warped: dict[str, list[np.ndarray]] = {}
    T_eval = drive.T_world_camera[frames]
    for name, depth in depths.items():
        per_frame = []
        for k in range(len(frames)):
            image, valid = warp_to_right(left[k], depth[k], K_eval, drive.baseline_m)
            per_frame.append(view_metrics(image, right[k], valid))
            filled = filled_right_view(k, left, depth, T_eval, K_eval, drive.baseline_m, fill_frames, source_margin)
            per_frame[-1]["psnr_all_filled_db"] = view_metrics(filled, right[k], np.ones(valid.shape, bool))["psnr_db"]
            warped.setdefault(name, []).append(image)
        rows.append(_row(name, per_frame, seconds[name]))
    result = StereoResult(
        str(folder), [int(drive.index[i]) for i in frames], [W, H], [ew, eh], drive.baseline_m, rows,
        fill_frames=list(fill_frames), source_margin=source_margin,
    )  # fmt: skip
    if figure_path is not None:
        chosen = figure_row or ("mvs" if "mvs" in methods else [*depths][0])
        worst = int(np.argmin(result.row(chosen).per_frame_psnr_db))
        save_worst_frame(figure_path, left[worst], warped[chosen][worst], right[worst], depths[chosen][worst],
                         cfg.max_depth_m, f"{chosen}, frame {result.frames[worst]}")  # fmt: skip
        result.figure = str(figure_path)
        result.worst = {
            "row": chosen,
            "frame": result.frames[worst],
            "psnr_db": result.row(chosen).per_frame_psnr_db[worst],
        }
    return result


def _identity_row(left: np.ndarray, right: np.ndarray) -> StereoRow:
    per_frame = [view_metrics(lf, rt, np.ones(lf.shape[:2], bool)) for lf, rt in zip(left, right, strict=True)]
    return _row(IDENTITY, per_frame, 0.0)


def _row(name: str, per_frame: list[dict[str, float]], seconds_per_frame: float | None) -> StereoRow:
    mean = {k: float(np.mean([m[k] for m in per_frame])) for k in per_frame[0]}
    return StereoRow(name, mean["psnr_db"], mean["ssim"], mean["filled_fraction"], mean["psnr_all_db"],
                     seconds_per_frame, mean.get("psnr_all_filled_db"),
                     [round(m["psnr_db"], 3) for m in per_frame])  # fmt: skip


def _world_depth(world: Path, frames: list[int], size: tuple[int, int]) -> tuple[str, np.ndarray]:
    """A built world's stored depth of the evaluated frames (matched by trace frame index), at `size`."""
    from drivesim.sim.world import World

    loaded = World.load(world)
    index = {int(t): k for k, t in enumerate(loaded.path["frame_index"])}
    missing = [i for i in frames if i not in index]
    if missing:
        raise InputError(
            f"the world has no frame {missing[0]} of the stereo folder; build it from the whole folder", world
        )
    depth = np.stack([np.asarray(loaded.depth_m[index[i]], np.float32) for i in frames])
    if depth.shape[1:] != (size[1], size[0]):
        depth = resize_depth(depth, size[0], size[1], "min")
    return f"built world {world.parent.name} ({loaded.info.get('depth_method', '?')})", depth


def save_worst_frame(
    path: Path,
    left: np.ndarray,
    warped: np.ndarray,
    right: np.ndarray,
    depth_m: np.ndarray,
    max_depth_m: float,
    title: str,
) -> None:
    """PNG of one frame, top to bottom: left, warped into the right camera, real right, |error| (holes magenta),
    depth."""
    error = np.abs(warped.astype(np.int16) - right.astype(np.int16)).mean(axis=-1)
    error_rgb = cv2.applyColorMap(np.clip(error * 4, 0, 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1].copy()
    error_rgb[warped.max(axis=-1) == 0] = (255, 0, 255)
    tiles = []
    panels = (
        (left, "left (recorded)"),
        (warped, f"warped: {title}"),
        (right, "right (recorded)"),
        (error_rgb, "|error| x4 (holes magenta)"),
        (colour_depth(depth_m, max_depth_m), "depth"),
    )
    for image, label in panels:
        tile = np.ascontiguousarray(image[..., ::-1])
        cv2.putText(tile, label, (3, 9), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (0, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=0))


def _fill_sentence(result: StereoResult) -> str:
    """How the 'holes filled' column filled the holes, in words."""
    steps = []
    if result.source_margin > 0:
        steps.append(
            f"every left frame widened by {result.source_margin:.0%} of its width on each side, filled from its "
            f"neighbours {', '.join(f'{o:+d}' for o in MARGIN_FRAMES)} (the nearest first)"
        )
    if result.fill_frames:
        steps.append(
            f"the neighbouring left frames {', '.join(f'{o:+d}' for o in result.fill_frames)} warped into the side "
            "wedges, merged by depth"
        )
    return "; ".join(steps + ["then inpainted"]) if steps else "inpainted only"


def stereo_markdown(result: StereoResult, machine: str, command: str, date: str) -> str:
    """The result as a markdown report."""
    lines = [
        *report_header(
            "Real lateral views: left frame warped into the right camera of a stereo pair", machine, command, date
        ),
        f"- data: `{result.folder}`, frames {result.frames[0]}-{result.frames[-1]} ({len(result.frames)}); depth at "
        f"{result.working_size_px[0]}x{result.working_size_px[1]}, measured at {result.eval_size_px[0]}x"
        f"{result.eval_size_px[1]}; baseline {result.baseline_m:.3f} m (right camera to the right)",
        "- PSNR and SSIM over the pixels the warp fills; 'PSNR all' over the whole image with holes black; 'PSNR all,"
        " holes filled' over the whole image with the holes filled as the policy's view is: " + _fill_sentence(result),
        "",
        "| depth | PSNR dB (filled) | SSIM (filled) | filled | PSNR dB (all) | PSNR dB (all, holes filled) | "
        "worst frame dB | s / frame |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result.rows:
        sec = "" if r.seconds_per_frame is None else f"{r.seconds_per_frame:.3f}"
        all_filled = "" if r.psnr_all_filled_db is None else f"{r.psnr_all_filled_db:.2f}"
        lines.append(
            f"| {r.name} | {r.psnr_db:.2f} | {r.ssim:.3f} | {r.filled_fraction:.3f} | {r.psnr_all_db:.2f} | "
            f"{all_filled} | {min(r.per_frame_psnr_db):.2f} | {sec} |"
        )
    if result.figure:
        worst = result.worst
        lines += [
            "",
            f"Worst frame of {worst['row']} (frame {worst['frame']}, {worst['psnr_db']:.2f} dB): `{result.figure}` "
            "(top to bottom: left, warped, right, error, depth).",
        ]
    return "\n".join(lines) + "\n"
