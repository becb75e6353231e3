"""How real the inserted cars look: a classifier two-sample test (C2ST) of real vs inserted car crops.

The recording's own cars are boxed by hand in frames of the real drives (`benchmarks/data/real_car_boxes.json`). For
each box a library car is inserted into the same frame at the same place: standing on the flat road 1.65 m below the
camera (KITTI's height), its near end on the ground row of the box's bottom edge, its centre column on the box's,
seen from the side the real car shows (the box's hand-judged `view`: rear, front, or broadside pointing left or
right). It is drawn with the simulator's own parts (the rasterizer, the scene's lighting,
the contact shadow, luma on a gray camera, the statistical harmonizer, the camera's look), switched on one level at a
time. Both cars
are cropped by their boxes (the inserted one by its drawn mask's box), resized to one size, described by HOG
features and told apart by an L2-regularized logistic regression under stratified k-fold cross-validation:
50 % accuracy means the classifier cannot tell them apart, 100 % that it always can.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from skimage.feature import hog

from drivesim.sim.camera_look import apply_camera_look_, look_of_frame
from drivesim.sim.geometry import scale_intrinsics
from drivesim.sim.harmonize import Harmonizer, StatisticalHarmonizer, harmonize_view_uint8_
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.raster import Rasterizer, roi_intrinsics
from drivesim.sim.shading import contact_shadow_
from drivesim.sim.vehicle_library import VehicleLibrary, VehicleModel
from drivesim.sim.vehicles import sample_paint

CAMERA_HEIGHT_M = 1.65  # KITTI's camera 0 above the road
CROP_SIZE_PX = (64, 40)  # (width, height) every crop is resized to
CROP_MARGIN = 0.05  # fraction of the box's size added on each side of a crop
LEVELS = ("mesh", "materials", "lighting", "shadow", "harmonization", "camera")
"""Rendering levels, each adding one part to the one before: a flat gray mesh, its materials (paint, glass, tyres,
lights; unlit), the scene's lighting, the contact shadow, harmonization, the camera's look (blended edges, the frame's
blur and noise)."""
DRIVES = {
    "0001": ("kitti_raw/2011_09_26/2011_09_26_drive_0001_sync/image_00/data/{:010d}.png", "kitti_raw/2011_09_26"),
    "06": ("kitti_odometry_stereo/image_l/{:06d}.png", "kitti_odometry_stereo"),
    "00": ("kitti_odometry_00_first200/image_0/{:06d}.png", "kitti_odometry_00_first200"),
    "07": ("kitti_odometry_07_first160/image_0/{:06d}.png", "kitti_odometry_07_first160"),
}
"""Real drive id -> (frame path pattern, folder holding its calibration), under the real-data folder."""
VIEW_YAW_RAD = {"rear": 0.0, "front": np.pi, "left": 0.5 * np.pi, "right": -0.5 * np.pi}
"""The side of a car the camera sees -> the car's heading relative to the optical axis (0: driving away from the
camera; positive: turned toward the image's left)."""
_FLAT_GRAY = Material(diffuse_rgb=(0.5, 0.5, 0.5), specular_rgb=(0.0, 0.0, 0.0), shininess=1.0, roughness=1.0)
_UNLIT = np.array([1, 1, 1, 0, 0, 1, 0, 0, 0], dtype=np.float32)  # ambient 1, no directional light: base colour
_DIRECTIONAL_GAIN = 0.8  # the simulator's default (ViewConfig.directional_gain)
_CONTACT_SHADOW = 0.6  # the simulator's default (ViewConfig.contact_shadow)


@dataclass(frozen=True)
class CarBox:
    """One hand-marked car: drive id, frame index, box (x0, y0, x1, y1) px (x1, y1 exclusive), parked or moving, the
    side of it the camera sees (`VIEW_YAW_RAD`)."""

    drive: str
    frame: int
    box: tuple[int, int, int, int]
    motion: str
    view: str = "rear"


