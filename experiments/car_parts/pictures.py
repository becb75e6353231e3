"""Before/after pictures of the cars' parts (trim, lined arches, occlusion and window ramps, per-car materials).

Each version of the code renders its cells into an .npz (`--cells`), run once with the earlier code first on
PYTHONPATH and once with this checkout; `--compose` puts them side by side:

1. `car_parts_crops.png`: hand-marked real cars of the KITTI drives (`benchmarks/data/real_car_boxes.json`) beside the
   library car inserted at the same place, seen from the same side, as the C2ST draws it at its last level (the
   camera's look), at the recording's resolution, enlarged 2x without smoothing: real | before | after.
2. `car_parts_sim.png`: the simulator's own view of a real drive's world with library cars ahead (9 m, and 16 m in
   the next lane), default `ViewConfig`, enlarged 2x without smoothing: before | after.

Run from the repository root:

    PYTHONPATH=/tmp/before .venv/bin/python experiments/car_parts/pictures.py --cells /tmp/before.npz --world W
    .venv/bin/python experiments/car_parts/pictures.py --cells /tmp/after.npz --world W
    .venv/bin/python experiments/car_parts/pictures.py --compose /tmp/before.npz /tmp/after.npz
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers
from crops import BOXES, REAL, ROOT, crop_cell, labelled  # noqa: E402

PICKS = (7, 13, 20, 28, 34, 55)  # front, front, rear, broadside left, broadside left, rear; three drives
SCALE = 2
CELL_PX = (160, 90)  # (w, h) of a crop cell before enlarging


def crop_cells() -> tuple[np.ndarray, np.ndarray]:
    """(real, inserted) cells of the `PICKS` boxes, each (n, h, w) uint8."""
    from drivesim.bench import car_realism as cr

    boxes = cr.load_boxes(BOXES)
    real, inserted = [], []
    for i in PICKS:
        b = boxes[i]
        frame = cr.load_frame(REAL, b.drive, b.frame)
        image, _ = cr.insert_car(frame, cr.drive_intrinsics(REAL, b.drive), b.box, cr.library_car(i), "camera", b.view)
        real.append(crop_cell(frame, b.box, 0.25, CELL_PX))
        inserted.append(crop_cell(image, b.box, 0.25, CELL_PX))
    return np.stack(real), np.stack(inserted)


def sim_view(world_dir: Path) -> np.ndarray:
    """The simulator's gray view (h, w) uint8 of `world_dir` at frame 20 with two library cars ahead."""
    from drivesim.sim.vehicle_library import VehicleLibrary
    from drivesim.sim.vehicles import sample_paint
    from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
    from drivesim.sim.world import World

    world = World.load(world_dir)
    models = VehicleLibrary.procedural(8, 0).models
    frame = 20
    x, y = float(world.path["x_m"][frame]), float(world.path["y_m"][frame])
    yaw = float(world.path["yaw_rad"][frame])
    cars = [
        CarPlacement(
            models[k].repainted(sample_paint(np.random.default_rng(k))),
            x + d * np.cos(yaw) - side * np.sin(yaw), y + d * np.sin(yaw) + side * np.cos(yaw), yaw,
        )
        for k, d, side in ((1, 9.0, 0.0), (2, 16.0, 3.5))
    ]  # fmt: skip
    view = ViewSynthesizer(world, ViewConfig()).render(
        np.array([frame]), np.array([x]), np.array([y]), np.array([yaw]), [cars]
    )
    return cv2.cvtColor(view.rgb[0], cv2.COLOR_RGB2GRAY)


def compose(before: dict, after: dict, out: Path) -> None:
    """Write `car_parts_crops.png` (and `car_parts_sim.png` when both hold a simulator view) into `out`."""
    rows = [np.hstack([r, b, a]) for r, b, a in zip(after["real"], before["inserted"], after["inserted"], strict=True)]
    grid = cv2.resize(np.vstack(rows), None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    names = ["real car", "inserted, before", "inserted, with its parts"]
    cv2.imwrite(str(out / "car_parts_crops.png"), labelled(grid, names, CELL_PX[0] * SCALE))
    if "sim" in before and "sim" in after:
        gap = np.full((before["sim"].shape[0], 2), 255, np.uint8)
        strip = cv2.resize(np.hstack([before["sim"], gap, after["sim"]]), None, fx=SCALE, fy=SCALE,
                           interpolation=cv2.INTER_NEAREST)  # fmt: skip
        names = ["before", "with its parts"]
        cv2.imwrite(str(out / "car_parts_sim.png"), labelled(strip, names, (before["sim"].shape[1] + 2) * SCALE))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=Path, help="render this code's cells into this .npz")
    parser.add_argument("--world", type=Path, help="a real drive's world folder (for the simulator's view)")
    parser.add_argument("--compose", type=Path, nargs=2, metavar=("BEFORE", "AFTER"), help="two .npz of --cells")
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="folder the PNGs are written to")
    args = parser.parse_args()
    if args.cells is not None:
        real, inserted = crop_cells()
        cells = {"real": real, "inserted": inserted}
        if args.world is not None:
            cells["sim"] = sim_view(args.world)
        np.savez(args.cells, **cells)
    if args.compose is not None:
        compose(*(dict(np.load(p)) for p in args.compose), args.out)


if __name__ == "__main__":
    main()
