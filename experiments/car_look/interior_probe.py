"""Probe: is it the car's outline or its inside that the C2ST tells apart?

The default crops of `what_separates.py` (64 x 40, the car drawn at a world's 320 px with the camera's look), then the
same classifier on each crop's inside only (a margin of `f` of the crop's size cut off each side, the rest resized
back to 64 x 40) and on its border band only (the inside filled with the crop's mean gray).

    .venv/bin/python experiments/car_look/interior_probe.py   # ~1 min
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

MARGINS = (0.15, 0.25)


def inside(crops: np.ndarray, margin: float) -> np.ndarray:
    """Each crop without a `margin` band on every side, resized back to the crop's size."""
    h, w = crops.shape[1:]
    dy, dx = int(h * margin), int(w * margin)
    return np.stack([cv2.resize(c[dy : h - dy, dx : w - dx], (w, h), interpolation=cv2.INTER_LINEAR) for c in crops])


def border(crops: np.ndarray, margin: float) -> np.ndarray:
    """Each crop with its inside (all but a `margin` band on every side) filled with the crop's mean gray."""
    h, w = crops.shape[1:]
    dy, dx = int(h * margin), int(w * margin)
    out = crops.copy()
    for c in out:
        c[dy : h - dy, dx : w - dx] = int(c.mean())
    return out


def main() -> int:
    real, inserted, _, _ = ws.default_crops(ws.cr.load_boxes(ws.BOXES))
    print(f"| whole crop | {100 * ws.accuracy(real, inserted).mean():.0f} % |")
    for margin in MARGINS:
        kept_inside = ws.accuracy(inside(real, margin), inside(inserted, margin)).mean()
        kept_border = ws.accuracy(border(real, margin), border(inserted, margin)).mean()
        print(f"| inside, {margin:.0%} cut each side | {100 * kept_inside:.0f} % |")
        print(f"| border band of {margin:.0%} only | {100 * kept_border:.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