def load_boxes(path: Path) -> list[CarBox]:
    """The hand-marked boxes of `path`; ValueError naming the first bad entry."""
    data = json.loads(Path(path).read_text())
    boxes = []
    for i, entry in enumerate(data.get("boxes", [])):
        box = tuple(int(v) for v in entry.get("box", ()))
        if entry.get("drive") not in DRIVES or len(box) != 4 or entry.get("motion") not in ("parked", "moving"):
            raise ValueError(f"{path}: box {i} needs drive in {sorted(DRIVES)}, box [x0, y0, x1, y1], motion")
        if box[2] <= box[0] or box[3] <= box[1] or int(entry.get("frame", -1)) < 0:
            raise ValueError(f"{path}: box {i} is empty or has a negative frame: {entry}")
        view = entry.get("view", "rear")
        if view not in VIEW_YAW_RAD:
            raise ValueError(f"{path}: box {i} has view {view!r}; use one of {sorted(VIEW_YAW_RAD)}")
        boxes.append(CarBox(entry["drive"], int(entry["frame"]), box, entry["motion"], view))  # type: ignore[arg-type]
    if not boxes:
        raise ValueError(f"{path}: no boxes")
    return boxes


def drive_intrinsics(real_root: Path, drive: str) -> np.ndarray:
    """(3, 3) intrinsics of camera 0 of a real drive, from its calibration file."""
    folder = Path(real_root) / DRIVES[drive][1]
    if drive == "0001":
        line = next(x for x in (folder / "calib_cam_to_cam.txt").read_text().splitlines() if x.startswith("P_rect_00"))
    else:
        line = (folder / "calib.txt").read_text().splitlines()[0]
    P = np.array([float(v) for v in line.split()[-12:]]).reshape(3, 4)
    return P[:, :3]


def load_frame(real_root: Path, drive: str, frame: int) -> np.ndarray:
    """A recorded frame as (h, w, 3) uint8 RGB (a gray camera's three equal channels); FileNotFoundError if absent."""
    path = Path(real_root) / DRIVES[drive][0].format(frame)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"no frame {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def ground_distance_m(K: np.ndarray, bottom_row_px: float, height_px: float) -> float:
    """Distance along the optical axis of the road point seen at `bottom_row_px` (flat road, camera 1.65 m up); from
    the box height (a 1.5 m tall car) when the row is at or above the horizon."""
    below_horizon_px = bottom_row_px - float(K[1, 2])
    if below_horizon_px > 2.0:
        return float(K[1, 1]) * CAMERA_HEIGHT_M / below_horizon_px
    return float(K[1, 1]) * 1.5 / max(height_px, 1.0)


def crop(
    image: np.ndarray, box: tuple[int, int, int, int], margin: float = CROP_MARGIN, width_px: int | None = None
) -> np.ndarray:
    """The box of `image` widened by `margin` of its size on each side (clipped to the image), as a gray
    `CROP_SIZE_PX` uint8 crop; with `width_px`, cut from the image first reduced to that width (a world's
    resolution)."""
    x0, y0, x1, y1 = box
    if width_px is not None and width_px < image.shape[1]:
        scale = width_px / image.shape[1]
        image = cv2.resize(image, (width_px, max(1, round(image.shape[0] * scale))), interpolation=cv2.INTER_AREA)
        x0, y0, x1, y1 = (v * scale for v in box)
    dx, dy = margin * (x1 - x0), margin * (y1 - y0)
    h, w = image.shape[:2]
    x0, x1 = max(0, int(round(x0 - dx))), min(w, int(round(x1 + dx)))
    y0, y1 = max(0, int(round(y0 - dy))), min(h, int(round(y1 + dy)))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"box {box} lies outside the {w} x {h} image")
    patch = image[y0:y1, x0:x1]
    if patch.ndim == 3:
        patch = cv2.cvtColor(np.ascontiguousarray(patch), cv2.COLOR_RGB2GRAY)
    return cv2.resize(patch, CROP_SIZE_PX, interpolation=cv2.INTER_AREA)


