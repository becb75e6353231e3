"""Benchmark of `drivesim synth`: world size, seconds per rendered 960x600 frame, and the demo command end to end.

    .venv/bin/python benchmarks/bench_synth.py            # full run (about 1-2 minutes on a quiet 2-core machine)
    .venv/bin/python benchmarks/bench_synth.py --quick    # smoke run

Writes benchmarks/results/synth.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line
from drivesim.stages.synth.config import SynthConfig
from drivesim.stages.synth.drive import Trajectory
from drivesim.stages.synth.synthesize import resolve_config, single_torch_thread, synthesize
from drivesim.stages.synth.world import SEMANTIC_IDS, SynthWorld

RESULTS = Path(__file__).resolve().parent / "results" / "synth.md"


def bench_world(cfg: SynthConfig) -> dict[str, float]:
    """World build time and triangle counts."""
    tic = time.perf_counter()
    world = SynthWorld.from_seed(cfg.seed, cfg)
    build_s = time.perf_counter() - tic
    by_kind = {name: 0 for name in SEMANTIC_IDS}
    for mesh in world.meshes:
        kind = next(k for k, v in SEMANTIC_IDS.items() if v == mesh.object_id)
        by_kind[kind] += mesh.triangle_count
    return {
        "world": world,
        "build_s": build_s,
        "triangles": world.triangle_count,
        **{f"tri_{k}": v for k, v in by_kind.items()},
    }


def bench_frames(world: SynthWorld, cfg: SynthConfig, n_frames: int) -> dict[str, float]:
    """Wall and CPU seconds per 960x600 frame (colour + depth), over frames along the demo drive."""
    traj = Trajectory(world.path, cfg.drive)
    cam = world.camera
    times = np.linspace(0.0, cfg.drive.duration_s, n_frames, endpoint=False)
    walls, cpus = [], []
    with single_torch_thread():
        world.render(traj.vehicle_pose(0.0) @ cam.T_vehicle_camera, cam.K, cam.width_px, cam.height_px)  # warm-up
        for t in times:
            T = traj.vehicle_pose(float(t)) @ cam.T_vehicle_camera
            w0, c0 = time.perf_counter(), time.process_time()
            world.render(T, cam.K, cam.width_px, cam.height_px)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
    return {"frame_wall_s": statistics.median(walls), "frame_cpu_s": statistics.median(cpus), "frames": n_frames}


def bench_demo(duration_s: float) -> dict[str, float]:
    """The `make demo` synth call (seed 0, 10 Hz, 960x600, with previews), timed end to end in this process."""
    cfg = SynthConfig.model_validate({"seed": 0, "drive": {"duration_s": duration_s}})
    with tempfile.TemporaryDirectory() as tmp:
        w0, c0 = time.perf_counter(), time.process_time()
        result = synthesize(cfg, Path(tmp) / "demo.mcap", preview=True)
        return {
            "demo_wall_s": time.perf_counter() - w0,
            "demo_cpu_s": time.process_time() - c0,
            "demo_frames": result.frame_count,
            "demo_render_s": result.render_s,
            "demo_mb": result.size_bytes / 1e6,
            "demo_s": duration_s,
        }


def main() -> None:
    """Run the benchmark and write its markdown table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: 3 frames and a 1 s demo")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    cfg = resolve_config(SynthConfig())
    w = bench_world(cfg)
    f = bench_frames(w["world"], cfg, 3 if args.quick else 20)
    d = bench_demo(1.0 if args.quick else 8.0)
    cmd = "python benchmarks/bench_synth.py" + (" --quick" if args.quick else "")
    tri = ", ".join(f"{k[4:]} {w[k]}" for k in w if k.startswith("tri_"))
    lines = [
        "# synth: procedural drive with ground truth",
        "",
        f"Machine: {machine_line()} (load average {load:.1f} at start). Date: "
        f"{datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}. Reproduce: `{cmd}`.",
        "",
        "| measure | value |",
        "|---|---|",
        f"| world triangles (seed 0, {w['world'].road.length_m:.0f} m of road) | {w['triangles']} ({tri}) |",
        f"| world build (road, scenery, textures, meshes) | {w['build_s']:.2f} s |",
        f"| render 960x600 colour + depth, median of {f['frames']} frames (1 torch thread) | "
        f"{f['frame_wall_s']:.3f} s wall, {f['frame_cpu_s']:.3f} s CPU |",
        f"| demo synth: {d['demo_s']:g} s drive, {d['demo_frames']} frames at 10 Hz, MCAP + previews | "
        f"{d['demo_wall_s']:.1f} s wall, {d['demo_cpu_s']:.1f} s CPU (rendering {d['demo_render_s']:.1f} s) |",
        f"| demo recording size | {d['demo_mb']:.1f} MB |",
        "",
        "The demo row is the `make demo` synth call (`drivesim synth --seed 0 --duration-s 8 --preview`) run "
        "in-process; the CLI adds about 2 s of imports.",
        "",
    ]
    world = {k: v for k, v in w.items() if k != "world"} | {"road_length_m": w["world"].road.length_m}
    raw = {"command": cmd, "load_average_start": load, "world": world, "frames": f, "demo": d}
    write_markdown(RESULTS, lines, raw)


if __name__ == "__main__":
    main()
