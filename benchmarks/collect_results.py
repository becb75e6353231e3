"""Write `benchmarks/RESULTS.md` from the result files the benchmark scripts write into `benchmarks/results/`.

    python benchmarks/collect_results.py            # rewrite benchmarks/RESULTS.md
    python benchmarks/collect_results.py --check    # exit 1 when RESULTS.md is not what the results make

RESULTS.md is a summary table (one row per section: what it measures, when, on what machine, at what load, by which
script), then one section per benchmark in the order of `SECTIONS`. Every file under `benchmarks/results/` must be
named by a section (or in `NOT_SECTIONS`), and every named file must exist: anything else is an error, so a new
benchmark's results cannot land unordered. A section measured before `RESTATED_SINCE` (older than the code it
describes) keeps its file but RESULTS.md states none of its figures, only the command that measures it again.
Prose lines are wrapped at `WRAP_COLUMNS`; a line that cannot be wrapped (a table row) over `MAX_LINE_CHARS` is an
error.
"""

from __future__ import annotations

import argparse
import re
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS_DIR = HERE / "results"
OUTPUT = HERE / "RESULTS.md"
MAX_LINE_CHARS = 300
WRAP_COLUMNS = 120
# The oldest measurement date whose figures RESULTS.md restates (ISO date, UTC): the day the code was last changed in
# a way that can move a figure. Raise it when such a change lands.
RESTATED_SINCE = "2026-11-27"


@dataclass(frozen=True)
class Section:
    """One benchmark's section: `key` is its anchor, `files` its result files (the first, a markdown file, dated)."""

    key: str
    title: str
    measures: str
    command: str
    files: tuple[str, ...]


