"""How real the inserted cars look on the real drives: a classifier two-sample test (C2ST), per drive and per level.

The recording's own cars, boxed by hand (`benchmarks/data/real_car_boxes.json`), against library cars inserted into
the same frames at the same places and seen from the same side (`drivesim.bench.car_realism`), drawn at six levels
(a flat gray mesh, + its materials, + the scene's lighting, + the contact shadow, + harmonization, + the camera's
look). A logistic regression
on HOG features of the gray crops, stratified 5-fold cross-validation repeated 5 times: 50 % = indistinguishable,
100 % = always told apart. Per drive: the same out-of-fold predictions, counted over that drive's crops only.

    .venv/bin/python benchmarks/bench_car_realism.py   # writes benchmarks/results/car_realism.{md,json,png}
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from _lib.report import measured_now, write_markdown

from drivesim.bench import car_realism as cr
from drivesim.sim.harmonize import Harmonizer

HERE = Path(__file__).resolve().parent
REAR = "camera_rear"
RESULTS = HERE / "results" / "car_realism.md"
BOXES = HERE / "data" / "real_car_boxes.json"
REAL = HERE.parent.parent / "shared" / "data" / "real"
LEVEL_NAMES = {
    "mesh": "mesh only (flat gray)",
    "materials": "+ materials (unlit)",
    "lighting": "+ lighting",
    "shadow": "+ contact shadow",
    "harmonization": "+ harmonization",
    "camera": "+ camera look (blended edges, the frame's blur and noise; the default)",
    REAR: "the default, every car seen from behind (the protocol before the boxes' views)",
}
ROWS = (*cr.LEVELS, REAR)
WORLD_WIDTH_PX = 320  # build-world's default sim_width_px
RESOLUTIONS = {"recording": (None, False), "world": (WORLD_WIDTH_PX, False), "world_drawn": (WORLD_WIDTH_PX, True)}
"""Where cars are drawn and crops cut, as (width px, drawn at that width): the recorded frames as they are; reduced to
a world's width after the car is drawn at the recording's; the car drawn into the reduced frame, as the simulator
draws it."""
GRID_PER_DRIVE = 3
GRID_SCALE = 2


def crops_of(
    boxes: list[cr.CarBox],
    real_root: Path,
    seed: int,
    width_px: int | None,
    drawn_at_width: bool = False,
    harmonizer: Harmonizer | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(n, h, w) real crops and, per level, the (n, h, w) crops of the car inserted at each box; cut from the frames
    reduced to `width_px` (None: at the recording's resolution), the car drawn before the reduction or, with
    `drawn_at_width`, into the reduced frame; `harmonizer` for the harmonization level (None: the statistical one)."""
    real, inserted = [], {row: [] for row in ROWS}
    for i, b in enumerate(boxes):
        frame = cr.load_frame(real_root, b.drive, b.frame)
        K = cr.drive_intrinsics(real_root, b.drive)
        real.append(cr.crop(frame, b.box, width_px=width_px))
        model = cr.library_car(i, seed)
        target, K_target, box_target, cut_width = frame, K, b.box, width_px
        if drawn_at_width and width_px is not None:
            target, K_target, box_target = cr.reduced_view(frame, K, b.box, width_px)
            cut_width = None
        for row in ROWS:
            level, view = ("camera", "rear") if row == REAR else (row, b.view)
            image, box = cr.insert_car(target, K_target, box_target, model, level, view, harmonizer)
            inserted[row].append(cr.crop(image, box, width_px=cut_width))
    return np.stack(real), {level: np.stack(c) for level, c in inserted.items()}


def measure(real: np.ndarray, inserted: dict[str, np.ndarray], drives: np.ndarray, seed: int) -> dict[str, dict]:
    """Per level: the C2ST accuracy and interval over all boxes and per drive."""
    real_features = cr.hog_features(real)
    labels = np.r_[np.zeros(len(real)), np.ones(len(real))]
    both_drives = np.r_[drives, drives]
    out = {}
    for level in ROWS:
        features = np.vstack([real_features, cr.hog_features(inserted[level])])
        correct = cr.c2st(features, labels, seed=seed)
        entry = {"all": cr.accuracy_interval(correct), "n_crops": int(len(labels))}
        for drive in sorted(set(drives.tolist())):
            entry[drive] = cr.accuracy_interval(correct[:, both_drives == drive])
        out[level] = entry
    halves = np.random.default_rng(seed).permutation(len(real)) % 2  # a control: real vs real, random halves
    correct = cr.c2st(real_features, halves, seed=seed)
    out["control"] = {"all": cr.accuracy_interval(correct), "n_crops": int(len(real))}
    return out


