"""Merge the per-area result files `benchmarks/results/*.md` into `benchmarks/RESULTS.md`.

Each benchmark script writes its own section (with the machine, date and command that produced it); this script only
orders and concatenates them so the figures live in one file.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent
ORDER = [
    "targets",
    "demo",
    "sim",
    "sim_previous_code",
    "sim_second_machine",
    "vista",
    "car_fidelity",
    "meshes",
    "train_speed",
    "learning",
    "eval",
    "ray",
    "record",
    "ingest",
    "video_sfm",
    "render",
    "synth",
    "poses",
    "depth",
    "stereo",
    "preprocess_world",
    "fidelity",
]


def main() -> None:
    """Write benchmarks/RESULTS.md from benchmarks/results/*.md."""
    sections = sorted((HERE / "results").glob("*.md"), key=lambda p: ORDER.index(p.stem) if p.stem in ORDER else 99)
    parts = [
        "# Benchmark results\n",
        "Measured by the scripts in `benchmarks/` (each section says how to reproduce it). "
        "Regenerate this file with `python benchmarks/collect_results.py` after running them.\n",
        "VISTA 2.0.6, the predecessor, runs on this machine at 41–60 ms per step on the KITTI drive at 200x320 "
        "(`../shared/bench/vista/`).\n",
    ]
    parts += [p.read_text().strip() + "\n" for p in sections]
    (HERE / "RESULTS.md").write_text("\n".join(parts))
    print(f"wrote {HERE / 'RESULTS.md'} from {len(sections)} sections")


if __name__ == "__main__":
    main()
