"""A lit contact sheet of a vehicle library: each model from a front three-quarter view, rendered with the
simulator's own rasterizer and shading (so what you see is what the policy's view gets)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivesim.sim.vehicle_library import VehicleLibrary, VehicleModel

_BACKGROUND_RGB = (0.62, 0.66, 0.70)
_GROUND_RGB = (0.32, 0.32, 0.33)


def _look_at(eye_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """T_camera_world of a camera at `eye_m` looking at `target_m` with z up (optical x right, y down, z forward)."""
    forward = target_m - eye_m
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera axes in the world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye_m
    return T


def _ground(size_m: float):
    from drivesim.sim.mesh import Material, Mesh

    h = size_m / 2
    vertices = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return Mesh(vertices, faces, material=Material(diffuse_rgb=_GROUND_RGB, roughness=0.9), object_id=-1)


def render_model(model: VehicleModel, detail: str, width_px: int, height_px: int) -> np.ndarray:
    """One model on a grey ground, seen from the front-left three-quarter view: (H, W, 3) uint8."""
    from drivesim.sim.geometry import intrinsics_from_hfov
    from drivesim.sim.raster import Rasterizer
    from drivesim.sim.shading import Lighting

    meshes = model.full if detail == "full" else model.light
    distance = 1.25 * max(model.length_m, 2.0)
    eye = np.array([0.75 * distance, 0.95 * distance, 0.55 * distance + 0.6])
    T = _look_at(eye, np.array([0.0, 0.0, 0.45 * model.height_m]))
    K = intrinsics_from_hfov(width_px, height_px, np.radians(50.0))
    # the sun from above-left-front, expressed in the camera frame (the light travels along light_dir)
    sun_world = np.array([-0.4, -0.5, -1.0])
    light_dir = T[:3, :3] @ (sun_world / np.linalg.norm(sun_world))
    lighting = Lighting(
        ambient_rgb=np.array([0.38, 0.40, 0.43]), light_dir_cam=light_dir, light_rgb=np.array([0.85, 0.83, 0.78])
    )
    raster = Rasterizer(width_px, height_px)
    result = raster.render([_ground(4 * distance), *meshes], T, K, lighting, background_rgb=_BACKGROUND_RGB)
    rgb = result.rgb[0].numpy()
    return (np.clip(rgb, 0.0, 1.0) ** (1 / 2.2) * 255.0 + 0.5).astype(np.uint8)  # linear -> display gamma


def contact_sheet(
    library: VehicleLibrary,
    out_path: Path,
    detail: str = "full",
    tile_px: tuple[int, int] = (320, 220),
    columns: int = 4,
) -> Path:
    """Write a PNG grid of every model of `library` (named under each tile); returns its path."""
    from PIL import Image, ImageDraw

    w, h = tile_px
    n = len(library.models)
    cols = min(columns, n)
    rows = (n + cols - 1) // cols
    sheet = Image.new("RGB", (cols * w, rows * (h + 16)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, model in enumerate(library.models):
        tile = render_model(model, detail, w, h)
        x, y = (i % cols) * w, (i // cols) * (h + 16)
        sheet.paste(Image.fromarray(tile), (x, y))
        label = f"{model.name}  {model.length_m:.2f} x {model.width_m:.2f} x {model.height_m:.2f} m"
        draw.text((x + 4, y + h + 2), label, fill=(0, 0, 0))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_path)
    return out_path
