"""Before/after pictures of the camera's look on inserted cars, for docs/fidelity.md.

1. `car_look_crops.png`: hand-marked real cars of the KITTI drives (`benchmarks/data/real_car_boxes.json`) beside
   the library car inserted at the same place by the C2ST (`drivesim.bench.car_realism`), before (harmonization
   level) and after (+ the camera's look), at the recording's resolution, enlarged 2x without smoothing.
2. `car_look_sim.png` (with `--world`): the simulator's own view of a real drive's world with a library car 9 m and
   16 m ahead, `ViewConfig(camera_look=False)` then `True`, enlarged 2x without smoothing.

Run from the repository root:  .venv/bin/python experiments/car_look/pictures.py [--world WS/world]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from drivesim.bench import car_realism as cr
from drivesim.sim.vehicle_library import VehicleLibrary
from drivesim.sim.vehicles import sample_paint
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from drivesim.sim.world import World

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers
from crops import BOXES, REAL, ROOT, crop_cell, labelled  # noqa: E402

PICKS = (9, 20, 55)  # boxes of three drives
SCALE = 2
CELL_PX = (120, 64)  # (w, h) of a crop cell before enlarging


def crops_picture(out: Path) -> None:
    """Real | before | after for the `PICKS` boxes."""
    boxes = cr.load_boxes(BOXES)
    rows = []
    for i in PICKS:
        b = boxes[i]
        frame = cr.load_frame(REAL, b.drive, b.frame)
        K = cr.drive_intrinsics(REAL, b.drive)
        model = cr.library_car(i)
        cells = [crop_cell(frame, b.box, 0.5, CELL_PX)]
        for level in ("harmonization", "camera"):
            image, _ = cr.insert_car(frame, K, b.box, model, level)
            cells.append(crop_cell(image, b.box, 0.5, CELL_PX))
        rows.append(np.hstack(cells))
    grid = cv2.resize(np.vstack(rows), None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    names = ["real car", "inserted, before", "inserted, + camera look"]
    cv2.imwrite(str(out), labelled(grid, names, CELL_PX[0] * SCALE))


def sim_picture(world_dir: Path, out: Path) -> None:
    """The simulator's view with a library car ahead, without then with the camera's look."""
    world = World.load(world_dir)
    model = VehicleLibrary.procedural(8, 0).models[1].repainted(sample_paint(np.random.default_rng(3)))
    frame = 20
    x, y = float(world.path["x_m"][frame]), float(world.path["y_m"][frame])
    yaw = float(world.path["yaw_rad"][frame])
    views = []
    for look in (False, True):
        vs = ViewSynthesizer(world, ViewConfig(camera_look=look))
        cars = [
            CarPlacement(model, x + d * np.cos(yaw) - side * np.sin(yaw), y + d * np.sin(yaw) + side * np.cos(yaw), yaw)
            for d, side in ((9.0, 0.0), (16.0, 3.5))
        ]
        view = vs.render(np.array([frame]), np.array([x]), np.array([y]), np.array([yaw]), [cars])
        views.append(cv2.cvtColor(view.rgb[0], cv2.COLOR_RGB2GRAY))
    strip = np.hstack([views[0], np.full((views[0].shape[0], 2), 255, np.uint8), views[1]])
    strip = cv2.resize(strip, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(out), labelled(strip, ["camera_look off", "camera_look on"], (views[0].shape[1] + 2) * SCALE))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", type=Path, help="a real drive's world folder (for the simulator's view)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="folder the PNGs are written to")
    args = parser.parse_args()
    crops_picture(args.out / "car_look_crops.png")
    if args.world is not None:
        sim_picture(args.world, args.out / "car_look_sim.png")


if __name__ == "__main__":
    main()
