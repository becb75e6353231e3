"""The learned harmonizer against the statistical one: trained on the synthetic world's true look of inserted cars,
measured on held-out synthetic seeds (car PSNR / SSIM against the truth), on the real drives' C2ST, and in time.

Run from the repository root:
    .venv/bin/python benchmarks/bench_harmonizer.py [--world WS/world] [--write-model sim/models/harmonizer.onnx]
Trains on `--train-seeds`, measures on `--test-seeds` (pairs kept in `--cache`), writes `results/harmonizer.{md,json}`
and `results/harmonizer.png` (per row: the true look, none, statistical, learned). `--write-model` also writes the
trained ONNX there: `sim/models/harmonizer.onnx` is the one drivesim ships, made by this script's defaults.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _lib.report import measured_now, write_markdown
from bench_car_realism import BOXES, REAL, WORLD_WIDTH_PX, crops_of, measure

from drivesim.bench import car_realism as cr
from drivesim.bench import harmonizer_training as ht
from drivesim.bench.sim_steps import make_env, time_env_steps
from drivesim.sim.harmonize import Harmonizer, LearnedHarmonizer, StatisticalHarmonizer, harmonize_view_uint8_

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "harmonizer.md"
C2ST_LEVELS = ("shadow", "harmonization", "camera")


def c2st_rows(harmonizers: dict[str, Harmonizer], seed: int) -> dict[str, dict]:
    """Per harmonizer, the C2ST's accuracy at the contact-shadow, harmonization and camera-look levels, with the car
    drawn at a world's 320 px as the simulator draws it."""
    boxes = cr.load_boxes(BOXES)
    drives = np.array([b.drive for b in boxes])
    rows = {}
    for name, harmonizer in harmonizers.items():
        real, inserted = crops_of(boxes, REAL, seed, WORLD_WIDTH_PX, True, harmonizer)
        measured = measure(real, inserted, drives, seed)
        rows[name] = {level: measured[level]["all"] for level in C2ST_LEVELS}
    return rows


def microseconds_per_view(harmonizer: Harmonizer, pairs: dict[str, np.ndarray], rounds: int = 3) -> float:
    """Median time of harmonizing one uint8 view in place (the simulator's CPU path) over the pairs' views."""
    times = []
    for _ in range(rounds):
        for view, mask in zip(pairs["composite"], pairs["sim_mask"], strict=True):
            work = view.copy()
            start = time.perf_counter()
            harmonize_view_uint8_(harmonizer, work, mask)
            times.append(time.perf_counter() - start)
    return 1e6 * float(np.median(times))


CAR_PARTS = ("raster", "composite", "lighting", "harmonize")


def step_costs(world: str, learned: LearnedHarmonizer, steps: int, rounds: int) -> dict[str, dict[str, float]]:
    """Per harmonizer (the statistical one and `learned`), over `rounds` alternating rounds of `steps` car-drawn
    expert overtake steps on `world` (one thread): the median car-drawn step and the mean ms of the car's parts
    (raster, composite, lighting, harmonize), each the median over the rounds."""
    per: dict[str, list[dict[str, float]]] = {"statistical": [], "learned": []}
    for _ in range(rounds):
        for name in per:
            env = make_env("overtake", world, None, "eval")
            env.reset(seed=0)  # the simulator is made on the first reset
            if name == "learned":  # the model just trained, which may not be the one drivesim ships yet
                env.unwrapped.sim.renderer.harmonizer = learned
            times = time_env_steps(env, steps, seed=0, car_drawn_steps=steps, max_steps=40 * steps)
            parts = times.mean_part_ms(True)
            per[name].append({"step_ms": times.median_ms(True), "car_ms": sum(parts[k] for k in CAR_PARTS), **parts})
            env.close()
    return {name: {k: float(np.median([r[k] for r in rows])) for k in rows[0]} for name, rows in per.items()}


def _pct(acc: tuple[float, float, float]) -> str:
    return f"{100 * acc[0]:.0f} % [{100 * acc[1]:.0f}, {100 * acc[2]:.0f}]"


def _step_lines(costs: dict | None, args: argparse.Namespace) -> list[str]:
    if not costs:
        return []
    ratio = costs["learned"]["car_ms"] / costs["statistical"]["car_ms"]
    return [
        f"A car-drawn overtake step on `{Path(args.world).parent.name}`'s world (expert actions, one thread; "
        f"{args.step_rounds} alternating rounds of {args.steps_timed} car-drawn steps, medians over the rounds): the "
        f"car's share is raster + composite + lighting + harmonize; learned / statistical x{ratio:.2f} (target 1.5).",
        "",
        "| harmonizer | car-drawn step ms (median) | car's share ms | harmonize ms |",
        "|---|---:|---:|---:|",
        *(f"| {name} | {c['step_ms']:.2f} | {c['car_ms']:.3f} | {c['harmonize']:.3f} |" for name, c in costs.items()),
        "",
    ]


