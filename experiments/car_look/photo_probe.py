"""Probe: how real does an inserted car look when its body carries a photograph of a real car?

The default crops of `what_separates.py` (the car drawn at a world's 320 px with the camera's look), then each car
drawn again with the pixels inside its drawn silhouette taken from a real car of another drive (a donor: the
hand-marked box of a car seen from the same side, reduced to the world's resolution and stretched over the
silhouette's box) before harmonization and the camera's look. An upper bound for a car library textured from
photographs: the silhouette, the place and the shading are the simulator's, the body's detail is a real car's.

No crop may share its content with a crop of the other class, so the drives are split in two halves: cars inserted
into one half's frames take their donors from the other half, and each half has its own C2ST (real crops of that half
against its inserted crops); the two halves' out-of-fold results are pooled.

    .venv/bin/python experiments/car_look/photo_probe.py [--any-side] [--whole-box] [--raw]   # ~2 min

`--any-side`: donors from cars seen from any side; `--whole-box`: the donor's whole box (its own outline and the
background around it) over the drawn car's box, the harmonizer and the camera's look still applied to the
silhouette; `--raw`: the photograph as it is, without the harmonizer and the camera's look.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

cr = ws.cr
HALVES = ({"0001", "06"}, {"00", "07"})
WHOLE_BOX = "--whole-box" in sys.argv  # the donor's whole box, its outline and background too, not the silhouette only
RAW = "--raw" in sys.argv  # the photograph as it is: no harmonizer and no camera look over it
ANY_SIDE = "--any-side" in sys.argv  # donors from every side: each used about once, not a few used many times


def _donor_patches(boxes: list, donor_drives: set[str]) -> dict[str, list[np.ndarray]]:
    """View -> the donor drives' real cars seen from that side, each its box at the world's resolution (RGB)."""
    patches: dict[str, list[np.ndarray]] = {}
    for b in boxes:
        if b.drive not in donor_drives:
            continue
        frame = cr.load_frame(ws.REAL, b.drive, b.frame)
        small, _, (x0, y0, x1, y1) = cr.reduced_view(
            frame, cr.drive_intrinsics(ws.REAL, b.drive), b.box, ws.WORLD_WIDTH_PX
        )
        if y1 - y0 >= 4:
            patches.setdefault(b.view, []).append(small[y0:y1, x0:x1].copy())
    return patches


def _with_photo(donor: np.ndarray):
    """A stand-in for the harmonizer that first paints `donor` over the car's silhouette box, then harmonizes."""
    original = cr.harmonize_view_uint8_

    def harmonize(harmonizer, region: np.ndarray, mask: np.ndarray) -> None:
        rows, cols = np.nonzero(mask)
        if len(rows):
            r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
            stretched = cv2.resize(donor, (int(c1 - c0), int(r1 - r0)), interpolation=cv2.INTER_LINEAR)
            window = region[r0:r1, c0:c1]
            inside = np.ones_like(mask[r0:r1, c0:c1]) if WHOLE_BOX else mask[r0:r1, c0:c1]
            window[inside] = stretched[inside]
        if not RAW:
            original(harmonizer, region, mask)

    return harmonize


def _half_crops(boxes: list, test_drives: set[str], donor_drives: set[str]) -> tuple[np.ndarray, ...]:
    """Real, shipped-inserted and photo-inserted crops of the boxes of `test_drives`."""
    donors = _donor_patches(boxes, donor_drives)
    every_donor = [p for patches in donors.values() for p in patches]
    real, shipped, photo = [], [], []
    original = cr.harmonize_view_uint8_
    for i, b in enumerate(boxes):
        if b.drive not in test_drives:
            continue
        scene = ws.scene_of(i, b)
        real.append(scene.real)
        shipped.append(scene.shipped)
        pool = every_donor if ANY_SIDE else (donors.get(b.view) or every_donor)
        cr.harmonize_view_uint8_ = _with_photo(pool[i % len(pool)])
        try:
            level = "harmonization" if RAW else "camera"
            image, own_box = cr.insert_car(scene.small, scene.K_small, scene.box_small, scene.car, level, b.view)
        finally:
            cr.harmonize_view_uint8_ = original
        photo.append(cr.crop(image, own_box))
    return np.stack(real), np.stack(shipped), np.stack(photo)


def main() -> int:
    if not ws.REAL.is_dir():
        print(f"no real drives at {ws.REAL}: this needs ../shared/data/real", file=sys.stderr)
        return 2
    boxes = cr.load_boxes(ws.BOXES)
    shipped_correct, photo_correct = [], []
    for test_drives, donor_drives in (HALVES, HALVES[::-1]):
        real, shipped, photo = _half_crops(boxes, test_drives, donor_drives)
        s, p = ws.accuracy(real, shipped), ws.accuracy(real, photo)
        shipped_correct.append(s)
        photo_correct.append(p)
        names = "+".join(sorted(test_drives))
        shown = f"as shipped {100 * s.mean():.0f} %, photo body {100 * p.mean():.0f} %"
        print(f"drives {names} ({len(real)} boxes): {shown}")
    for name, parts in (("as shipped", shipped_correct), ("photo body", photo_correct)):
        acc, low, high = cr.accuracy_interval(np.concatenate(parts)[None])
        print(f"pooled, {name}: {100 * acc:.0f} % [{100 * low:.0f}, {100 * high:.0f}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
