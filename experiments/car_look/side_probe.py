"""Probe: the C2ST of `photo_probe.py` and `paste_probe.py` split by the side of the car the camera sees.

Per box, the mean out-of-fold correctness of its real and its inserted crop, over the two halves of the drives, for:
the library car as shipped, a real car's photograph inside the library car's outline, and a real car blended into the
box with its own outline (Poisson). Then the library car itself blended into the frame the same way (its drawn
region, dilated by a pixel, over the frame without it), pooled over all boxes.

    .venv/bin/python experiments/car_look/side_probe.py   # ~3 min
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import paste_probe as pa  # noqa: E402
import photo_probe as pp  # noqa: E402
import what_separates as ws  # noqa: E402

cr = ws.cr
WAYS = ("as shipped", "photo inside our outline", "real car blended with its outline")
SIDES = ("rear", "front", "left", "right")


def ours_blended(small: np.ndarray, drawn: np.ndarray) -> np.ndarray:
    """The frame with the library car's drawn pixels (the region `drawn` changed, dilated by 1 px) Poisson-blended."""
    mask = cv2.dilate(np.any(drawn != small, axis=-1).astype(np.uint8) * 255, np.ones((3, 3), np.uint8))
    rows, cols = np.nonzero(mask)
    r0, r1 = max(0, rows.min() - 2), min(small.shape[0], rows.max() + 3)
    c0, c1 = max(0, cols.min() - 2), min(small.shape[1], cols.max() + 3)
    region = mask[r0:r1, c0:c1].copy()
    region[[0, -1], :] = 0
    region[:, [0, -1]] = 0
    try:
        centre = ((c0 + c1) // 2, (r0 + r1) // 2)
        return cv2.seamlessClone(np.ascontiguousarray(drawn[r0:r1, c0:c1]), small, region, centre, cv2.NORMAL_CLONE)
    except cv2.error:  # no room around the car at the frame's edge
        return drawn


def main() -> int:
    boxes = cr.load_boxes(ws.BOXES)
    per_box: dict[str, list[np.ndarray]] = {way: [] for way in WAYS}
    sides: list[str] = []
    real_all, blended_all = [], []
    original = cr.harmonize_view_uint8_
    for test_drives, donor_drives in (pp.HALVES, pp.HALVES[::-1]):
        donors = [p for patches in pp._donor_patches(boxes, donor_drives).values() for p in patches]
        real, crops = [], {way: [] for way in WAYS}
        for i, b in enumerate(boxes):
            if b.drive not in test_drives:
                continue
            sides.append(b.view)
            scene = ws.scene_of(i, b)
            small, K, box, car, donor = scene.small, scene.K_small, scene.box_small, scene.car, donors[i % len(donors)]
            real.append(scene.real)
            crops["as shipped"].append(scene.shipped)
            blended_all.append(cr.crop(ours_blended(small, scene.image), scene.own_box))
            cr.harmonize_view_uint8_ = pp._with_photo(donor)
            try:
                image, own = cr.insert_car(small, K, box, car, "camera", b.view)
            finally:
                cr.harmonize_view_uint8_ = original
            crops["photo inside our outline"].append(cr.crop(image, own))
            crops["real car blended with its outline"].append(cr.crop(pa.pasted(small, box, donor, True), box))
        real_all.extend(real)
        for way in WAYS:
            correct = ws.accuracy(np.stack(real), np.stack(crops[way]))
            per_box[way].append(0.5 * (correct[: len(real)] + correct[len(real) :]))
    side = np.array(sides)
    print("| crops | " + " | ".join(SIDES) + " |\n|---|" + "---:|" * len(SIDES))
    for way, parts in per_box.items():
        both = np.concatenate(parts)
        cells = " | ".join(f"{100 * both[side == s].mean():.0f} % ({(side == s).sum()})" for s in SIDES)
        print(f"| {way} | {cells} |")
    acc, low, high = cr.accuracy_interval(ws.accuracy(np.stack(real_all), np.stack(blended_all))[None])
    shown = f"{100 * acc:.0f} % [{100 * low:.0f}, {100 * high:.0f}]"
    print(f"\nthe library car Poisson-blended into the frame, all boxes in one C2ST: {shown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
