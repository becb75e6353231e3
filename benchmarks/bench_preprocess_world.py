"""`drivesim preprocess` and `drivesim build-world`: seconds per 1000 frames at 960x600 and peak memory.

Set-up (not timed): a synthetic drive (seed 0, the synth API) rendered at 480x300 to keep the set-up short, then
`drivesim ingest --set image.width_px=960 --set image.upscale=true` so the trace's working resolution is 960x600.
The stages' cost depends on the resolution and the frame count, not on the pixels' content, so the upscaled frames
time the same as native 960x600 ones. The recording is cached in the system temp folder between runs.

Measured: each stage as the CLI runs it, in its own subprocess (wall time; peak RSS of that child from `os.wait4`,
the per-child form of getrusage(RUSAGE_CHILDREN).ru_maxrss), for each depth method at two frame counts
(`--set frames.stop=N`). Seconds per 1000 frames = the marginal cost (difference of the two runs / difference of
the frame counts x 1000), so the fixed start-up (imports, pose fusion set-up) does not inflate the extrapolation;
the fixed part is reported beside it. build-world runs after each preprocess (its point cloud and bird's-eye PNG
included). Runs with plane depth are repeated 3 times and the fastest kept.

Usage: python benchmarks/bench_preprocess_world.py [--quick]   (writes benchmarks/results/preprocess_world.md)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "preprocess_world.md"
FRAME_RATE_HZ = 10.0
RENDER_OVERRIDES = [
    "seed=0",
    "camera.width_px=480",
    "camera.height_px=300",
    "world.scenery.view_distance_m=80",
]
INGEST_OVERRIDES = ["image.width_px=960", "image.upscale=true"]
# Cheap runs are repeated and the fastest kept (the machine is shared); mvs runs are long enough to be steady.
REPEATS = {"plane": 3, "mvs": 1}


@dataclass
class Run:
    """One measured command: wall seconds and the child's peak resident memory."""

    seconds: float
    peak_rss_mb: float


def measure(args: list[str]) -> Run:
    """Run `args` in a subprocess; its wall time and peak RSS (ru_maxrss of exactly that child, via os.wait4)."""
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = proc.stdout.read() if proc.stdout is not None else b""
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}):\n{output.decode(errors='replace')}")
    return Run(seconds=seconds, peak_rss_mb=usage.ru_maxrss / 1024.0)  # Linux reports KiB


def drivesim(ws: Path, *args: str) -> list[str]:
    """The command line of `drivesim --workspace ws ARGS`."""
    return [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args]


