"""Fidelity of the simulator's views with an inserted car, against ground truth (which neither the paper nor VISTA
measures), and of view synthesis on real frames.

(a) Synthetic: a drive through `SynthWorld` gives frames with true depth and poses; a library car is placed 10 m ahead
in the procedural scene and the true image (scene + car, rendered by the synthetic world's own renderer with its sun,
sky and haze) is rendered from the agent's pose at lateral offsets 0, 0.5 and 1.0 m, straight at the policy's region
of interest and resolution. The simulator's view (warp of the recorded frame + insertion + lighting + harmonization)
is compared with it: PSNR and SSIM over the region of interest and over the true car mask, with lighting and
harmonization each off and on.
(b) Real: a recorded frame of a KITTI world is warped to the pose of a later recorded frame and compared with that
frame over the pixels the warp fills, for each world given (one per depth method).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from drivesim.bench.fidelity import image_metrics, render_drive
from drivesim.bench.machine import report_header
from drivesim.sim.geometry import invert, pose_2d, yaw_of
from drivesim.sim.vehicle_library import VehicleLibrary
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from drivesim.sim.warp import forward_warp
from drivesim.sim.world import World

OFFSETS_M = (0.0, 0.5, 1.0)
CAR_AHEAD_M = 10.0
_CAR_ID = 1000
VARIANTS = {
    "none": {"lighting": False, "harmonization": False},
    "lighting": {"lighting": True, "harmonization": False},
    "harmonization": {"lighting": False, "harmonization": True},
    "both": {"lighting": True, "harmonization": True},
    # Not the paper's model: the directional light raised 45 degrees, about where the synthetic world's sun is; it
    # tells whether what lighting loses in SSIM comes from the light's direction or from the shading itself.
    "lighting 45 deg up": {"lighting": True, "harmonization": False, "light_elevation_deg": 45.0},
}


@dataclass
class CarFidelityResult:
    """Rows of (a) and (b) as dicts; `figure` the side-by-side PNG."""

    synthetic: list[dict] = field(default_factory=list)
    real: list[dict] = field(default_factory=list)
    figure: str = ""


def world_from_drive(drive, root: Path) -> World:  # noqa: ANN001 (bench.fidelity.SyntheticDrive)
    """An in-memory World over a synthetic drive's frames, true depth and true poses."""
    n = len(drive.rgb)
    T_wv = drive.T_world_vehicle
    x, y = T_wv[:, 0, 3], T_wv[:, 1, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    path = {
        "x_m": x, "y_m": y, "z_m": T_wv[:, 2, 3], "yaw_rad": yaw_of(T_wv), "speed_mps": np.zeros(n),
        "curvature_1pm": np.zeros(n), "arc_length_m": arc, "t_ns": np.arange(n, dtype=np.int64),
        "frame_index": np.arange(n), "T_world_vehicle": T_wv, "T_world_camera": drive.T_world_camera,
    }  # fmt: skip
    width, height = drive.size
    return World(
        root=root, frames=drive.rgb, depth_m=drive.depth_m, K=drive.K, T_vehicle_camera=drive.T_vehicle_camera,
        width_px=width, height_px=height, camera_height_m=None, path=path, road_width_m=7.0, lane_width_m=3.5,
        info={"format": 1},
    )  # fmt: skip


def true_view(drive, car_meshes_world: list, T_world_camera: np.ndarray, K: np.ndarray, size: tuple[int, int]):  # noqa: ANN001
    """The synthetic world's own render with the car added: colour (h, w, 3) uint8 and the car's true mask."""
    from drivesim.stages.synth.render import CellCulling

    synth = drive.world
    culling = synth._culling  # the car joins the scene's meshes for this render only
    synth._culling = CellCulling(synth.meshes + list(car_meshes_world))
    try:
        rgb, _, ids = synth.render_full(T_world_camera, K, *size)
    finally:
        synth._culling = culling
    return rgb, ids == _CAR_ID


def synthetic_rows(frames: int = 3, seed: int = 0) -> tuple[list[dict], dict[str, np.ndarray]]:
    """(a): metric rows per offset and variant (means over `frames` frames) and images for the figure."""
    drive = render_drive(seed, 4 * frames + 4, 320, 200)
    world = world_from_drive(drive, Path("."))
    model = VehicleLibrary.procedural(count=4, seed=seed).models[0]
    views = {name: ViewSynthesizer(world, ViewConfig(**flags)) for name, flags in VARIANTS.items()}
    any_view = views["none"]
    size = (any_view.config.out_width_px, any_view.config.out_height_px)
    sums: dict[tuple, list[dict]] = {}
    images: dict[str, np.ndarray] = {}
    for k in range(frames):
        i = 4 * k + 1
        T_world_car = drive.T_world_vehicle[i] @ pose_2d(CAR_AHEAD_M, 0.0, 0.0)
        car_meshes = [dataclasses.replace(m.transformed(T_world_car), object_id=_CAR_ID) for m in model.full]
        car_yaw = float(yaw_of(T_world_car))
        placement = CarPlacement(model, float(T_world_car[0, 3]), float(T_world_car[1, 3]), car_yaw)
        for offset in OFFSETS_M:
            T_world_agent = drive.T_world_vehicle[i] @ pose_2d(0.0, offset, 0.0)
            truth, car_mask = true_view(
                drive, car_meshes, T_world_agent @ drive.T_vehicle_camera, any_view.K_view, size
            )
            agent = (np.array([i]), T_world_agent[0, 3:4], T_world_agent[1, 3:4], np.atleast_1d(yaw_of(T_world_agent)))
            for name, vs in views.items():
                out = vs.render(*agent, [[placement]])
                view = out.rgb[0]
                roi = image_metrics(view, truth, np.ones(car_mask.shape, bool))
                car = image_metrics(view, truth, car_mask)
                sums.setdefault((offset, name), []).append(
                    {"psnr_roi_db": roi["psnr_db"], "ssim_roi": roi["ssim"], "psnr_car_db": car["psnr_db"],
                     "ssim_car": car["ssim"], "car_iou": float((out.car_mask[0] & car_mask).sum()
                                                                / max((out.car_mask[0] | car_mask).sum(), 1))}
                )  # fmt: skip
                if k == 0 and offset == 0.5:
                    images[name] = view
            if k == 0 and offset == 0.5:
                images["truth"] = truth
    rows = []
    for (offset, name), values in sums.items():
        row = {"offset_m": offset, "variant": name}
        row.update({key: float(np.mean([v[key] for v in values])) for key in values[0]})
        rows.append(row)
    return rows, images


def real_rows(worlds: dict[str, Path], gaps: tuple[int, ...] = (2, 5), step: int = 4) -> list[dict]:
    """(b): each world's frame i warped to the pose of frame i + gap, compared with that frame (filled pixels)."""
    rows = []
    for method, path in worlds.items():
        world = World.load(path)
        for gap in gaps:
            metrics = []
            for i in range(0, world.frame_count - gap, step):
                src_rgb = torch.from_numpy(np.array(world.frames[i]))
                src_depth = torch.from_numpy(np.array(world.depth_m[i], dtype=np.float32))
                T_dst_src = invert(world.path["T_world_camera"][i + gap]) @ world.path["T_world_camera"][i]
                out = forward_warp(src_rgb, src_depth, world.K, T_dst_src, world.K, world.width_px, world.height_px)
                valid = out.valid.numpy()
                metrics.append(image_metrics(out.rgb.numpy(), np.asarray(world.frames[i + gap]), valid))
            rows.append(
                {"depth": method, "gap_frames": gap, "pairs": len(metrics),
                 "psnr_db": float(np.mean([m["psnr_db"] for m in metrics])),
                 "ssim": float(np.mean([m["ssim"] for m in metrics])),
                 "filled_fraction": float(np.mean([m["filled_fraction"] for m in metrics]))}
            )  # fmt: skip
    return rows


def save_side_by_side(path: Path, images: dict[str, np.ndarray], scale: int = 3) -> None:
    """Truth and the simulator's variants side by side, with labels."""
    import cv2

    tiles = []
    for name in ("truth", *VARIANTS):
        tile = cv2.resize(images[name], None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        tile = np.ascontiguousarray(tile)
        cv2.putText(tile, name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.vstack(tiles), cv2.COLOR_RGB2BGR))


def run_car_fidelity(real_worlds: dict[str, Path], figure: Path, frames: int = 3, seed: int = 0) -> CarFidelityResult:
    """Both parts; the figure of (a) at offset 0.5 m goes to `figure`."""
    torch.set_num_threads(1)
    rows, images = synthetic_rows(frames, seed)
    save_side_by_side(figure, images)
    return CarFidelityResult(synthetic=rows, real=real_rows(real_worlds), figure=str(figure))


def car_fidelity_markdown(result: CarFidelityResult, machine: str, command: str) -> str:
    """The results as markdown."""
    lines = [
        *report_header("Inserted-car fidelity and real-frame view synthesis", machine, command),
        "",
        f"## (a) Synthetic world: simulator view vs true render with the car {CAR_AHEAD_M:.0f} m ahead",
        "",
        "ROI = the policy's whole view; car = the true car mask. Means over the evaluated frames.",
        "",
        "| offset m | variant | PSNR ROI dB | SSIM ROI | PSNR car dB | SSIM car | car mask IoU |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in sorted(result.synthetic, key=lambda r: (r["offset_m"], list(VARIANTS).index(r["variant"]))):
        lines.append(
            f"| {r['offset_m']:.1f} | {r['variant']} | {r['psnr_roi_db']:.2f} | {r['ssim_roi']:.3f} | "
            f"{r['psnr_car_db']:.2f} | {r['ssim_car']:.3f} | {r['car_iou']:.3f} |"
        )
    lines += ["", f"Figure (offset 0.5 m; truth, {', '.join(VARIANTS)}): `{result.figure}`", ""]
    lines += ["## (b) KITTI: recorded frame warped to a later frame's pose, vs that frame", ""]
    lines += ["| depth | gap (frames) | pairs | PSNR dB | SSIM | filled |", "|---|---:|---:|---:|---:|---:|"]
    for r in result.real:
        lines.append(
            f"| {r['depth']} | {r['gap_frames']} | {r['pairs']} | {r['psnr_db']:.2f} | {r['ssim']:.3f} | "
            f"{r['filled_fraction']:.3f} |"
        )
    return "\n".join(lines) + "\n"