SECTIONS: tuple[Section, ...] = (
    Section(
        "sim",
        "Simulator speed",
        "env steps/s per task, car-drawn steps counted apart",
        "drivesim bench sim --world W",
        ("sim.md",),
    ),
    Section(
        "vista",
        "Against VISTA 2.0.6",
        "ms per step beside VISTA on one KITTI drive",
        "python benchmarks/bench_vista_ratio.py",
        ("vista.md", "vista.json"),
    ),
    Section(
        "car_step",
        "A car-drawn step, before and after",
        "ms per overtake step with the car drawn, two code versions",
        "python benchmarks/bench_car_step.py --before DIR",
        ("car_step.md",),
    ),
    Section(
        "threads_busy",
        "Render threads on a busy machine",
        "`render_threads` 1 vs 2 with and without a busy core",
        "python benchmarks/bench_threads_busy.py --world W",
        ("threads_busy.md", "threads_busy.json"),
    ),
    Section(
        "demo",
        "The demo run",
        "`make demo` wall time per stage",
        "python benchmarks/bench_demo.py",
        ("demo.md", "demo.json"),
    ),
    Section(
        "train_speed",
        "Training speed",
        "env steps/s of `drivesim train` (the preset's whole loop) and of the bare PPO loop",
        "python benchmarks/bench_train_speed.py --world W",
        ("train_speed.md", "train_speed.json"),
    ),
    Section(
        "gpu",
        "On a GPU",
        "views/s of the batched GPU path, `learn()` on a GPU",
        "python benchmarks/bench_gpu.py --world W",
        ("gpu.md", "gpu.json", "gpu_h100.md", "gpu_h100.json"),
    ),
    Section(
        "table1",
        "Table I on real drives",
        "`drivesim run REC` as a user runs it, then 1000 episodes per row and the baselines on the same seeds",
        "python benchmarks/bench_table1.py --drives NAME",
        ("table1.md", "table1.json"),
    ),
    Section(
        "eval",
        "Evaluation (Table I)",
        "episodes/min of `drivesim eval`, the paper's metrics",
        "python benchmarks/bench_eval.py --world W",
        ("eval.md",),
    ),
    Section(
        "eval_startup",
        "Evaluation start-up",
        "time before the first episode of a 10,000-episode evaluation",
        "python benchmarks/bench_eval_startup.py",
        ("eval_startup.md", "eval_startup.json"),
    ),
    Section(
        "ray",
        "Evaluation on Ray",
        "Ray's overhead against local workers",
        "python benchmarks/bench_ray.py --world W",
        ("ray.md",),
    ),
    Section(
        "preprocess_ray",
        "Preprocessing on Ray",
        "camera-only depth: one process against a 2-node loopback Ray cluster, bytes per frame, N machines on paper",
        "python benchmarks/bench_preprocess_ray.py",
        ("preprocess_ray.md", "preprocess_ray.json"),
    ),
    Section(
        "record",
        "Foxglove recordings",
        "time `--record failures` adds to an evaluation",
        "python benchmarks/bench_record.py",
        ("record.md",),
    ),
    Section(
        "export",
        "ONNX export",
        "torch vs onnxruntime, ms per policy step",
        "python benchmarks/bench_export.py --workspace WS",
        ("export.md",),
    ),
    Section(
        "ingest",
        "Ingest",
        "frames/s and peak memory of `drivesim ingest`",
        "python benchmarks/bench_ingest.py",
        ("ingest.md",),
    ),
    Section(
        "video_sfm",
        "Plain video: SfM poses and scale",
        "camera path and scale from a video against GPS",
        "python benchmarks/bench_video_sfm.py",
        ("video_sfm.md",),
    ),
    Section(
        "video_lane",
        "Plain video to a lane policy",
        "the whole chain from an MP4",
        "python benchmarks/bench_video_lane.py",
        ("video_lane.md",),
    ),
    Section(
        "synth",
        "Synthetic drives",
        "seconds per rendered frame of `drivesim synth`",
        "python benchmarks/bench_synth.py",
        ("synth.md", "synth.json"),
    ),
    Section(
        "meshes",
        "Vehicle library",
        "build time and raster time per vehicle",
        "python benchmarks/bench_meshes.py",
        ("meshes.md", "meshes.json"),
    ),
    Section(
        "render",
        "Rendering",
        "rasterizer and warp ms per frame beside OpenGL",
        "python benchmarks/bench_render.py",
        ("render.md", "render.json"),
    ),
    Section(
        "poses",
        "Poses",
        "GPS + IMU + speed fusion error and speed",
        "python benchmarks/bench_poses.py",
        ("poses.md", "poses.json"),
    ),
    Section(
        "depth", "Depth", "per-frame depth speed, memory, accuracy", "python benchmarks/bench_depth.py", ("depth.md",)
    ),
    Section(
        "preprocess_world",
        "preprocess and build-world",
        "seconds per 1000 frames, peak memory",
        "python benchmarks/bench_preprocess_world.py",
        ("preprocess_world.md",),
    ),
    Section(
        "scaling",
        "Scaling with the drive's length",
        "per stage: ms per frame, peak memory, disk per minute, for drives of 1 to 30 minutes; float16 depth's "
        "and JPEG frames' cost",
        "python benchmarks/bench_scaling.py --minutes 1,5,30",
        (
            "scaling.md",
            "scaling.json",
            "scaling.png",
            "scaling_view_cache.md",
            "scaling_view_cache.json",
            "storage_fidelity.md",
            "storage_fidelity.json",
            "frame_storage.md",
            "frame_storage.json",
        ),
    ),
    Section(
        "fidelity",
        "Depth and view fidelity",
        "depth and novel views against ground truth",
        "drivesim bench fidelity --frames N --markdown F",
        ("fidelity.md", "fidelity.png"),
    ),
    Section(
        "stereo",
        "Real lateral views",
        "views warped into a real stereo pair's right camera",
        "python benchmarks/bench_stereo.py",
        ("stereo.md", "stereo_worst.png", "stereo_filled.md", "stereo_filled.json", "stereo_filled_worst.png"),
    ),
    Section(
        "view_fill",
        "No black in the view",
        "recorded share of the view off the path, cost of filling",
        "python benchmarks/bench_view_fill.py",
        ("view_fill.md", "view_fill_speed.md"),
    ),
    Section(
        "car_fidelity",
        "Inserted-car fidelity",
        "an inserted car against ground truth",
        "drivesim bench car-fidelity",
        ("car_fidelity.md", "car_fidelity.png"),
    ),
    Section(
        "car_gray",
        "Cars on a gray camera",
        "an inserted car on a monochrome camera",
        "python benchmarks/bench_car_gray.py",
        ("car_gray.md", "car_gray.json"),
    ),
    Section(
        "car_realism",
        "Inserted cars against real cars (C2ST)",
        "a classifier telling the recording's own cars from inserted ones, per drive and level",
        "python benchmarks/bench_car_realism.py",
        ("car_realism.md", "car_realism.json", "car_realism.png"),
    ),
    Section(
        "harmonizer",
        "The learned harmonizer",
        "the learned harmonizer against the statistical one: synthetic truth, the C2ST, time per view",
        "python benchmarks/bench_harmonizer.py",
        ("harmonizer.md", "harmonizer.json", "harmonizer.png"),
    ),
    Section(
        "occlusion",
        "Inserted cars in the right depth order",
        "background pixels shown through a car body over expert steps on each real drive",
        "python benchmarks/bench_occlusion.py --world NAME=W",
        ("occlusion.md", "occlusion.json"),
    ),
)
# Files under results/ that are no benchmark's section, and why.
NOT_SECTIONS: dict[str, str] = {"targets.md": "the issue targets table, linked from the summary"}
# Restated markdown files with no raw JSON beside them yet, and why (a script writes `<name>.json` with the figures of
# its table; these were measured before it did and are not cheap to measure again, or come from `drivesim bench`).
RAW_MISSING: dict[str, str] = {
    "sim.md": "written by `drivesim bench sim`, which writes no JSON",
    "fidelity.md": "written by `drivesim bench fidelity`, which writes no JSON",
    "car_fidelity.md": "written by `drivesim bench car-fidelity`, which writes no JSON",
    "car_step.md": "its world and earlier code folder are gone",
    "eval.md": "its world is gone; over a minute to measure",
    "export.md": "its trained run is gone",
    "ray.md": "its world is gone",
    "record.md": "about 5 minutes to measure",
    "ingest.md": "about 2 minutes to measure",
    "depth.md": "over a minute and load-sensitive: measure on a quiet machine",
    "stereo.md": "about 4 minutes to measure",
    "view_fill.md": "its real-drive world is gone",
    "view_fill_speed.md": "about 2 minutes to measure",
    "video_sfm.md": "minutes of SfM to measure",
    "video_lane.md": "a 15-minute training to measure",
}