def reduced_view(
    frame: np.ndarray, K: np.ndarray, box: tuple[int, int, int, int], width_px: int
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """`frame` reduced to `width_px` wide (area mean, as `build-world` makes a world's frames), its intrinsics and
    `box` scaled with it: where a car is drawn at a world's resolution, as the simulator draws it."""
    scale = width_px / frame.shape[1]
    height_px = max(1, round(frame.shape[0] * scale))
    small = cv2.resize(frame, (width_px, height_px), interpolation=cv2.INTER_AREA)
    K_small = scale_intrinsics(K, scale, height_px / frame.shape[0])
    x0, y0, x1, y1 = (round(v * scale) for v in box)
    return small, K_small, (x0, y0, max(x1, x0 + 1), max(y1, y0 + 1))


def _level_meshes(model: VehicleModel, level: str) -> list[Mesh]:
    """The model's full meshes as a level draws them: all one flat gray at "mesh", their own materials above."""
    if level != "mesh":
        return list(model.full)
    return [dataclasses.replace(m, material=_FLAT_GRAY, vertex_rgb=None, texture_rgb=None, uv=None) for m in model.full]


def camera_pose_of_car(
    K: np.ndarray, box: tuple[int, int, int, int], length_m: float, width_m: float = 1.8, yaw_rad: float = 0.0
) -> np.ndarray:
    """(4, 4) T_camera_car of a car on the road whose near end stands on the box's bottom row, centred on its
    column, heading `yaw_rad` from the optical axis (0: driving away from the camera, pi / 2: toward the image's
    left)."""
    x0, y0, x1, y1 = box
    near_m = ground_distance_m(K, y1, y1 - y0)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    half_depth_m = 0.5 * (abs(c) * length_m + abs(s) * width_m)  # the footprint's half extent along the axis
    T = np.eye(4)
    to_camera = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # car x forward, y left, z up
    T[:3, :3] = to_camera @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [(0.5 * (x0 + x1) - K[0, 2]) * near_m / K[0, 0], CAMERA_HEIGHT_M, near_m + half_depth_m]
    return T


def insert_car(
    frame: np.ndarray,
    K: np.ndarray,
    box: tuple[int, int, int, int],
    model: VehicleModel,
    level: str,
    view: str = "rear",
    harmonizer: Harmonizer | None = None,
    light_elevation_deg: float = 0.0,
    light_gain: float = 1.0,
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """`frame` (h, w, 3) uint8 with `model` inserted at the place of `box`, seen from its `view` side
    (`VIEW_YAW_RAD`), drawn at `level` (`LEVELS`), and the inserted car's own box (x0, y0, x1, y1) px; only a region
    around the box is rendered. `harmonizer`: the harmonization level's (None: the simulator's statistical one);
    `light_elevation_deg`: the directional light's elevation as the view's setting of that name (0: from the
    viewpoint, 90: from overhead); `light_gain`: the scene's light (ambient and directional) times this."""
    if level not in LEVELS:
        raise ValueError(f"level {level!r}: choose one of {LEVELS}")
    if view not in VIEW_YAW_RAD:
        raise ValueError(f"view {view!r}: choose one of {sorted(VIEW_YAW_RAD)}")
    h, w = frame.shape[:2]
    bx0, by0, bx1, by1 = box
    bw, bh = bx1 - bx0, by1 - by0
    x0, y0 = max(0, bx0 - 2 * bw), max(0, by0 - 2 * bh)
    x1, y1 = min(w, bx1 + 2 * bw), min(h, by1 + bh)
    K_roi = roi_intrinsics(K, (x0, y0, x1 - x0, y1 - y0))
    T = camera_pose_of_car(K, box, float(model.length_m), float(model.width_m), VIEW_YAW_RAD[view])
    rank = LEVELS.index(level)
    lights = _UNLIT[None]
    if rank >= LEVELS.index("lighting"):
        mean = frame.reshape(-1, 3).mean(axis=0) / 255.0
        elevation_rad = np.deg2rad(light_elevation_deg)
        direction = [0.0, np.sin(elevation_rad), np.cos(elevation_rad)]  # travelling down and forward, camera frame
        ambient = light_gain * mean
        lights = np.concatenate([ambient, direction, _DIRECTIONAL_GAIN * ambient]).astype(np.float32)[None]
    raster = Rasterizer(x1 - x0, y1 - y0, cull_back_faces=True)
    drawn = raster.render(_level_meshes(model, level), T, K_roi, lighting=lights)
    out = frame.copy()
    region = np.ascontiguousarray(out[y0:y1, x0:x1])
    no_depth = np.full(region.shape[:2], np.inf, dtype=np.float32)  # nothing recorded in front of the car
    if rank >= LEVELS.index("shadow"):
        contact_shadow_(region, no_depth, K_roi, T, float(model.length_m), float(model.width_m), _CONTACT_SHADOW)
    car_depth = drawn.depth_m[0].numpy()
    mask = np.isfinite(car_depth)
    car = drawn.rgb[0].numpy().clip(0.0, 1.0)
    luma = (car @ np.array([0.299, 0.587, 0.114]))[..., None]  # a gray camera's car: luma, as the simulator draws it
    region[mask] = (np.repeat(luma, 3, axis=-1)[mask] * 255.0 + 0.5).astype(np.uint8)
    if rank >= LEVELS.index("harmonization"):
        harmonize_view_uint8_(harmonizer if harmonizer is not None else StatisticalHarmonizer(), region, mask)
    if rank >= LEVELS.index("camera"):
        apply_camera_look_(region, mask, look_of_frame(frame))
    out[y0:y1, x0:x1] = region
    if not mask.any():
        raise ValueError(f"the car inserted at box {box} is not in view")
    rows, cols = np.nonzero(mask)
    return out, (x0 + int(cols.min()), y0 + int(rows.min()), x0 + int(cols.max()) + 1, y0 + int(rows.max()) + 1)


def library_car(index: int, seed: int = 0) -> VehicleModel:
    """The procedural library's car for box `index`: models in turn, each box's car with its own sampled paint."""
    models = VehicleLibrary.procedural(8, seed).models
    rng = np.random.default_rng(seed * 100_003 + index)
    return models[index % len(models)].repainted(sample_paint(rng))


def hog_features(crops: np.ndarray) -> np.ndarray:
    """(n, d) HOG descriptors of (n, h, w) uint8 gray crops (9 orientations, 8 px cells, 2 x 2 cell blocks)."""
    return np.stack(
        [hog(c, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(2, 2), feature_vector=True) for c in crops]
    )


def _fit_logistic(x: np.ndarray, y: np.ndarray, l2: float, steps: int = 300) -> np.ndarray:
    """Weights (d + 1,) of an L2-regularized logistic regression (bias last) by gradient descent on standardized x."""
    xb = np.hstack([x, np.ones((len(x), 1))])
    w = np.zeros(xb.shape[1])
    lr = 1.0 / (0.25 * np.mean(np.sum(xb * xb, axis=1)) + l2)  # a safe step: the loss's curvature bound
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-(xb @ w)))
        grad = xb.T @ (p - y) / len(y) + l2 * np.r_[w[:-1], 0.0]
        w -= lr * grad
    return w


