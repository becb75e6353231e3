"""Probe: does the real car under the inserted one give the inserted car away in the C2ST?

The default crops of `what_separates.py` (the car drawn at a world's 320 px with the camera's look, over the frame's
own car at the hand-marked box), then each car drawn again into the frame with the real car's box first filled from
its surroundings (OpenCV's Telea inpainting of the box widened by `--grow` of its size each side), so that no part of
the real car shows around the inserted one. Prints both accuracies.

    .venv/bin/python experiments/car_look/cleared_probe.py [--grow 0.1]   # ~1 min
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

cr = ws.cr


def cleared(small: np.ndarray, box: tuple[int, int, int, int], grow: float) -> np.ndarray:
    """`small` with `box` (widened by `grow` of its size each side) inpainted from the pixels around it."""
    x0, y0, x1, y1 = box
    dx, dy = round(grow * (x1 - x0)) + 1, round(grow * (y1 - y0)) + 1
    hole = np.zeros(small.shape[:2], np.uint8)
    hole[max(0, y0 - dy) : y1 + dy, max(0, x0 - dx) : x1 + dx] = 255
    return cv2.inpaint(small, hole, 3, cv2.INPAINT_TELEA)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grow", type=float, default=0.1, help="fraction of the box's size added each side")
    args = parser.parse_args()
    boxes = cr.load_boxes(ws.BOXES)
    real, shipped, on_cleared = [], [], []
    for i, b in enumerate(boxes):
        scene = ws.scene_of(i, b)
        real.append(scene.real)
        shipped.append(scene.shipped)
        frame = cleared(scene.small, scene.box_small, args.grow)
        image, own_box = cr.insert_car(frame, scene.K_small, scene.box_small, scene.car, "camera", b.view)
        on_cleared.append(cr.crop(image, own_box))
    real_crops = np.stack(real)
    for name, crops in (("as shipped", shipped), ("over the cleared box", on_cleared)):
        acc, low, high = cr.accuracy_interval(ws.accuracy(real_crops, np.stack(crops))[None])
        print(f"C2ST {name}: {100 * acc:.0f} % [{100 * low:.0f}, {100 * high:.0f}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