DATE = re.compile(r"(20\d\d-\d\d-\d\d)(?:[ T,]+(\d\d:\d\d))?")
MACHINE = re.compile(r"(\d+-core CPU(?: \((?:[^()]|\([^)]*\))*\))?|NVIDIA [A-Z0-9]+(?: [0-9A-Za-z]+GB)?|\d+ cores)")
LOAD = re.compile(r"load average(?: after| before)?:? ([0-9]+(?:\.[0-9]+)?)")


class ResultsError(Exception):
    """The results folder and SECTIONS disagree, or a line is too long."""


@dataclass(frozen=True)
class Measured:
    """When, where and at what load a result file says it was measured ("?" where it does not say)."""

    date: str
    time_utc: str
    machine: str
    load: str


def measured(text: str) -> Measured:
    """The first date, machine and load average named in a result file's first lines."""
    head = "\n".join(text.splitlines()[:8])
    date = DATE.search(head)
    machine = MACHINE.search(head)
    load = LOAD.search(head)
    return Measured(
        date=date.group(1) if date else "?",
        time_utc=(date.group(2) or "") if date else "",
        machine=machine.group(1).replace("(R)", "") if machine else "?",
        load=load.group(1) if load else "?",
    )


def check_files(results_dir: Path) -> None:
    """Raise ResultsError when a file under results_dir is in no section, or a section's file is missing."""
    listed = {name for s in SECTIONS for name in s.files} | set(NOT_SECTIONS)
    present = {p.relative_to(results_dir).as_posix() for p in results_dir.rglob("*") if p.is_file()}
    unlisted = sorted(present - listed)
    missing = sorted(listed - present)
    if unlisted:
        raise ResultsError(f"results files in no section of collect_results.SECTIONS: {', '.join(unlisted)}")
    if missing:
        raise ResultsError(
            f"files named in collect_results.SECTIONS but absent from {results_dir}: {', '.join(missing)}"
        )


def check_raw(results_dir: Path) -> None:
    """Raise ResultsError when a restated markdown file has no JSON beside it and no reason in RAW_MISSING, or a
    RAW_MISSING file has its JSON after all (the reason is stale)."""
    for section in SECTIONS:
        for name in section.files:
            if not name.endswith(".md") or not restated(measured((results_dir / name).read_text())):
                continue
            raw = name.removesuffix(".md") + ".json"
            has_raw = raw in section.files and (results_dir / raw).is_file()
            if not has_raw and name not in RAW_MISSING:
                raise ResultsError(f"{name} is restated but has no {raw} in its section: its script must write it")
            if has_raw and name in RAW_MISSING:
                raise ResultsError(f"{name} has its {raw}: remove it from collect_results.RAW_MISSING")


