"""Probe: does the C2ST move when each inserted car is drawn at the real car's size in the image?

The default crops of `what_separates.py` (the car drawn at a world's 320 px with the camera's look), then each car
drawn again with its distance scaled by (its drawn box's height / the hand-marked box's height), so that its height
in the image matches the real car's, and the same classifier on those crops. Prints the spread of the height ratio
and both accuracies.

    .venv/bin/python experiments/car_look/size_probe.py   # ~1 min
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

cr = ws.cr


def _drawn_at_distance_scale(small, K_small, box_small, car, view: str, scale: float):
    """`insert_car` with the ground distance of the box's bottom row times `scale`."""
    original = cr.ground_distance_m
    cr.ground_distance_m = lambda K, row_px, height_px: original(K, row_px, height_px) * scale
    try:
        return cr.insert_car(small, K_small, box_small, car, "camera", view)
    finally:
        cr.ground_distance_m = original


def main() -> int:
    boxes = cr.load_boxes(ws.BOXES)
    real, shipped, matched, ratios = [], [], [], []
    for i, b in enumerate(boxes):
        scene = ws.scene_of(i, b)
        real.append(scene.real)
        shipped.append(scene.shipped)
        own_box, box_small = scene.own_box, scene.box_small
        ratio = (own_box[3] - own_box[1]) / max(1, box_small[3] - box_small[1])
        ratios.append(ratio)
        image, own_box = _drawn_at_distance_scale(scene.small, scene.K_small, box_small, scene.car, b.view, ratio)
        matched.append(cr.crop(image, own_box))
    real_crops = np.stack(real)
    p10, p50, p90 = np.percentile(ratios, [10, 50, 90])
    print(f"inserted / real box height: median {p50:.2f}, 10-90 % {p10:.2f}-{p90:.2f}")
    print(f"C2ST as shipped: {100 * ws.accuracy(real_crops, np.stack(shipped)).mean():.0f} %")
    print(f"C2ST size-matched: {100 * ws.accuracy(real_crops, np.stack(matched)).mean():.0f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
