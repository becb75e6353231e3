"""Plain video to a lane policy (issue 23), as a user runs it: the shared KITTI raw drive's grey frames as an MP4
through the whole chain, `drivesim run kitti.mp4 --camera-height-m 1.65 --preset lane` (ingest by SfM, preprocess
with mvs depth, build-world, meshes, at most 15 min of lane training, 100 lane evaluation episodes, export).
Writes benchmarks/results/video_lane.md.

    python benchmarks/bench_video_lane.py                      # the whole chain, ~35 min on 2 cores
    python benchmarks/bench_video_lane.py --from-workspace W   # the table from a chain already run in W
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _lib.report import write_markdown
from bench_video_sfm import make_video

from drivesim.bench.machine import machine_line

RESULTS = Path(__file__).resolve().parent / "results" / "video_lane.md"
COMMAND = ["run", "--camera-height-m", "1.65", "--preset", "lane"]


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a rate."""
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def run_chain(ws: Path, video: Path) -> tuple[float, float]:
    """`drivesim --workspace ws run video ...` in a child process; (wall s, peak child memory GB)."""
    start = time.perf_counter()
    argv = [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), COMMAND[0], str(video), *COMMAND[1:]]
    subprocess.run(argv, check=True)
    wall = time.perf_counter() - start
    return wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2


def _manifest(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())


def _minutes(first_utc: str, last_utc: str) -> float:
    return (dt.datetime.fromisoformat(last_utc) - dt.datetime.fromisoformat(first_utc)).total_seconds() / 60


def figures(ws: Path) -> dict:
    """What the chain in `ws` made: the trace's SfM summary, the lane run and its evaluation."""
    trace = _manifest(ws / "trace")
    runs = sorted((p for p in (ws / "runs").iterdir() if (p / "manifest.json").is_file()), key=lambda p: p.name)
    run = _manifest(runs[-1])
    evals = [p for p in (ws / "eval").iterdir() if (p / "manifest.json").is_file()]
    lane = [m for m in map(_manifest, evals) if m["summary"].get("task") == "lane"]
    evaluation = max(lane, key=lambda m: m["created_utc"])
    return {
        "trace": trace,
        "run": run,
        "run_dir": runs[-1].name,
        "eval": evaluation,
        "chain_min": _minutes(trace["created_utc"], evaluation["created_utc"]),
    }


def table(f: dict) -> list[str]:
    """The result's lines (markdown)."""
    s, r = f["eval"]["summary"], f["run"].get("summary", {})
    n = int(s["episodes"])
    ok = round(s["success"] * n)
    lo, hi = wilson(ok, n)
    steps = r.get("steps", "?")
    train_min = r.get("wall_s", float("nan")) / 60
    return [
        "| video frames (registered) | training | episodes | success (95 % interval) | intervention | off lane | "
        "over-rotation | collision | max deviation (m) |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {f['trace']['summary']['frame_count']} ({f['trace']['summary']['sensors']['poses']['message_count']}) | "
        f"{train_min:.1f} min, {steps} steps | {n} | {s['success']:.0%} ({lo:.0%}-{hi:.0%}) | "
        f"{s['intervention']:.2f} | {s['off_lane']:.2f} | {s['over_rotation']:.2f} | {s['collision']:.2f} | "
        f"{s['max_deviation_m']:.2f} |",
    ]


def main() -> None:
    """Run the chain (or read one already run) and write the results file."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from-workspace", type=Path, help="a workspace where this chain already ran")
    parser.add_argument("--note", default="", help="a sentence added under the table (how the run was made)")
    args = parser.parse_args()
    wall_s, peak_gb = None, None
    if args.from_workspace is None:
        with tempfile.TemporaryDirectory(prefix="bench-video-lane-") as tmp:
            video = Path(tmp) / "kitti_0001.mp4"
            make_video(video)
            wall_s, peak_gb = run_chain(Path(tmp) / "ws", video)
            f = figures(Path(tmp) / "ws")
    else:
        f = figures(args.from_workspace)
    timing = (
        f"The chain took {wall_s / 60:.1f} min, peak memory {peak_gb:.2f} GB."
        if wall_s is not None
        else f"Table read with `--from-workspace` from a workspace where that chain ran: from the ingest's trace to "
        f"the evaluation's manifest {f['chain_min']:.1f} min."
    )
    text = "\n".join(
        [
            "## Plain video to a lane policy (issue 23)",
            "",
            f"Machine: {machine_line()} (when this file was written; the machine is shared). "
            f"Date: {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC. Command: `python "
            f"benchmarks/bench_video_lane.py`, which runs `drivesim --workspace W {COMMAND[0]} kitti_0001.mp4 "
            f"{' '.join(COMMAND[1:])}` on the 108 grey frames of `kitti_raw/2011_09_26_drive_0001_sync/image_00` "
            "written as an MP4 (as in video_sfm.md): no intrinsics, no GPS, only the camera height. "
            "The lane preset (`configs/run/lane.yaml`): mvs depth, `configs/train/lane.yaml`'s training stopped "
            "after 15 min, 100 lane evaluation episodes (seeds 0-99). Success: the episode ends at the end of the "
            "drive's data without intervention (off lane, over-rotation or collision). " + timing,
            "",
            *table(f),
            "",
            "Target: a lane policy trained on the video's world keeps its lane in >= 90 % of 100 evaluation episodes.",
            *(["", args.note] if args.note else []),
            "",
        ]
    )
    write_markdown(RESULTS, [text], {"chain_wall_s": wall_s, "peak_memory_gb": peak_gb, "note": args.note} | f)


if __name__ == "__main__":
    main()