def wrap(text: str) -> list[str]:
    """The lines of a markdown text, prose and list items over WRAP_COLUMNS wrapped; tables and code kept."""
    out: list[str] = []
    in_code = False
    for line in text.splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if in_code or len(line) <= WRAP_COLUMNS or line.lstrip().startswith(("|", "#", "![")):
            out.append(line)
            continue
        item = re.match(r"(\s*(?:[-*]|\d+\.)\s+)", line)
        indent = " " * len(item.group(1)) if item else re.match(r"\s*", line).group(0)
        out += textwrap.wrap(
            line, WRAP_COLUMNS, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False
        )
    return out


def demote(lines: list[str]) -> list[str]:
    """Headings two levels below the section's (`#` -> `###`), the file's own title dropped."""
    if lines and lines[0].startswith("#"):
        lines = lines[1:]
    while lines and not lines[0].strip():
        lines = lines[1:]
    return [("##" + line) if line.startswith("#") else line for line in lines]


def restated(when: Measured) -> bool:
    """Whether a file measured then is restated (measured on or after RESTATED_SINCE)."""
    return when.date != "?" and when.date >= RESTATED_SINCE


def section_text(section: Section, results_dir: Path) -> tuple[list[str], Measured]:
    """A section's markdown lines and its first file's measurement; each file older than RESTATED_SINCE (and the
    pictures of a section whose first file is) gets one line instead of its figures."""
    first = measured((results_dir / section.files[0]).read_text())
    links = ", ".join(f"[`{name}`](results/{name})" for name in section.files)
    lines = [
        f'<a id="{section.key}"></a>',
        f"## {section.title}",
        "",
        *wrap(f"Files: {links}. Measure again: `{section.command}`."),
        "",
    ]
    for name in section.files:
        if name.endswith(".md"):
            when = measured((results_dir / name).read_text())
            if restated(when):
                lines += demote(wrap((results_dir / name).read_text().strip())) + [""]
            else:
                lines += [
                    f"`{name}`: measured {when.date} on older code; its figures are not restated here. Run the "
                    "command above to measure them on today's code.",
                    "",
                ]
        elif name.endswith(".png") and restated(first):
            lines += [f"![{name}](results/{name})", ""]
    return lines, first


def summary_row(section: Section, when: Measured) -> str:
    """The summary table's row of one section."""
    stated = "restated" if restated(when) else "not restated (older code)"
    measured_at = f"{when.date} {when.time_utc}".strip()
    return (
        f"| [{section.title}](#{section.key}) | {section.measures} | {measured_at} | {when.machine} | {when.load} | "
        f"{stated} |"
    )


def collect(results_dir: Path = RESULTS_DIR) -> str:
    """The text of RESULTS.md from results_dir; raises ResultsError on an unlisted or missing file or a long line."""
    check_files(results_dir)
    check_raw(results_dir)
    bodies: list[str] = []
    rows: list[str] = []
    for section in SECTIONS:
        lines, when = section_text(section, results_dir)
        bodies += lines + [""]
        rows.append(summary_row(section, when))
    head = [
        "# Benchmark results",
        "",
        "Written by `python benchmarks/collect_results.py` from `benchmarks/results/` (do not edit by hand).",
        f"Each section names its script; figures measured before {RESTATED_SINCE} are on older code and are not",
        "restated. Issue targets: [`results/targets.md`](results/targets.md).",
        "",
        "| section | measures | measured (UTC) | machine | load average | figures |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
    ]
    lines = head + bodies
    too_long = [(n + 1, len(line)) for n, line in enumerate(lines) if len(line) > MAX_LINE_CHARS]
    if too_long:
        where = ", ".join(f"line {n} ({length} chars)" for n, length in too_long[:5])
        raise ResultsError(f"RESULTS.md would have lines over {MAX_LINE_CHARS} characters: {where}")
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    """Write (or with --check, compare) benchmarks/RESULTS.md; exit 2 with one line on a results error."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when RESULTS.md differs from what it would be")
    args = parser.parse_args()
    try:
        text = collect()
    except ResultsError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.check:
        same = OUTPUT.exists() and OUTPUT.read_text() == text
        print(f"{OUTPUT} is {'up to date' if same else 'stale: run python benchmarks/collect_results.py'}")
        return 0 if same else 1
    OUTPUT.write_text(text)
    print(f"wrote {OUTPUT} ({len(SECTIONS)} sections)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