def stratified_folds(labels: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) fold index of each sample: each class shuffled and dealt round-robin over k folds."""
    fold = np.empty(len(labels), dtype=np.int64)
    for value in np.unique(labels):
        idx = rng.permutation(np.flatnonzero(labels == value))
        fold[idx] = np.arange(len(idx)) % k
    return fold


def c2st(
    features: np.ndarray, labels: np.ndarray, k: int = 5, repeats: int = 5, l2: float = 0.1, seed: int = 0
) -> np.ndarray:
    """(repeats, n) out-of-fold correctness (1 right, 0 wrong) of a logistic regression telling label 1 from 0 under
    stratified k-fold cross-validation, repeated with new folds; its mean is the C2ST accuracy."""
    labels = np.asarray(labels, dtype=np.float64)
    rng = np.random.default_rng(seed)
    correct = np.zeros((repeats, len(labels)))
    for r in range(repeats):
        folds = stratified_folds(labels, k, rng)
        for f in range(k):
            test, train = folds == f, folds != f
            mean, std = features[train].mean(axis=0), features[train].std(axis=0) + 1e-6
            w = _fit_logistic((features[train] - mean) / std, labels[train], l2)
            score = ((features[test] - mean) / std) @ w[:-1] + w[-1]
            correct[r, test] = (score > 0) == (labels[test] > 0.5)
    return correct


def accuracy_interval(correct: np.ndarray) -> tuple[float, float, float]:
    """(accuracy, low, high): the mean correctness over repeats and its Wilson 95 % interval over the samples."""
    n = correct.shape[-1]
    acc = float(correct.mean())
    z = 1.96
    centre = (acc + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(acc * (1 - acc) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return acc, float(centre - half), float(centre + half)
