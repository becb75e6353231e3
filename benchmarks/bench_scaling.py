"""How the chain's cost grows with the drive's length: per stage, wall time per frame, peak memory, disk per minute.

For each drive length (default 1, 5 and 30 minutes; `--minutes 1,5` chooses) a synthetic drive is rendered by
`drivesim synth --duration-s` (seed 0, the default 960x600 camera at 10 Hz) and run through `drivesim ingest`,
`drivesim preprocess` and `drivesim build-world`, each stage as the CLI runs it in its own process. Then
`drivesim bench sim --tasks lane` measures the training env's steps/s on that world (random starts over the whole
drive, so a long world's frames are read from all over its files).

Measured per stage and length: wall seconds of the process and per frame (frames = the trace's frame count), the
stage's own seconds from its manifest summary, the child's peak resident memory (`os.wait4`'s ru_maxrss of exactly
that process: the CLI's imports, ~300 MB with torch, included), and the load average before and after. Per artifact
(the recording, trace/, preprocessed/, world/): bytes on disk, per frame and per minute of driving, file by file.

Usage: python benchmarks/bench_scaling.py [--minutes 1,5,30] [--depth-method auto] [--keep DIR]
With --keep, the shortest and the longest world are also measured alternately: a bare env's steps/s (3 runs each,
--alternate-steps) and `drivesim train lane`'s training env steps/s from its progress.csv (2 runs each, --train-steps).
With --keep and --reuse-measured, the stages of a kept workspace are read back and only the env is measured again.
Writes benchmarks/results/scaling.md, scaling.json and scaling.png (cost vs drive length per stage).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from _lib.report import measured_now, write_markdown
from _lib.train_run import train_stage_row

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
STAGES = ("synth", "ingest", "preprocess", "build-world", "sim")
ARTIFACTS = {
    "recording": "recordings", "trace": "trace", "preprocessed": "preprocessed", "world": "world",
    "view cache": "world/view_cache",
}  # fmt: skip
# The view's prepared frames (sim/frame_cache.py), written beside the world by the first env: a cache the simulator
# can rebuild, counted apart from the world and outside the workspace.
VIEW_CACHE = "view_cache"
# Artifacts that make up the workspace at the default settings (the recording is the user's input, not counted).
WORKSPACE_ARTIFACTS = ("trace", "preprocessed", "world")
MANIFEST = {"ingest": "trace", "preprocess": "preprocessed", "build-world": "world"}


@dataclass
class StageRun:
    """One stage's process: wall seconds, peak RSS, the stage's own seconds (manifest), the load around it."""

    stage: str
    minutes: float
    frames: int
    wall_s: float
    peak_rss_mb: float
    stage_s: float | None
    load_before: float
    load_after: float
    extra: dict[str, Any]

    @property
    def ms_per_frame(self) -> float:
        """Wall milliseconds per frame of the drive."""
        return 1000.0 * self.wall_s / max(self.frames, 1)


def load_1min() -> float:
    """The 1-minute load average."""
    return round(os.getloadavg()[0], 2)


def uptime_line() -> str:
    """What `uptime` says (its load averages), or the load average when it cannot be run."""
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def measure(args: list[str]) -> tuple[float, float, str]:
    """Run `args`; (wall s, peak RSS MB of exactly that child via os.wait4, its stdout). Exits on failure."""
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = proc.stdout.read() if proc.stdout is not None else b""
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    text = output.decode(errors="replace")
    if code != 0:
        raise SystemExit(f"{' '.join(args)} failed ({code}):\n{text[-4000:]}")
    return seconds, usage.ru_maxrss / 1024.0, text  # Linux reports KiB


def drivesim(ws: Path, *args: str) -> list[str]:
    """The command line of `drivesim --workspace ws ARGS`."""
    return [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args]


def folder_bytes(folder: Path) -> dict[str, int]:
    """Bytes on disk of every file under `folder` (allocated blocks, so sparse files count what they hold)."""
    if not folder.is_dir():
        return {}
    return {
        p.relative_to(folder).as_posix(): p.stat().st_blocks * 512 for p in sorted(folder.rglob("*")) if p.is_file()
    }


def run_stage(ws: Path, stage: str, minutes: float, frames: int, args: list[str]) -> StageRun:
    """Run one stage's command and collect its figures (the manifest summary's seconds when the stage has one)."""
    before = load_1min()
    print(f"[{time.strftime('%H:%M:%S')}] {minutes:g} min: {stage} (load {before}) ...", flush=True)
    wall_s, rss_mb, output = measure(args)
    stage_s = None
    extra: dict[str, Any] = {}
    if stage in MANIFEST:
        summary = json.loads((ws / MANIFEST[stage] / "manifest.json").read_text()).get("summary", {})
        stage_s = summary.get("seconds")
        extra = {k: summary[k] for k in ("depth_method", "depth_seconds_per_frame", "frame_count") if k in summary}
    if stage == "sim":
        result = json.loads(output[output.index("{") :])
        lane = next(t for t in result["tasks"] if t["task"] == "lane")
        extra = {"steps_per_s": round(lane["steps_per_s"], 1), "ms_per_step": round(lane["ms_per_step"]["total"], 3)}
    run = StageRun(stage, minutes, frames, wall_s, rss_mb, stage_s, before, load_1min(), extra)
    print(f"    {wall_s:.1f} s, {run.ms_per_frame:.1f} ms/frame, peak RSS {rss_mb:.0f} MB {extra}", flush=True)
    return run


def measure_length(work: Path, minutes: float, depth_method: str, sim_steps: int) -> dict[str, Any]:
    """Every stage on a drive of `minutes`; the runs, and the artifacts' bytes per file."""
    ws = work / f"{minutes:g}min"
    recording = ws / "recordings" / "drive.mcap"
    frames = round(minutes * 60 * 10)  # the synth camera's 10 Hz; replaced by the trace's count after ingest
    synth_json = ws / "synth_run.json"
    if recording.is_file() and synth_json.is_file():  # a kept workspace: the drive is not rendered again
        synth = StageRun(**{**json.loads(synth_json.read_text()), "extra": {"reused": "kept recording"}})
        print(f"{minutes:g} min: reusing {recording} (synth figures of its first run)", flush=True)
    else:
        synth_args = ["synth", "--seed", "0", "--duration-s", f"{minutes * 60:g}", "--output", str(recording)]
        synth = run_stage(ws, "synth", minutes, frames, drivesim(ws, *synth_args))
        synth_json.write_text(json.dumps(asdict(synth)))
    runs = [synth, run_stage(ws, "ingest", minutes, frames, drivesim(ws, "ingest", str(recording), "--force"))]
    frames = int(json.loads((ws / "trace" / "manifest.json").read_text())["summary"]["frame_count"])
    for run in runs:
        run.frames = frames
    depth = ["--set", f"depth.method={depth_method}"]
    runs.append(run_stage(ws, "preprocess", minutes, frames, drivesim(ws, "preprocess", *depth, "--force")))
    runs.append(run_stage(ws, "build-world", minutes, frames, drivesim(ws, "build-world", "--force")))
    sim_args = ["bench", "sim", "--world", str(ws / "world"), "--tasks", "lane", "--steps", str(sim_steps), "--json"]
    runs.append(run_stage(ws, "sim", minutes, frames, drivesim(ws, *sim_args)))
    disk = {name: folder_bytes(ws / sub) for name, sub in ARTIFACTS.items()}
    disk["world"] = {rel: n for rel, n in disk["world"].items() if not rel.startswith(f"{VIEW_CACHE}/")}
    return {"minutes": minutes, "frames": frames, "runs": [asdict(r) for r in runs], "disk_bytes": disk}


