"""Picture helpers shared by the car studies: a car's box cropped into a grid cell, a grid with named columns."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
BOXES = ROOT / "benchmarks" / "data" / "real_car_boxes.json"
REAL = ROOT.parent / "shared" / "data" / "real"


def crop_cell(image: np.ndarray, box: tuple[int, int, int, int], widen: float, cell_px: tuple[int, int]) -> np.ndarray:
    """The box (x0, y0, x1, y1) of an RGB image widened by `widen` times its size on each side, gray, fitted into
    `cell_px` (w, h)."""
    x0, y0, x1, y1 = box
    dx, dy = int((x1 - x0) * widen), int((y1 - y0) * widen)
    h, w = image.shape[:2]
    patch = image[max(0, y0 - dy) : min(h, y1 + dy), max(0, x0 - dx) : min(w, x1 + dx)]
    return cv2.resize(cv2.cvtColor(np.ascontiguousarray(patch), cv2.COLOR_RGB2GRAY), cell_px, cv2.INTER_AREA)


def labelled(image: np.ndarray, names: list[str], cell_w: int) -> np.ndarray:
    """A gray grid with a white header naming its columns of `cell_w` pixels."""
    header = np.full((20, image.shape[1]), 255, dtype=np.uint8)
    for c, name in enumerate(names):
        cv2.putText(header, name, (c * cell_w + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, 0, 1, cv2.LINE_AA)
    return np.vstack([header, image])
