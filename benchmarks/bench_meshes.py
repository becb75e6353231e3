"""Benchmark of the vehicle library: build time per vehicle, triangles per level of detail, and raster time of one
car in the policy's 160x64 view for each level of detail (back faces culled, as the simulator draws vehicles).

    .venv/bin/python benchmarks/bench_meshes.py            # full run (under a minute on a quiet 2-core machine)
    .venv/bin/python benchmarks/bench_meshes.py --quick    # smoke run

Writes benchmarks/results/meshes.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch
from _lib.report import write_markdown

from drivesim.sim import geometry as g
from drivesim.sim.raster import Rasterizer
from drivesim.sim.vehicles import BODY_TYPES, build_vehicle_meshes, sample_paint, sample_vehicle_shape

RESULTS = Path(__file__).resolve().parent / "results" / "meshes.md"
VIEW_W, VIEW_H = 160, 64


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few repetitions (smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    reps = 3 if args.quick else 20
    rng = np.random.default_rng(0)
    K = g.intrinsics_from_hfov(VIEW_W, VIEW_H, np.radians(60.0))
    # the car 10 m ahead, slightly to the left, seen by a camera 1.6 m up (a front car in an overtake)
    T = g.invert(g.camera_mount(0.0, 0.0, 1.6, pitch_down_rad=0.05)) @ g.pose_2d(10.0, 1.5, 0.1)
    rows = []
    for body_type in BODY_TYPES:
        shape = sample_vehicle_shape(rng, body_type)
        paint = sample_paint(rng)
        row = {"body_type": body_type}
        for detail in ("full", "light"):
            times = []
            for _ in range(reps):
                tic = time.perf_counter()
                meshes = build_vehicle_meshes(shape, paint, detail)
                times.append(time.perf_counter() - tic)
            row[f"{detail}_build_ms"] = 1e3 * statistics.median(times)
            row[f"{detail}_triangles"] = sum(m.triangle_count for m in meshes)
            raster = Rasterizer(VIEW_W, VIEW_H, cull_back_faces=True)
            packed = raster.pack(meshes)
            raster.render(packed, T, K)  # warm-up
            times = []
            for _ in range(reps):
                tic = time.perf_counter()
                result = raster.render(packed, T, K)
                times.append(time.perf_counter() - tic)
            row[f"{detail}_raster_ms"] = 1e3 * statistics.median(times)
            row[f"{detail}_pixels"] = int(result.mask.sum())
        rows.append(row)
    load = os.getloadavg()[0]
    lines = [
        "# Vehicle library (`benchmarks/bench_meshes.py`)",
        "",
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, torch {torch.__version__}, 1 thread, CPU, load average "
        f"{load:.1f} (2 cores){', --quick' if args.quick else ''}. Median of {reps} repetitions.",
        "",
        f"Raster: one car 10 m ahead in the policy's {VIEW_W}x{VIEW_H} view (60° hfov), back faces culled, "
        "packed once.",
        "",
        "| body type | full: triangles | full: build ms | full: raster ms | light: triangles | light: build ms "
        "| light: raster ms | car pixels (full / light) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['body_type']} | {r['full_triangles']} | {r['full_build_ms']:.1f} | {r['full_raster_ms']:.2f} "
            f"| {r['light_triangles']} | {r['light_build_ms']:.1f} | {r['light_raster_ms']:.2f} "
            f"| {r['full_pixels']} / {r['light_pixels']} |"
        )
    raw = {"quick": args.quick, "repetitions": reps, "view_px": [VIEW_W, VIEW_H], "torch": torch.__version__}
    write_markdown(RESULTS, [*lines, ""], raw | {"rows": rows})


if __name__ == "__main__":
    main()
