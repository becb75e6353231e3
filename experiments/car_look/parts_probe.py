"""Probe: does the C2ST move with the body's light ramp, number plates or the strength of the scene's light?

The default crops of `what_separates.py` (the car drawn at a world's 320 px with the camera's look), with the library's
cars rebuilt under one change each: the body's occlusion floor (`BODY_OCCLUSION_FLOOR`, the light factor at the
ground) raised, white number plates (EU size, 520 x 110 mm, retroreflective white) on both ends, and the scene's
light (ambient from the frame's mean, and the directional light) scaled by `--light-gains`. Prints the C2ST
accuracy and the row profile of each arm.

    .venv/bin/python experiments/car_look/parts_probe.py [--light-gains 1.5,2,3] [--skip-parts]   # ~1 min an arm
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import numpy as np

from drivesim.sim import vehicles

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

PLATE_RGB = (0.75, 0.75, 0.72)


def _with_plates(original):
    """`vehicles._trim` with a number plate on each end."""

    def trim(shape, lay, parts):
        out = original(shape, lay, parts)
        bumper_z = lay.sill_z + 0.08
        for sign, end, z0 in ((1.0, lay.front_x, bumper_z), (-1.0, lay.rear_x, bumper_z + 0.14)):
            x = end - sign * (vehicles.LENS_PROUD_M - 2 * vehicles.TRIM_PROUD_M)
            out.append((*vehicles._end_box(x, sign * 0.02, 0.26, z0, z0 + 0.11), PLATE_RGB))
        return out

    return trim


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--light-gains", default="", help="comma-separated gains of the scene's light (arms)")
    parser.add_argument("--skip-parts", action="store_true", help="only the shipped car and the light arms")
    args = parser.parse_args()
    boxes = ws.cr.load_boxes(ws.BOXES)
    floor0, trim0, insert0 = vehicles.BODY_OCCLUSION_FLOOR, vehicles._trim, ws.cr.insert_car
    arms = [("as shipped", floor0, False, 1.0)]
    if not args.skip_parts:
        arms += [("plates", floor0, True, 1.0)] + [(f"occlusion floor {f}", f, False, 1.0) for f in (0.6, 1.0)]
        arms += [("floor 0.6 + plates", 0.6, True, 1.0)]
    arms += [(f"light x{g}", floor0, False, float(g)) for g in args.light_gains.split(",") if g]
    for name, floor, plates, gain in arms:
        vehicles.BODY_OCCLUSION_FLOOR = floor
        vehicles._trim = _with_plates(trim0) if plates else trim0
        ws.cr.insert_car = functools.partial(insert0, light_gain=gain)
        real, inserted, _, _ = ws.default_crops(boxes)
        correct = ws.accuracy(real, inserted)
        profile = np.round(inserted.mean(axis=(0, 2))[::8]).astype(int)
        print(f"| {name} | {100 * correct.mean():.0f} % | {profile} |", flush=True)
    print(f"real rows: {np.round(real.mean(axis=(0, 2))[::8]).astype(int)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
