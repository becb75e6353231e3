"""Probe: what a real car of another drive scores on the C2ST when pasted into each hand-marked box.

For each box, a real car from a drive of the other half (0001 + 06 against 00 + 07, as `photo_probe.py` splits them,
so no crop shares its content with a crop of the other class) is stretched over the box at a world's 320 px and
pasted: as a plain rectangle (its own background and a seam at the box's edge), or blended in the gradient domain
(OpenCV's seamlessClone, Poisson blending: the seam gone, the donor's outline and inside kept), from a car of any side
or, where the other half has one, of the same side. Each half its own C2ST, pooled. Beside `photo_probe.py` (the
same photographs inside the library car's silhouette) it separates the car's outline from the body's detail.

    .venv/bin/python experiments/car_look/paste_probe.py   # ~2 min
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import photo_probe as pp  # noqa: E402
import what_separates as ws  # noqa: E402

cr = ws.cr
WAYS = ("rectangle, any side", "blended, any side", "blended, same side")


def pasted(small: np.ndarray, box: tuple[int, int, int, int], donor: np.ndarray, blended: bool) -> np.ndarray:
    """`small` with `donor` stretched over `box`, as a rectangle or blended in the gradient domain."""
    x0, y0, x1, y1 = box
    stretched = cv2.resize(donor, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
    out = small.copy()
    if not blended:
        out[y0:y1, x0:x1] = stretched
        return out
    source = cv2.copyMakeBorder(stretched, 2, 2, 2, 2, cv2.BORDER_REFLECT)
    mask = np.zeros(source.shape[:2], np.uint8)
    mask[1:-1, 1:-1] = 255
    try:
        return cv2.seamlessClone(source, small, mask, ((x0 + x1) // 2, (y0 + y1) // 2), cv2.NORMAL_CLONE)
    except cv2.error:  # a box at the frame's edge: the blend needs room around it
        out[y0:y1, x0:x1] = stretched
        return out


def main() -> int:
    boxes = cr.load_boxes(ws.BOXES)
    correct: dict[str, list[np.ndarray]] = {way: [] for way in WAYS}
    for test_drives, donor_drives in (pp.HALVES, pp.HALVES[::-1]):
        donors = pp._donor_patches(boxes, donor_drives)
        every_donor = [p for patches in donors.values() for p in patches]
        real, crops = [], {way: [] for way in WAYS}
        for i, b in enumerate(boxes):
            if b.drive not in test_drives:
                continue
            frame = cr.load_frame(ws.REAL, b.drive, b.frame)
            small, _, box = cr.reduced_view(frame, cr.drive_intrinsics(ws.REAL, b.drive), b.box, ws.WORLD_WIDTH_PX)
            real.append(cr.crop(frame, b.box, width_px=ws.WORLD_WIDTH_PX))
            for way in WAYS:
                pool = (donors.get(b.view) or every_donor) if way.endswith("same side") else every_donor
                crops[way].append(cr.crop(pasted(small, box, pool[i % len(pool)], "blended" in way), box))
        for way in WAYS:
            correct[way].append(ws.accuracy(np.stack(real), np.stack(crops[way])))
    for way, parts in correct.items():
        acc, low, high = cr.accuracy_interval(np.concatenate(parts)[None])
        halves = " / ".join(f"{100 * p.mean():.0f}" for p in parts)
        print(f"{way}: {100 * acc:.0f} % [{100 * low:.0f}, {100 * high:.0f}] (halves {halves} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
