"""Where the passes on each side fail: the Table I evaluations' winnable starts by pass side, their failures by when
(in the first second or later) and where (a tight bend or not) the episode ended.

    python3 experiments/real_gap/by_side_and_bend.py WS1 WS2 ... > experiments/real_gap/results/by_side_and_bend.md

WS: a `drivesim run` workspace holding bench_table1.py's evaluations (`eval/table1-*`). Side: the ego passes left
when the front car starts right of the lane centre (other_lateral_m < 0). A tight bend: |road curvature| above
TIGHT_BEND_1PM in the episode's last five steps.
"""

from __future__ import annotations

import csv
import json
import sys
from collections import Counter
from pathlib import Path

TIGHT_BEND_1PM = 0.08
EARLY_S = 1.0
ROWS = ("table1-expert", "table1-warm-start", "table1-final-policy")


def _failure_class(episode: Path) -> str:
    """'first 1 s' or 'later', then 'tight bend' or 'elsewhere', from the episode's trajectory."""
    t = json.loads(episode.read_text())["trajectory"]
    when = "first 1 s" if t["t_s"][-1] <= EARLY_S else "later"
    bend = max(abs(c) for c in t["road_curvature_1pm"][-5:]) > TIGHT_BEND_1PM
    return f"{when}, {'tight bend' if bend else 'elsewhere'}"


def row_figures(folder: Path) -> tuple[Counter, Counter, Counter]:
    """(winnable starts per side, successes per side, failures per (side, class)) of one evaluation folder."""
    starts, wins, failures = Counter(), Counter(), Counter()
    with open(folder / "episodes.csv") as f:
        for r in csv.DictReader(f):
            if r["winnable"] != "True":
                continue
            side = "left" if float(r["other_lateral_m"]) < 0 else "right"
            starts[side] += 1
            if r["success"] == "True":
                wins[side] += 1
            else:
                failures[(side, _failure_class(folder / "episodes" / f"{r['seed']}.json"))] += 1
    return starts, wins, failures


def main() -> None:
    """Print the markdown table of every workspace given."""
    classes = [f"{w}, {b}" for w in ("first 1 s", "later") for b in ("tight bend", "elsewhere")]
    print("| drive | row | side | winnable starts | success | " + " | ".join(f"failed: {c}" for c in classes) + " |")
    print("|---|---|---|---:|---:|" + "---:|" * len(classes))
    for ws in map(Path, sys.argv[1:]):
        for row in ROWS:
            if not (ws / "eval" / row / "episodes.csv").exists():
                continue
            starts, wins, failures = row_figures(ws / "eval" / row)
            for side in ("left", "right"):
                cells = " | ".join(str(failures[(side, c)]) for c in classes)
                rate = wins[side] / max(1, starts[side])
                print(f"| {ws.name} | {row.removeprefix('table1-')} | {side} | {starts[side]} | {rate:.3f} | {cells} |")


if __name__ == "__main__":
    main()