def remeasure_sim(work: Path, length: dict[str, Any], sim_steps: int) -> dict[str, Any]:
    """A read-back length with its `sim` row measured again on its kept world (the env's code changes most often)."""
    ws = work / f"{length['minutes']:g}min"
    sim_args = ["bench", "sim", "--world", str(ws / "world"), "--tasks", "lane", "--steps", str(sim_steps), "--json"]
    sim = asdict(run_stage(ws, "sim", length["minutes"], length["frames"], drivesim(ws, *sim_args)))
    return {**length, "runs": [r for r in length["runs"] if r["stage"] != "sim"] + [sim]}


def stages_measured(report: Path) -> str:
    """When the stages read back with --reuse-measured were measured: the date of the report written beside them."""
    try:
        earlier = json.loads(report.with_suffix(".json").read_text())
        return earlier.get("stages_measured") or earlier["measured"]["date_utc"] + " UTC"
    except (OSError, KeyError, ValueError):
        return "an earlier run (date unknown)"


def _disk_row(minutes: float, frames: int, artifact: str, files: dict[str, int]) -> dict[str, Any]:
    """One artifact's row: MB, KB per frame, MB per minute of driving, and its three largest files' KB per frame."""
    total = sum(files.values())
    top = sorted(files.items(), key=lambda kv: -kv[1])[:3]
    return {
        "minutes": minutes,
        "artifact": artifact,
        "mb": total / 1e6,
        "kb_per_frame": total / 1e3 / max(frames, 1),
        "mb_per_min": total / 1e6 / minutes,
        "files": {k: round(v / 1e3 / max(frames, 1), 1) for k, v in top},
    }