def report(args: argparse.Namespace, result: dict) -> None:
    """Write the markdown report and the raw JSON."""
    when = measured_now()
    synthetic, c2st, speed = result["synthetic_test"], result["c2st_320_drawn"], result["us_per_view"]
    lines = [
        "# The learned harmonizer against the statistical one",
        "",
        f"- machine: {when['machine']}",
        f"- date: {when['date_utc']} UTC; took {result['seconds']:.0f} s",
        f"- command: `python benchmarks/bench_harmonizer.py --train-seeds {args.train_seeds} --test-seeds "
        f"{args.test_seeds} --samples {args.samples} --steps {args.steps}"
        + (f" --world {args.world}" if args.world else "")
        + "`",
        f"- load: before {' / '.join(f'{x:.2f}' for x in result['load_before'])}; after "
        f"{' / '.join(str(x) for x in when['load_average_1_5_15_min'])}",
        "",
        f"Trained on {result['train_views']} views of synthetic seeds {args.train_seeds}, measured on "
        f"{result['test_views']} views of seeds {args.test_seeds} (library cars 6-22 m ahead, up to 3.5 m to the side, "
        "the ego up to 1 m off its lane; the simulator's 160 x 64 view with lighting and contact shadow, before the "
        "camera's look). Car PSNR / SSIM over the true car mask against the synthetic world's own render of the "
        "same car in the same scene:",
        "",
        "| harmonizer | car PSNR dB (test) | car SSIM (test) | car PSNR dB (train) | us per view |",
        "|---|---:|---:|---:|---:|",
        *(
            f"| {name} | {synthetic[name]['psnr_db']:.2f} | {synthetic[name]['ssim']:.3f} | "
            f"{result['synthetic_train'][name]['psnr_db']:.2f} | {f'{speed[name]:.0f}' if name in speed else '-'} |"
            for name in ("none", "statistical", "learned")
        ),
        "",
        f"ONNX (onnxruntime, the shipped uint8 graph, on the car's box) against torch on the whole view: largest "
        f"difference {result['onnx_max_abs_diff']} grey levels over 8 test views.",
        "",
        f"C2ST on the real drives ({result['boxes']} hand-marked boxes; `bench_car_realism.py`'s protocol, the car "
        f"drawn at a world's {WORLD_WIDTH_PX} px), accuracy with its 95 % interval (50 % = indistinguishable):",
        "",
        "| harmonizer | + contact shadow (none) | + harmonization | + camera look (what the simulator draws) |",
        "|---|---|---|---|",
        *(f"| {name} | " + " | ".join(_pct(c2st[name][level]) for level in C2ST_LEVELS) + " |" for name in c2st),
        "",
        *_step_lines(result.get("step_costs"), args),
        "Pictures (`harmonizer.png`): test views around the car, per row the true look, then none, statistical, "
        "learned (each crop scaled to 96 x 64, the grid 2x, no smoothing). Time: one uint8 view harmonized in place "
        "as the simulator does it (the learned one on the car's box and ring), median.",
    ]
    write_markdown(args.out, lines, {**result, "measured": when})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train-seeds", default="1-10", help="synthetic seeds trained on ('1-10' or '1,4,7')")
    parser.add_argument("--test-seeds", default="11-13", help="synthetic seeds measured on")
    parser.add_argument("--samples", type=int, default=40, help="car placements tried per seed")
    parser.add_argument("--steps", type=int, default=800, help="training steps (minibatches of 32 views)")
    parser.add_argument("--cache", type=Path, default=None, help="folder keeping the pairs (default: a temporary one)")
    parser.add_argument("--write-model", type=Path, default=None, help="also write the trained ONNX here")
    parser.add_argument("--world", default=None, help="a world folder: also time car-drawn steps with each")
    parser.add_argument("--steps-timed", type=int, default=300, help="car-drawn steps per round (with --world)")
    parser.add_argument("--step-rounds", type=int, default=3, help="alternating rounds (with --world)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="markdown report (JSON and PNG beside it)")
    args = parser.parse_args()
    if not REAL.is_dir():
        print(f"bench_harmonizer: no real-data folder {REAL} (the C2ST needs ../shared)", file=sys.stderr)
        return 2
    torch.set_num_threads(1)  # beside other work a second thread mostly waits
    started, load_before = time.perf_counter(), os.getloadavg()
    cache = args.cache or Path(tempfile.mkdtemp(prefix="harmonizer-"))
    cache.mkdir(parents=True, exist_ok=True)
    try:
        train_pairs = ht.pairs_for(ht.parse_seeds(args.train_seeds), args.samples, cache)
        test_pairs = ht.pairs_for(ht.parse_seeds(args.test_seeds), args.samples, cache)
        model = ht.train(train_pairs, args.steps, seed=0)
        onnx_path = cache / "harmonizer.onnx"
        onnx_error = ht.export_onnx(model, onnx_path, test_pairs["composite"][:8], test_pairs["sim_mask"][:8])
        learned = LearnedHarmonizer(onnx_path)
        harmonizers = {"none": None, "statistical": StatisticalHarmonizer(), "learned": learned}
        result = {
            "train_views": len(train_pairs["composite"]),
            "test_views": len(test_pairs["composite"]),
            "onnx_max_abs_diff": onnx_error,
            "synthetic_test": ht.car_scores(test_pairs, harmonizers),
            "synthetic_train": ht.car_scores(train_pairs, harmonizers),
            "us_per_view": {name: microseconds_per_view(h, test_pairs) for name, h in harmonizers.items() if h},
            "c2st_320_drawn": c2st_rows({"statistical": StatisticalHarmonizer(), "learned": learned}, seed=0),
            "boxes": len(cr.load_boxes(BOXES)),
            "load_before": load_before,
        }
        if args.world is not None:
            result["step_costs"] = step_costs(args.world, learned, args.steps_timed, args.step_rounds)
        ht.figure(test_pairs, harmonizers, args.out.with_suffix(".png"))
        if args.write_model is not None:
            args.write_model.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(onnx_path, args.write_model)
    finally:
        if args.cache is None:
            shutil.rmtree(cache, ignore_errors=True)
    result["seconds"] = time.perf_counter() - started
    report(args, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