def grid_picture(path: Path, boxes: list[cr.CarBox], real: np.ndarray, inserted: dict[str, np.ndarray]) -> None:
    """A grid, a few boxes per drive: the real crop, then the inserted car at each level."""
    rows = []
    for drive in cr.DRIVES:
        for i in [i for i, b in enumerate(boxes) if b.drive == drive][:GRID_PER_DRIVE]:
            rows.append(np.hstack([real[i]] + [inserted[level][i] for level in cr.LEVELS]))
    image = cv2.resize(np.vstack(rows), None, fx=GRID_SCALE, fy=GRID_SCALE, interpolation=cv2.INTER_NEAREST)
    header = np.full((18, image.shape[1]), 255, dtype=np.uint8)
    cell_px = cr.CROP_SIZE_PX[0] * GRID_SCALE
    for c, name in enumerate(("real", *cr.LEVELS)):
        cv2.putText(header, name, (c * cell_px + 3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 0, 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack([header, image]))


def _cell(acc: tuple[float, float, float]) -> str:
    return f"{100 * acc[0]:.0f} % [{100 * acc[1]:.0f}, {100 * acc[2]:.0f}]"


def _interval(value: tuple[float, float, float] | int) -> dict[str, float] | int:
    """An (accuracy, low, high) triple as a record (counts as they are)."""
    if isinstance(value, int):
        return value
    return {"accuracy": round(value[0], 4), "low_95": round(value[1], 4), "high_95": round(value[2], 4)}


def _table(results: dict, drives: list[str], counts: dict[str, int]) -> list[str]:
    """The markdown table of one resolution's results: a row per level, then the real-vs-real control."""
    header = "| level | all drives | " + " | ".join(f"{d} ({counts[d]})" for d in drives) + " |"
    rows = [
        f"| {LEVEL_NAMES[level]} | {_cell(results[level]['all'])} | "
        + " | ".join(_cell(results[level][d]) for d in drives)
        + " |"
        for level in ROWS
    ]
    control = results["control"]
    return [
        header,
        "|" + "---|" * (2 + len(drives)),
        *rows,
        f"| control: real vs real (random halves of the {control['n_crops']} real crops) | {_cell(control['all'])} |"
        + " |" * len(drives),
    ]


def report(args: argparse.Namespace, boxes: list[cr.CarBox], results: dict, seconds: float, load: str) -> None:
    """Write the markdown tables (one per resolution) and the raw JSON."""
    drives = [d for d in cr.DRIVES if any(b.drive == d for b in boxes)]
    counts = {d: sum(b.drive == d for b in boxes) for d in drives}
    when = measured_now()
    lines = [
        "# Inserted cars against the recording's own cars (C2ST)",
        "",
        f"- machine: {when['machine']}",
        f"- date: {when['date_utc']} UTC; took {seconds:.0f} s",
        f"- command: `python benchmarks/bench_car_realism.py --seed {args.seed}`",
        f"- load: before {load}; after {' / '.join(str(x) for x in when['load_average_1_5_15_min'])}",
        f"- data: {len(boxes)} hand-marked car boxes ({sum(b.motion == 'parked' for b in boxes)} parked) in frames of "
        f"the real KITTI drives ({', '.join(f'{d}: {counts[d]}' for d in drives)}), "
        "`benchmarks/data/real_car_boxes.json`",
        "",
        "Accuracy of a logistic regression (HOG of 64 x 40 gray crops) telling a real car from a library car inserted "
        "at the same place, out of fold (stratified 5-fold, repeated 5 times), with its Wilson 95 % interval over the "
        "crops; 50 % = indistinguishable. Drive columns: the same predictions counted over that drive's crops "
        "(boxes in brackets). Levels add one part each; the camera-look level is what the simulator draws. The row "
        "after it draws that car from behind whatever side the real car shows, as the benchmark did before the boxes "
        "carried their views.",
        "",
        "At the recording's resolution (about 1240 x 375):",
        "",
        *_table(results["recording"], drives, counts),
        "",
        f"At a world's resolution (frames reduced to {WORLD_WIDTH_PX} px wide, `build-world`'s default, before "
        "cropping):",
        "",
        *_table(results["world"], drives, counts),
        "",
        f"At a world's resolution, drawn there (the car drawn into the frame reduced to {WORLD_WIDTH_PX} px, as the "
        "simulator draws it: no supersampling of its edges):",
        "",
        *_table(results["world_drawn"], drives, counts),
        "",
        "The inserted car stands on a flat road 1.65 m below the camera, its near end on the box's bottom row, seen "
        "from the side the real car shows (each box's hand-judged view: "
        f"{', '.join(f'{v} {sum(b.view == v for b in boxes)}' for v in cr.VIEW_YAW_RAD)}). Crops at the "
        "recording's resolution: `car_realism.png` (real, then the levels). In the second table the car is drawn at "
        "the recording's resolution and reduced with the frame; in the third it is drawn at the world's, as the "
        "simulator draws it.",
    ]
    raw = {
        "boxes": len(boxes),
        "boxes_per_drive": counts,
        "seed": args.seed,
        "seconds": round(seconds, 1),
        "world_width_px": WORLD_WIDTH_PX,
        "accuracy": {
            resolution: {level: {k: _interval(v) for k, v in r.items()} for level, r in per_level.items()}
            for resolution, per_level in results.items()
        },
    }
    write_markdown(args.out, lines, raw)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--boxes", type=Path, default=BOXES, help="hand-marked boxes (JSON)")
    parser.add_argument("--real", type=Path, default=REAL, help="folder of the real drives (shared/data/real)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the cars' paints and the folds")
    parser.add_argument("--out", type=Path, default=RESULTS, help="markdown report (JSON and PNG beside it)")
    args = parser.parse_args()
    try:
        boxes = cr.load_boxes(args.boxes)
        if not args.real.is_dir():
            raise FileNotFoundError(f"no real-data folder {args.real}: pass --real")
        load = " / ".join(f"{x:.2f}" for x in os.getloadavg())
        start = time.perf_counter()
        crops = {name: crops_of(boxes, args.real, args.seed, *where) for name, where in RESOLUTIONS.items()}
    except (ValueError, FileNotFoundError, OSError) as err:
        print(f"bench_car_realism: {err}", file=sys.stderr)
        return 2
    drives = np.array([b.drive for b in boxes])
    results = {name: measure(real, inserted, drives, args.seed) for name, (real, inserted) in crops.items()}
    seconds = time.perf_counter() - start
    grid_picture(args.out.with_suffix(".png"), boxes, *crops["recording"])
    report(args, boxes, results, seconds, load)
    return 0


if __name__ == "__main__":
    sys.exit(main())
