"""Per-frame depth speed, memory and accuracy at the working resolution (960x600) on a synthetic drive.

    python benchmarks/bench_depth.py            # 24 frames, writes benchmarks/results/depth.md
    python benchmarks/bench_depth.py --quick    # 8 frames, smoke run
    python benchmarks/bench_depth.py --real     # real drives: the "Real drives" section of depth.md only

The drive (frames, ground-truth depth, poses) is rendered once into a temporary folder; each depth method then runs
in its own process on memory-mapped frames, streaming into a memory-mapped output as `drivesim preprocess` does, so
its peak RSS is its own. Seconds per 1000 frames are extrapolated from the measured frames (the cost per frame does
not depend on the drive's length). AbsRel and delta<1.25 are over frames with every matching neighbour.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _lib.report import update_json, write_markdown

from drivesim.bench.machine import machine_line

RESULTS = Path(__file__).resolve().parent / "results" / "depth.md"
WIDTH_PX, HEIGHT_PX = 960, 600


def _render(folder: Path, n_frames: int, seed: int) -> None:
    from drivesim.bench.fidelity import render_drive

    drive = render_drive(seed, n_frames, WIDTH_PX, HEIGHT_PX)
    np.save(folder / "frames.npy", drive.rgb)
    np.save(folder / "gt_depth.npy", drive.depth_m)
    np.savez(
        folder / "camera.npz", K=drive.K, T_world_camera=drive.T_world_camera, T_vehicle_camera=drive.T_vehicle_camera
    )


def _peak_rss_mb() -> float:
    """This process's peak resident memory (MB)."""
    # VmHWM belongs to this process's own address space; ru_maxrss would carry the parent's peak across exec.
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _worker(folder: Path, method: str, overrides: list[str]) -> None:
    """Run one method on the rendered drive; print a JSON line with its timing and peak RSS."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.preprocess.config import DepthConfig
    from drivesim.stages.preprocess.depth import estimate_depth

    cfg = load_config(DepthConfig, overrides=[f"method={method}", *overrides])
    frames = np.load(folder / "frames.npy", mmap_mode="r")
    cam = np.load(folder / "camera.npz")
    out = np.lib.format.open_memmap(folder / f"depth_{method}.npy", mode="w+", dtype=np.float32, shape=frames.shape[:3])
    start = time.perf_counter()
    summary = estimate_depth(frames, cam["K"], cam["T_world_camera"], cam["T_vehicle_camera"], None, cfg, out)
    seconds = time.perf_counter() - start
    out.flush()
    peak_rss_mb = _peak_rss_mb()
    print(json.dumps({"seconds": seconds, "peak_rss_mb": peak_rss_mb, "summary": summary}))


REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
REAL_DRIVES = {
    "KITTI raw 0001": REAL / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync",
    "KITTI odometry snippet": REAL / "kitti_odometry_straight",
}
REAL_SECTION = "## Real drives"


def _real_workspace(recording: Path, root: Path) -> Path:
    """A workspace with `drivesim ingest` and `drivesim preprocess` (plane: only the fused poses are used) done."""
    ws = root / recording.name
    for args in (["ingest", str(recording)], ["preprocess", "--set", "depth.method=plane"]):
        subprocess.run([str(Path(sys.executable).with_name("drivesim")), "-w", str(ws), *args], check=True,
                       capture_output=True, text=True)  # fmt: skip
    return ws


def _real_section(methods: tuple[str, ...], overrides: list[str]) -> tuple[list[str], dict]:
    """Every real drive x method: forward views (frame i warped to frame i + k), the stereo snippet's lateral view;
    the markdown section and its raw figures."""
    from drivesim.bench.fidelity import forward_view_rows, load_real_drive, real_depths
    from drivesim.bench.stereo import REFERENCE, run_stereo_bench
    from drivesim.pipeline.config import load_config
    from drivesim.stages.preprocess.config import DepthConfig

    cfg = load_config(DepthConfig, overrides=overrides)
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-depth-real-") as tmp:
        for name, recording in REAL_DRIVES.items():
            drive = load_real_drive(_real_workspace(recording, Path(tmp)), name)
            depths, seconds = real_depths(drive, methods, cfg)
            for r in forward_view_rows(drive, depths):
                rows.append((name, f"forward, k = {r['gap_frames']}", r["depth"], r, seconds[r["depth"]]))
            print(f"{name}: done", flush=True)
    stereo = run_stereo_bench(REAL / "kitti_odometry_stereo", methods, depth_config=cfg)
    for r in stereo.rows[1:]:
        method = "stereo (SGBM on the true pair)" if r.name == REFERENCE else r.name
        metrics = {"psnr_db": r.psnr_db, "ssim": r.ssim, "filled_fraction": r.filled_fraction}
        rows.append(
            ("KITTI odometry stereo snippet", "lateral 0.537 m (right camera)", method, metrics, r.seconds_per_frame)
        )
    lines = [
        REAL_SECTION,
        "",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}; machine: {machine_line()}; load (shared "
        f"machine, s / frame vary with it): `{uptime}` at the start",
        f"- command: `python benchmarks/bench_depth.py --real{''.join(f' --set {o}' for o in overrides)}`",
        "- forward: each method's depth of frame i warps frame i to the pose of frame i + k, compared with the "
        "recorded "
        "frame i + k (every 2nd source frame, 3 frames from the ends); lateral: the left frame warped into the right "
        "camera, compared with the recorded right image (`drivesim bench stereo`). Depth at 640 px wide (the trace), "
        "measured at 320 px (the world); PSNR and SSIM over the pixels the warp fills",
        "",
        "| drive | view | depth | PSNR dB | SSIM | filled | s / frame |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for drive, view, method, m, sec in rows:
        sec_text = "" if sec is None else f"{sec:.2f}"
        lines.append(f"| {drive} | {view} | {method} | {m['psnr_db']:.2f} | {m['ssim']:.3f} | "
                     f"{m['filled_fraction']:.3f} | {sec_text} |")  # fmt: skip
    keys = ("drive", "view", "depth", "metrics", "seconds_per_frame")
    return lines, {
        "load_before": uptime,
        "overrides": overrides,
        "rows": [dict(zip(keys, r, strict=True)) for r in rows],
    }


def _write_real(output: Path, methods: tuple[str, ...], overrides: list[str]) -> None:
    section, raw = _real_section(methods, overrides)
    old = output.read_text() if output.is_file() else "# Per-frame depth: speed, memory, accuracy\n"
    kept = old.split(REAL_SECTION)[0].rstrip() + "\n\n"
    output.write_text(kept + "\n".join(section) + "\n")
    update_json(output.with_suffix(".json"), "real_drives", raw)
    print("\n".join(section))
    print(f"wrote {output}")


def main() -> None:
    """Run the benchmark (or, with the hidden worker flags, one measuring subprocess) and write its results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 frames: a smoke run")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="depth config override for mvs")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--real", action="store_true", help="the real drives' section only")
    parser.add_argument("--methods", default="plane,mvs", help="depth methods of the real drives' section")
    parser.add_argument("--worker", nargs=2, metavar=("FOLDER", "METHOD"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        _worker(Path(args.worker[0]), args.worker[1], args.overrides)
        return
    if args.real:
        _write_real(args.output, tuple(args.methods.split(",")), args.overrides)
        return

    n_frames = 8 if args.quick else args.frames
    load_1min = os.getloadavg()[0]
    rows = _measure_methods(n_frames, args.seed, args.overrides)

    command = "python benchmarks/bench_depth.py" + (" --quick" if args.quick else f" --frames {n_frames}")
    command += "".join(f" --set {o}" for o in args.overrides)
    lines = [
        "# Per-frame depth: speed, memory, accuracy",
        "",
        f"- machine: {machine_line()}, torch CPU",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}; load average at the start {load_1min:.1f} "
        "(timings on a shared machine vary up to 3x with its load)",
        f"- command: `{command}`",
        f"- input: synthetic drive (seed {args.seed}), {n_frames} frames at {WIDTH_PX}x{HEIGHT_PX}, 10 Hz, ~10 m/s; "
        "accuracy over frames with all neighbours, pixels with ground truth < 80 m",
        "",
        "| method | s / 1000 frames | min / 1000 frames | peak RSS (MB) | AbsRel | δ<1.25 |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method, per_1000_s, rss, metrics, _ in rows:
        lines.append(
            f"| {method} | {per_1000_s:.0f} | {per_1000_s / 60:.1f} | {rss:.0f} | {metrics['abs_rel']:.3f} | "
            f"{metrics['delta1']:.3f} |"
        )
    mvs_summary = rows[-1][4]
    fractions = ", ".join(
        f"{k.removesuffix('_fraction')} {v:.2f}"
        for k, v in mvs_summary.items()
        if k.endswith("_fraction") and k != "far_fraction"
    )
    lines += [
        "",
        f"mvs matching resolution {mvs_summary.get('matching_resolution_px')}; where its depth came from: {fractions}.",
        "Aims: plane under 1 min and mvs under 15 min per 1000 frames; mvs AbsRel at most 0.10.",
        "",
    ]
    keys = ("method", "seconds_per_1000_frames", "peak_rss_mb", "metrics", "summary")
    raw = {"command": command, "load_average_start": load_1min, "rows": [dict(zip(keys, r, strict=True)) for r in rows]}
    args.output.with_suffix(".json").unlink(missing_ok=True)  # the real drives' part is rewritten with the file
    write_markdown(args.output, lines)
    update_json(args.output.with_suffix(".json"), "synthetic", raw)


def _measure_methods(n_frames: int, seed: int, overrides_mvs: list[str]) -> list[tuple]:
    """(method, s per 1000 frames, peak RSS MB, depth metrics, stage summary) of plane and mvs depth, each run in a
    subprocess on a synthetic drive of `n_frames` rendered with its ground truth."""
    from drivesim.bench.fidelity import depth_metrics

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-depth-") as tmp:
        folder = Path(tmp)
        start = time.perf_counter()
        _render(folder, n_frames, seed)
        print(
            f"rendered {n_frames} frames at {WIDTH_PX}x{HEIGHT_PX} in {time.perf_counter() - start:.0f} s", flush=True
        )
        gt = np.load(folder / "gt_depth.npy", mmap_mode="r")
        for method in ("plane", "mvs"):
            overrides = overrides_mvs if method == "mvs" else []
            cmd = [sys.executable, __file__, "--worker", str(folder), method]
            cmd += [a for o in overrides for a in ("--set", o)]
            result = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
            depth = np.load(folder / f"depth_{method}.npy", mmap_mode="r")
            evaluated = slice(3, n_frames - 3) if n_frames > 6 else slice(0, n_frames)
            metrics = depth_metrics(np.asarray(depth[evaluated]), np.asarray(gt[evaluated]), 80.0)
            per_1000_s = result["seconds"] / n_frames * 1000.0
            rows.append((method, per_1000_s, result["peak_rss_mb"], metrics, result["summary"]))
            print(
                f"{method}: {per_1000_s / 60:.1f} min / 1000 frames, peak RSS {result['peak_rss_mb']:.0f} MB, "
                f"AbsRel {metrics['abs_rel']:.3f}, delta1 {metrics['delta1']:.3f}",
                flush=True,
            )
    return rows


if __name__ == "__main__":
    main()