def disk_rows(lengths: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per length and artifact: MB, KB per frame, MB per minute of driving, and the largest files' share; then the
    workspace (trace + preprocessed + world) and the workspace with the view cache as totals."""
    rows = []
    for length in lengths:
        minutes, frames, disk = length["minutes"], length["frames"], length["disk_bytes"]
        rows += [_disk_row(minutes, frames, name, files) for name, files in disk.items()]
        workspace = {f"{a}/{k}": n for a in WORKSPACE_ARTIFACTS for k, n in disk[a].items()}
        cache = {f"view cache/{k}": n for k, n in disk.get("view cache", {}).items()}
        rows.append({**_disk_row(minutes, frames, "workspace (trace + preprocessed + world)", workspace), "files": {}})
        rows.append({**_disk_row(minutes, frames, "workspace and view cache", workspace | cache), "files": {}})
    return rows


def plot(raw: dict[str, Any], path: Path) -> None:
    """scaling.png: per stage, ms per frame and peak RSS against the drive's length; MB per minute per artifact."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    lengths = raw["lengths"]
    minutes = [length["minutes"] for length in lengths]
    fig, axes = plt.subplots(1, 4, figsize=(19, 4.2), layout="constrained")
    for stage in STAGES:
        runs = [next(r for r in length["runs"] if r["stage"] == stage) for length in lengths]
        if stage != "sim":
            axes[0].plot(minutes, [1000.0 * r["wall_s"] / max(r["frames"], 1) for r in runs], "o-", label=stage)
        axes[1].plot(minutes, [r["peak_rss_mb"] for r in runs], "o-", label=stage)
    sim = [next(r for r in length["runs"] if r["stage"] == "sim") for length in lengths]
    axes[2].plot(minutes, [r["extra"]["steps_per_s"] for r in sim], "o-", label="bare env (lane), one run")
    for key, label in (("steps_interleaved", "bare env"), ("train_interleaved", "drivesim train lane")):
        steps = raw.get(key)
        if steps:
            axes[2].plot(
                [minutes[0], minutes[-1]], [steps["short_steps_per_s"], steps["long_steps_per_s"]], "s--",
                label=f"{label}, median of {steps['repeats']} alternating runs",
            )  # fmt: skip
    axes[2].set_ylim(bottom=0)
    for name in (*ARTIFACTS, "workspace"):
        parts = WORKSPACE_ARTIFACTS if name == "workspace" else (name,)
        per_min = [sum(sum(x["disk_bytes"].get(a, {}).values()) for a in parts) / 1e6 / x["minutes"] for x in lengths]
        axes[3].plot(minutes, per_min, "o-", label=name if name != "workspace" else "workspace (trace+pre+world)")
    axes[0].set_yscale("log")
    axes[3].axhline(150, color="grey", ls="--", lw=1, label="target: workspace 150 MB/min")
    titles = ("wall ms per frame (process)", "peak RSS (MB)", "env steps/s on the drive's world", "disk MB per minute")
    for ax, title in zip(axes, titles, strict=True):
        ax.set_xscale("log")
        ax.set_xticks(minutes, [f"{m:g}" for m in minutes])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("drive length (min)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(raw: dict[str, Any]) -> list[str]:
    """The report's lines: when, where and at what load; the stage table; the disk table."""
    lengths = raw["lengths"]
    m = raw["measured"]
    lines = [
        "## Scaling with the drive's length",
        "",
        f"Machine: {m['machine']}. Date: {m['date_utc']} UTC. Load average at start {raw['load_start']}, at end "
        f"{raw['load_end']} (`uptime` at start: {raw['uptime_start']}). Reproduce: `{raw['command']}`.",
        "",
        f"Synthetic drives (seed 0, 960x600 camera at 10 Hz) of {', '.join(f'{x:g}' for x in raw['minutes'])} "
        f"minutes through the chain at its default settings but depth.method={raw['depth_method']} (auto picks mvs "
        "for a camera-only drive: its cost is per frame, on a window of neighbours, see Depth), each stage one CLI "
        "process; ms/frame = the process's wall time / the drive's frames (imports included: a short drive pays "
        "more start-up per frame); peak RSS = that process's ru_maxrss (the CLI's imports ~300 MB included); sim = "
        f"`drivesim bench sim --tasks lane --steps {raw['sim_steps']}` on the drive's world (steps/s of one env). "
        "The load is beside each run. The view cache is what the first env writes beside a world of more than 2048 "
        "frames (`sim/frame_cache.py`): a cache the simulator rebuilds, counted apart from the workspace.",
        "",
    ]
    if "stages_measured" in raw:
        lines += [
            f"The rows of synth, ingest, preprocess and build-world and the disk table were measured at "
            f"{raw['stages_measured']} (read back with --reuse-measured from the kept workspaces); the sim rows and "
            "the alternating steps/s at the date above.",
            "",
        ]
    lines += [
        "| stage | minutes | frames | wall s | ms/frame | stage s | peak RSS MB | load before/after | notes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for stage in STAGES:
        for length in lengths:
            r = next(x for x in length["runs"] if x["stage"] == stage)
            per_frame = f"{1000.0 * r['wall_s'] / max(r['frames'], 1):.1f}" if stage != "sim" else "-"
            stage_s = "-" if r["stage_s"] is None else f"{r['stage_s']:.1f}"
            notes = ", ".join(f"{k} {v}" for k, v in r["extra"].items() if k != "frame_count")
            lines.append(
                f"| {stage} | {r['minutes']:g} | {r['frames']} | {r['wall_s']:.1f} | {per_frame} | {stage_s} "
                f"| {r['peak_rss_mb']:.0f} | {r['load_before']:.1f} / {r['load_after']:.1f} | {notes or '-'} |"
            )
    lines += [
        "",
        "Disk per artifact (allocated bytes; KB per frame of the three largest files in brackets):",
        "",
        "| minutes | artifact | MB | KB per frame | MB per minute | largest files (KB/frame) |",
        "|---|---|---|---|---|---|",
    ]
    for row in raw["disk"]:
        files = ", ".join(f"{k} {v:g}" for k, v in row["files"].items()) or "-"
        lines.append(
            f"| {row['minutes']:g} | {row['artifact']} | {row['mb']:.0f} | {row['kb_per_frame']:.0f} "
            f"| {row['mb_per_min']:.0f} | {files} |"
        )
    lines += targets(raw)
    if raw.get("before"):
        lines += comparison(raw)
    lines += ["", "Plot: `scaling.png` (per stage against the drive's length).", ""]
    return lines


def _run(length: dict[str, Any], stage: str) -> dict[str, Any]:
    return next(r for r in length["runs"] if r["stage"] == stage)


def _within(ratio: float, tolerance: float) -> str:
    return f"x{ratio:.2f}, {'within' if abs(ratio - 1) <= tolerance else 'beyond'} {100 * tolerance:.0f} %"


def targets(raw: dict[str, Any]) -> list[str]:
    """Lines comparing the lengths against the issue's targets: per-frame cost (the marginal ms per frame from each
    length to the next, which start-up does not enter) within 20 %, peak memory <= 4 GB and within 20 % from the
    second length to the longest, env steps/s of the longest world within 10 % of the shortest's (interleaved
    measurement), workspace <= 150 MB per minute."""
    lengths = raw["lengths"]
    if len(lengths) < 3:
        return []
    short, middle, long = lengths[0], lengths[1], lengths[-1]
    lines = [
        "",
        f"Against the targets (the {short['minutes']:g}-, {middle['minutes']:g}- and {long['minutes']:g}-minute "
        "drives):",
        "",
    ]
    for stage in ("synth", "ingest", "preprocess", "build-world"):
        a, b, c = _run(short, stage), _run(middle, stage), _run(long, stage)
        first = 1000 * (b["wall_s"] - a["wall_s"]) / max(b["frames"] - a["frames"], 1)
        second = 1000 * (c["wall_s"] - b["wall_s"]) / max(c["frames"] - b["frames"], 1)
        rss = c["peak_rss_mb"] / b["peak_rss_mb"]
        lines.append(
            f"- {stage}: {first:.1f} ms per added frame from {short['minutes']:g} to {middle['minutes']:g} min, "
            f"{second:.1f} from {middle['minutes']:g} to {long['minutes']:g} ({_within(second / first, 0.2)}); "
            f"peak RSS {c['peak_rss_mb']:.0f} MB at {long['minutes']:g} min "
            f"({'under' if c['peak_rss_mb'] <= 4096 else 'over'} 4 GB), "
            f"{_within(rss, 0.2)} of {middle['minutes']:g} min"
        )
    steps = raw.get("steps_interleaved")
    if not steps:  # the workspaces were not kept: one run per world, in turn
        sim = [_run(length, "sim")["extra"]["steps_per_s"] for length in (short, long)]
        steps = {"steps": raw["sim_steps"], "repeats": 1, "short_steps_per_s": sim[0], "long_steps_per_s": sim[1]}
    lines.append(
        f"- env steps/s (lane, one bare env, {steps['steps']} steps, {steps['repeats']} alternating runs each, "
        f"median): {steps['long_steps_per_s']:.0f} on the {long['minutes']:g}-minute world against "
        f"{steps['short_steps_per_s']:.0f} on the {short['minutes']:g}-minute one "
        f"({_within(steps['long_steps_per_s'] / steps['short_steps_per_s'], 0.1)})"
    )
    lines.append(
        "  (a world of more than 2048 frames reads a frame its env has not kept from the view cache, an LZ4 decode of "
        "tens of microseconds, on most steps of a bare env; the shortest world holds all its frames)"
    )
    train = raw.get("train_interleaved")
    if train:
        lines.append(
            f"- training env steps/s (`{train['command']}`, its progress.csv, {train['repeats']} alternating runs "
            f"each, median): {train['long_steps_per_s']:.0f} on the {long['minutes']:g}-minute world against "
            f"{train['short_steps_per_s']:.0f} on the {short['minutes']:g}-minute one "
            f"({_within(train['long_steps_per_s'] / train['short_steps_per_s'], 0.1)})"
        )
    for artifact in ("workspace (trace + preprocessed + world)", "workspace and view cache"):
        worst = max(r["mb_per_min"] for r in raw["disk"] if r["artifact"] == artifact)
        lines.append(
            f"- {artifact}: at most {worst:.0f} MB per minute of driving "
            f"(target 150: {'met' if worst <= 150 else 'not met'})"
        )
    return lines


def train_interleaved(work: Path, lengths: list[float], steps: int, repeats: int = 2) -> dict[str, Any]:
    """Training env steps/s of `drivesim train lane` (the preset's loop, towns left out, no evaluation within the
    budget) on the shortest and the longest world, alternately `repeats` times each; the medians of the rates
    the runs' progress.csv report."""
    measured: dict[str, list[float]] = {"short": [], "long": []}
    command = ""
    for _ in range(repeats):
        for key, minutes in (("short", lengths[0]), ("long", lengths[-1])):
            print(f"[{time.strftime('%H:%M:%S')}] drivesim train lane on the {minutes:g}-minute world ...", flush=True)
            world = work / f"{minutes:g}min" / "world"
            row = train_stage_row(world, "lane", steps, eval_every=10 * steps, eval_episodes=1)
            measured[key].append(row["last_progress_row"]["steps_per_s_run"])
            command = row["command"].replace(str(world), "WORLD")
    return {
        "command": command,
        "steps": steps,
        "repeats": repeats,
        "runs": measured,
        "short_steps_per_s": statistics.median(measured["short"]),
        "long_steps_per_s": statistics.median(measured["long"]),
    }


def steps_interleaved(work: Path, lengths: list[float], steps: int, repeats: int = 3) -> dict[str, Any]:
    """Env steps/s (lane, one env) on the shortest and the longest world, measured alternately `repeats` times each
    so that a change of the machine's load falls on both; the medians."""
    short_ws, long_ws = work / f"{lengths[0]:g}min", work / f"{lengths[-1]:g}min"
    measured: dict[str, list[float]] = {"short": [], "long": []}
    for _ in range(repeats):
        for key, ws in (("short", short_ws), ("long", long_ws)):
            args = ["bench", "sim", "--world", str(ws / "world"), "--tasks", "lane", "--steps", str(steps), "--json"]
            _, _, output = measure(drivesim(ws, *args))
            result = json.loads(output[output.index("{") :])
            measured[key].append(next(t for t in result["tasks"] if t["task"] == "lane")["steps_per_s"])
    return {
        "steps": steps,
        "repeats": repeats,
        "runs": measured,
        "short_steps_per_s": statistics.median(measured["short"]),
        "long_steps_per_s": statistics.median(measured["long"]),
    }


def comparison(raw: dict[str, Any]) -> list[str]:
    """Lines of a table of this run beside an earlier code version's run (`--before`), per stage and length."""
    before = raw["before"]
    m = before["measured"]
    lines = [
        "",
        f"Beside the code before this change ({before['label']}; measured {m['date_utc']} UTC, load average at start "
        f"{before['load_start']}, on the same recordings): peak RSS and ms/frame per stage, MB per minute per "
        "artifact.",
        "",
        "| stage or artifact | minutes | peak RSS MB before / now | ms/frame before / now "
        "| MB per minute before / now |",
        "|---|---|---|---|---|",
    ]
    old = {x["minutes"]: x for x in before["lengths"]}
    for stage in STAGES[1:]:
        for length in raw["lengths"]:
            if length["minutes"] not in old:
                continue
            a = next(r for r in old[length["minutes"]]["runs"] if r["stage"] == stage)
            b = next(r for r in length["runs"] if r["stage"] == stage)
            if stage == "sim":
                per_frame = f"steps/s {a['extra']['steps_per_s']:.0f} / {b['extra']['steps_per_s']:.0f}"
            else:
                per_frame = f"{1000 * a['wall_s'] / a['frames']:.1f} / {1000 * b['wall_s'] / b['frames']:.1f}"
            lines.append(
                f"| {stage} | {b['minutes']:g} | {a['peak_rss_mb']:.0f} / {b['peak_rss_mb']:.0f} | {per_frame} | - |"
            )
    rows_before = {(r["minutes"], r["artifact"]): r for r in before["disk"]}
    for row in raw["disk"]:
        a = rows_before.get((row["minutes"], row["artifact"]))
        if a is not None and row["artifact"] != "recording":
            lines.append(
                f"| {row['artifact']} | {row['minutes']:g} | - | - | {a['mb_per_min']:.0f} / {row['mb_per_min']:.0f} |"
            )
    return lines


def parse_minutes(text: str) -> list[float]:
    """`1,5,30` -> [1.0, 5.0, 30.0]; one clear line and exit 2 for anything else."""
    try:
        values = sorted({float(x) for x in text.split(",") if x.strip()})
    except ValueError:
        values = []
    if not values or any(v <= 0 or v > 60 for v in values):
        print(f"--minutes {text!r}: give drive lengths in minutes, comma-separated, each in (0, 60]", file=sys.stderr)
        raise SystemExit(2)
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", default="1,5,30", help="drive lengths in minutes, comma-separated")
    parser.add_argument("--depth-method", default="auto", help="preprocess depth.method (default: the chain's)")
    parser.add_argument("--sim-steps", type=int, default=3000, help="env steps of the steps/s measurement")
    parser.add_argument(
        "--alternate-steps", type=int, default=10000, help="with --keep: env steps of each alternating steps/s run"
    )
    parser.add_argument(
        "--train-steps",
        type=int,
        default=16384,
        help="with --keep: env steps of each alternating `drivesim train lane` run (0: none)",
    )
    parser.add_argument("--keep", type=Path, default=None, help="keep the workspaces in this folder")
    parser.add_argument("--output", type=Path, default=RESULTS / "scaling.md", help="markdown report to write")
    parser.add_argument(
        "--reuse-measured",
        action="store_true",
        help="with --keep: read back the lengths measured by an earlier run into the same folder",
    )
    parser.add_argument("--before", type=Path, default=None, help="scaling.json of an earlier code version")
    parser.add_argument("--before-label", default="an earlier commit", help="what --before measured")
    args = parser.parse_args()
    minutes = parse_minutes(args.minutes)
    work = args.keep or Path(tempfile.mkdtemp(prefix="drivesim-bench-scaling-"))
    work.mkdir(parents=True, exist_ok=True)
    command = f"python benchmarks/bench_scaling.py --minutes {args.minutes}"
    if args.depth_method != "auto":
        command += f" --depth-method {args.depth_method}"
    if args.keep is not None:
        command += " --keep DIR" + (" --reuse-measured" if args.reuse_measured else "")
    raw: dict[str, Any] = {
        "measured": measured_now(),
        "command": command,
        "minutes": minutes,
        "depth_method": args.depth_method,
        "sim_steps": args.sim_steps,
        "load_start": load_1min(),
        "uptime_start": uptime_line(),
        "lengths": [],
    }
    try:
        for m in minutes:
            done = work / f"{m:g}min" / "length.json"
            if args.reuse_measured and done.is_file():
                print(f"{m:g} min: read back from {done}; the env's steps/s measured again", flush=True)
                raw["lengths"].append(remeasure_sim(work, json.loads(done.read_text()), args.sim_steps))
                raw["stages_measured"] = stages_measured(args.output)
                continue
            raw["lengths"].append(measure_length(work, m, args.depth_method, args.sim_steps))
            done.write_text(json.dumps(raw["lengths"][-1]))
            if args.keep is None:
                shutil.rmtree(work / f"{m:g}min", ignore_errors=True)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    if len(minutes) >= 2 and args.keep is not None:
        print(f"[{time.strftime('%H:%M:%S')}] env steps/s, alternating worlds ...", flush=True)
        raw["steps_interleaved"] = steps_interleaved(work, minutes, args.alternate_steps)
        if args.train_steps > 0:
            raw["train_interleaved"] = train_interleaved(work, minutes, args.train_steps)
    raw["load_end"] = load_1min()
    raw["uptime_end"] = uptime_line()
    raw["disk"] = disk_rows(raw["lengths"])
    if args.before is not None:
        raw["before"] = {**json.loads(args.before.read_text()), "label": args.before_label}
        raw["before"].pop("before", None)
    plot(raw, args.output.with_suffix(".png"))
    write_markdown(args.output, markdown(raw), raw)


if __name__ == "__main__":
    main()