def recording(frame_count: int) -> Path:
    """A cached synthetic recording with `frame_count` frames (rendered once per configuration)."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.synth.config import SynthConfig
    from drivesim.stages.synth.synthesize import synthesize

    overrides = [*RENDER_OVERRIDES, f"drive.duration_s={frame_count / FRAME_RATE_HZ}"]
    cfg = load_config(SynthConfig, overrides=overrides)
    digest = hashlib.sha256(json.dumps(cfg.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / "drivesim-bench-preprocess-world" / f"drive-{digest}.mcap"
    if not path.is_file():
        print(f"rendering a {frame_count}-frame synthetic drive (cached at {path}) ...", flush=True)
        synthesize(cfg, path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: few frames, results not representative")
    args = parser.parse_args()
    counts = {"plane": (5, 10), "mvs": (3, 6)} if args.quick else {"plane": (20, 40), "mvs": (8, 16)}
    total_frames = max(n for pair in counts.values() for n in pair)

    source = recording(total_frames)
    work = Path(tempfile.mkdtemp(prefix="drivesim-bench-pw-"))
    try:
        ws = work / "ws"
        measure(drivesim(ws, "ingest", str(source), *sum((["--set", o] for o in INGEST_OVERRIDES), [])))
        calibration = json.loads((ws / "trace" / "calibration.json").read_text())
        resolution = f"{calibration['width_px']}x{calibration['height_px']}"
        rows = []
        for method, (small, large) in counts.items():
            # stage -> frame count -> one (stage seconds, process run) per repeat
            samples: dict[str, dict[int, list[tuple[float, Run]]]] = {"preprocess": {}, "build-world": {}}
            summaries = {}
            for n in (small, large):
                sets = ["--set", f"depth.method={method}", "--set", f"frames.stop={n}"]
                for _ in range(REPEATS[method]):
                    pre = measure(drivesim(ws, "preprocess", *sets, "--force"))
                    world = measure(drivesim(ws, "build-world", "--force"))
                    summaries[n] = json.loads((ws / "preprocessed" / "manifest.json").read_text())["summary"]
                    world_s = json.loads((ws / "world" / "manifest.json").read_text())["summary"]["seconds"]
                    samples["preprocess"].setdefault(n, []).append((summaries[n]["seconds"], pre))
                    samples["build-world"].setdefault(n, []).append((world_s, world))
                print(f"{method} {n} frames measured", flush=True)
            for stage, by_n in samples.items():
                # fastest repeat for time (the machine is shared), largest for memory
                own = {n: min(s for s, _ in runs) for n, runs in by_n.items()}
                wall = {n: min(r.seconds for _, r in runs) for n, runs in by_n.items()}
                rss_mb = max(r.peak_rss_mb for runs in by_n.values() for _, r in runs)
                per_frame_s = max(own[large] - own[small], 0.0) / (large - small)
                fixed_s = own[small] - per_frame_s * small
                rows.append(
                    {
                        "stage": stage,
                        "method": method,
                        "small": small,
                        "large": large,
                        "wall_small": wall[small],
                        "wall_large": wall[large],
                        "s_small": own[small],
                        "s_large": own[large],
                        "s_per_1000": per_frame_s * 1000.0,
                        "fixed_s": fixed_s,
                        "rss_mb": rss_mb,
                        "depth_s_per_frame": summaries[large].get("depth_seconds_per_frame"),
                    }
                )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write_results(rows, resolution, args.quick)


def write_results(rows: list[dict], resolution: str, quick: bool) -> None:
    """Write the markdown table to benchmarks/results/preprocess_world.md."""
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    command = "python benchmarks/bench_preprocess_world.py" + (" --quick" if quick else "")
    lines = [
        "## preprocess and build-world: seconds per 1000 frames",
        "",
        f"Machine: {machine_line()}. Date: {now}. Reproduce: `{command}`.",
        f"Input: a synthetic drive, trace at {resolution}; world at 320 px wide (default config). "
        "Each figure is one CLI run in its own process. wall s: the whole process (interpreter start and imports "
        "included); stage s: the stage's own time from its manifest summary. s per 1000 frames: the marginal stage "
        "cost between the two frame counts x 1000; fixed s: the per-run part it leaves out (PNGs, pose-fusion "
        "set-up; 0 when noise makes it negative). "
        "Peak RSS: the child's ru_maxrss (memmapped output pages it touched included; the CLI alone imports torch, "
        "~300 MB).",
        "" if not quick else "**--quick smoke run: too few frames to be representative.**",
        "",
        "| stage | depth method | frames | wall s | stage s | s per 1000 frames | fixed s | depth s/frame "
        "| peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        depth = f"{r['depth_s_per_frame']:.3f}" if r["stage"] == "preprocess" and r["depth_s_per_frame"] else "-"
        lines.append(
            f"| {r['stage']} | {r['method']} | {r['small']} / {r['large']} | {r['wall_small']:.1f} / "
            f"{r['wall_large']:.1f} | {r['s_small']:.1f} / {r['s_large']:.1f} "
            f"| {r['s_per_1000']:.0f} | {max(r['fixed_s'], 0.0):.1f} | {depth} | {r['rss_mb']:.0f} |"
        )
    lines.append("")
    write_markdown(RESULTS, lines, {"command": command, "trace_resolution": resolution, "rows": rows})


if __name__ == "__main__":
    main()
