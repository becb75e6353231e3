"""Does a light from above (the sky, a high sun) make inserted cars harder to tell from real ones? (issue 44)

The C2ST of `benchmarks/bench_car_realism.py` at its default level (the car drawn at a world's 320 px with the
camera's look, as the simulator draws it) with the directional light at several elevations: the view's
`light_elevation_deg` (0, the default, is the paper's light from the viewpoint; 90 lights the roof and bonnet only).
Per elevation: the accuracy over all boxes, for boxes 12 px tall and more at 320 px (the near cars a policy passes),
and the crops' mean gray per 8 rows against the real crops'.

    .venv/bin/python experiments/car_look/light_elevation_probe.py --elevations 0,30,60,90
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from drivesim.bench import car_realism as cr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from what_separates import BOXES, REAL, WORLD_WIDTH_PX, accuracy  # noqa: E402


def inserted_crops(boxes: list[cr.CarBox], elevation_deg: float) -> np.ndarray:
    """The inserted crops of every box at the default level, drawn at 320 px, with the light at `elevation_deg`."""
    crops = []
    for i, b in enumerate(boxes):
        frame = cr.load_frame(REAL, b.drive, b.frame)
        small, K_small, box_small = cr.reduced_view(frame, cr.drive_intrinsics(REAL, b.drive), b.box, WORLD_WIDTH_PX)
        model = cr.library_car(i, 0)
        image, own_box = cr.insert_car(small, K_small, box_small, model, "camera", b.view, None, elevation_deg)
        crops.append(cr.crop(image, own_box))
    return np.stack(crops)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elevations", default="0,30,60,90", help="comma-separated elevations [deg]")
    args = parser.parse_args()
    if not REAL.is_dir():
        print(f"no real drives at {REAL}: this needs ../shared/data/real", file=sys.stderr)
        return 2
    boxes = cr.load_boxes(BOXES)
    real = np.stack([cr.crop(cr.load_frame(REAL, b.drive, b.frame), b.box, width_px=WORLD_WIDTH_PX) for b in boxes])
    # box heights at 320 px from the odometry frames' 1241 px width (0001's 1242 alike): the tall set can differ by a
    # box or two from what_separates.py's, which rounds each box's corners at 320 px
    tall = np.r_[[(b.box[3] - b.box[1]) * WORLD_WIDTH_PX / 1241 >= 12 for b in boxes] * 2]
    print(f"real crops' mean gray per 8 rows: {np.round(real.mean(axis=(0, 2))[::8]).astype(int)}")
    print("| light elevation | C2ST, all boxes | boxes 12 px and taller | mean gray per 8 rows |\n|---:|---:|---:|---|")
    for elevation_deg in (float(e) for e in args.elevations.split(",")):
        inserted = inserted_crops(boxes, elevation_deg)
        correct = accuracy(real, inserted)
        rows = np.round(inserted.mean(axis=(0, 2))[::8]).astype(int)
        print(f"| {elevation_deg:g} deg | {100 * correct.mean():.0f} % | {100 * correct[tall].mean():.0f} % | {rows} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
