"""What tells an inserted car from a real one in the C2ST: the crops' geometry, frequencies, rows, sizes and views.

The crops of `benchmarks/bench_car_realism.py` at its default level (the car drawn at a world's 320 px with the
camera's look, as the simulator draws it), then the same logistic regression on HOG with the crops changed or
split: cut at the hand-marked box instead of the car's own, both blurred, both reduced to 16 x 10, each crop's
mean and contrast equalized, the top or bottom half only; accuracy by box height and by the side the car shows.

    .venv/bin/python experiments/car_look/what_separates.py   # prints a table; ~1 min
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivesim.bench import car_realism as cr

ROOT = Path(__file__).resolve().parents[2]
BOXES = ROOT / "benchmarks" / "data" / "real_car_boxes.json"
REAL = ROOT.parent / "shared" / "data" / "real"
WORLD_WIDTH_PX = 320


@dataclass(frozen=True)
class BoxScene:
    """One hand-marked box at a world's resolution: its real crop, the reduced frame, intrinsics and box, the library
    car the benchmark inserts there, that car drawn as shipped and its crop."""

    real: np.ndarray
    small: np.ndarray
    K_small: np.ndarray
    box_small: tuple[int, int, int, int]
    car: cr.VehicleModel
    image: np.ndarray
    own_box: tuple[int, int, int, int]

    @property
    def shipped(self) -> np.ndarray:
        """The crop of the car as shipped, cut at its own drawn box."""
        return cr.crop(self.image, self.own_box)


def scene_of(index: int, b: cr.CarBox) -> BoxScene:
    """Box `index` of the boxes file at a world's resolution, with the benchmark's car drawn as shipped."""
    frame = cr.load_frame(REAL, b.drive, b.frame)
    small, K_small, box_small = cr.reduced_view(frame, cr.drive_intrinsics(REAL, b.drive), b.box, WORLD_WIDTH_PX)
    car = cr.library_car(index, 0)
    image, own_box = cr.insert_car(small, K_small, box_small, car, "camera", b.view)
    real = cr.crop(frame, b.box, width_px=WORLD_WIDTH_PX)
    return BoxScene(real, small, K_small, box_small, car, image, own_box)


def default_crops(boxes: list[cr.CarBox]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Real crops, inserted crops (the car's own box), inserted crops cut at the real box, box heights at 320 px."""
    real, inserted, at_real_box, heights = [], [], [], []
    for i, b in enumerate(boxes):
        frame = cr.load_frame(REAL, b.drive, b.frame)
        K = cr.drive_intrinsics(REAL, b.drive)
        real.append(cr.crop(frame, b.box, width_px=WORLD_WIDTH_PX))
        small, K_small, box_small = cr.reduced_view(frame, K, b.box, WORLD_WIDTH_PX)
        image, own_box = cr.insert_car(small, K_small, box_small, cr.library_car(i, 0), "camera", b.view)
        inserted.append(cr.crop(image, own_box))
        at_real_box.append(cr.crop(image, box_small))
        heights.append(box_small[3] - box_small[1])
    return np.stack(real), np.stack(inserted), np.stack(at_real_box), np.array(heights)


def accuracy(real: np.ndarray, inserted: np.ndarray) -> np.ndarray:
    """Per-crop out-of-fold correctness (2n,) of the benchmark's classifier on the two sets of crops."""
    labels = np.r_[np.zeros(len(real)), np.ones(len(inserted))]
    features = np.vstack([cr.hog_features(np.ascontiguousarray(real)), cr.hog_features(np.ascontiguousarray(inserted))])
    return cr.c2st(features, labels).mean(axis=0)


def _blurred(crops: np.ndarray) -> np.ndarray:
    return np.stack([cv2.GaussianBlur(c, (0, 0), 2.0) for c in crops])


def _coarse(crops: np.ndarray) -> np.ndarray:
    w, h = cr.CROP_SIZE_PX
    return np.stack([cv2.resize(cv2.resize(c, (16, 10), interpolation=cv2.INTER_AREA), (w, h)) for c in crops])


def _equalized(crops: np.ndarray) -> np.ndarray:
    c = crops.astype(np.float32)
    mean, std = c.mean(axis=(1, 2), keepdims=True), c.std(axis=(1, 2), keepdims=True) + 1.0
    return np.clip((c - mean) / std * 40.0 + 110.0, 0, 255).astype(np.uint8)


def main() -> int:
    if not REAL.is_dir():
        print(f"no real drives at {REAL}: this needs ../shared/data/real", file=sys.stderr)
        return 2
    boxes = cr.load_boxes(BOXES)
    real, inserted, at_real_box, heights = default_crops(boxes)
    rows = {
        "default (the benchmark's)": accuracy(real, inserted),
        "inserted cut at the hand-marked box": accuracy(real, at_real_box),
        "both blurred (sigma 2 px of the 64 x 40 crop)": accuracy(_blurred(real), _blurred(inserted)),
        "both reduced to 16 x 10": accuracy(_coarse(real), _coarse(inserted)),
        "each crop's mean and contrast equalized": accuracy(_equalized(real), _equalized(inserted)),
        "top half of the crops": accuracy(real[:, :20], inserted[:, :20]),
        "bottom half of the crops": accuracy(real[:, 20:], inserted[:, 20:]),
    }
    print("| crops | C2ST accuracy |\n|---|---:|")
    for name, correct in rows.items():
        print(f"| {name} | {100 * correct.mean():.0f} % |")
    correct, n = rows["default (the benchmark's)"], len(boxes)
    both_heights, views = np.r_[heights, heights], np.array([b.view for b in boxes] * 2)
    print("\n| boxes | count | C2ST accuracy |\n|---|---:|---:|")
    for low, high in ((0, 6), (6, 12), (12, 1000)):
        chosen = (both_heights >= low) & (both_heights < high)
        print(f"| {low}-{high} px tall at 320 px | {chosen.sum() // 2} | {100 * correct[chosen].mean():.0f} % |")
    for view in sorted(set(views.tolist())):
        print(f"| seen from the {view} | {(views == view).sum() // 2} | {100 * correct[views == view].mean():.0f} % |")
    profile = np.stack([real.mean(axis=(0, 2)), inserted.mean(axis=(0, 2))])[:, ::8]
    print(
        f"\nmean gray per 8 rows of the crop, top to bottom ({n} boxes): real {np.round(profile[0]).astype(int)}, "
        f"inserted {np.round(profile[1]).astype(int)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
