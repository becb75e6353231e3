"""The eval stage's typed summary (the figures it records in its manifest and `drivesim status` shows), and the
Table I rows `drivesim run` and `drivesim eval` end with, read from the evaluation's metrics.json.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivesim.pipeline.stage import StageSummary


class EvalSummary(StageSummary):
    """A finished evaluation: the headline metrics (means and rates over its episodes)."""

    task: str
    """lane, follow or overtake."""
    policy: str
    """expert, a run folder's name or an ONNX file's name."""
    episodes: int
    """Episodes evaluated."""
    intervention: float
    """Intervention rate (collision, off lane or over-rotation)."""
    collision: float
    """Rate of episodes with a polygon overlap > 0."""
    off_lane: float
    """Rate of episodes that left the lane."""
    over_rotation: float
    """Rate of episodes that turned too far from the road heading."""
    success: float
    """Success rate."""
    min_clearance_m: float | None
    """Mean minimum clearance over all episodes with another car, collisions (0) included [m]."""
    max_deviation_m: float | None
    """Mean maximum |lateral deviation| [m]."""
    max_yaw_rad: float | None
    """Mean maximum |yaw relative to the road| [rad]."""
    episodes_resumed: int
    """Episodes found on disk from an interrupted evaluation."""
    episodes_per_min: float | None
    """Episodes run per minute in this session (None when all were resumed) [1/min]."""
    workers: int
    """Worker processes used (Ray actors with the ray backend)."""
    videos: list[str] = []
    """MP4 files rendered."""


RESULT_COLUMNS = (
    ("intervention", "intervention [95 % CI]"),
    ("success", "success"),
    ("collision", "collision"),
    ("off_lane", "off lane"),
    ("over_rotation", "over-rotation"),
    ("min_clearance_m", "min clearance, all episodes (m)"),
    ("max_deviation_m", "max deviation (m)"),
    ("max_yaw_rad", "max yaw (rad)"),
)
"""The end-of-run table's columns after the row name and its episodes: (metrics.json key, heading)."""


@dataclass
class ResultRow:
    """One row of the end-of-run table: a name, its episodes (None for the paper's) and a cell per column."""

    name: str
    episodes: int | None
    cells: dict[str, str]


@dataclass
class ResultTable:
    """What `drivesim run` and `drivesim eval` end with, read from an evaluation's metrics.json.

    :param rows: the policy, its baselines on the same seeds, then the paper's garage and outdoor columns.
    :param note: where the task's geometry differs from the paper's Table I setup ("" when not told).
    :param trained_on: the worlds the policy trained on (labels); None when not known (expert, ONNX file).
    :param report: the evaluation's report.html.
    """

    rows: list[ResultRow]
    note: str
    trained_on: list[str] | None
    report: Path


def _cell(estimate: dict[str, Any] | None, interval: bool) -> str:
    if not estimate or estimate.get("value") is None:
        return "n/a"
    text = f"{estimate['value']:.3f}"
    if interval and estimate.get("ci_low") is not None:
        text += f" [{estimate['ci_low']:.3f}, {estimate['ci_high']:.3f}]"
    return text


def _row(name: str, figures: dict[str, Any]) -> ResultRow:
    cells = {key: _cell(figures.get(key), key == "intervention") for key, _ in RESULT_COLUMNS}
    return ResultRow(name, int(figures.get("episodes", 0)), cells)


def result_table(eval_dir: Path) -> ResultTable | None:
    """The Table I rows of the evaluation in `eval_dir` (its metrics.json), or None when it has none."""
    try:
        data = json.loads((Path(eval_dir) / "metrics.json").read_text())
        aggregate = data["aggregate"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    rows = [_row(f"{data.get('policy', 'policy')} (all episodes)", {"episodes": data.get("episodes"), **aggregate})]
    for row in data.get("baselines") or []:
        if row.get("policy") == data.get("policy") and row.get("episodes") == data.get("episodes"):
            continue  # the policy on the baselines' seeds is every episode: the row above says it already
        rows.append(_row(str(row.get("row", "")), row))
    paper = data.get("paper_table_i") or {}
    for place in ("garage", "outdoor"):
        cells = {
            key: f"{paper[key][place]:.3f}" if key in paper and place in paper[key] else "" for key, _ in RESULT_COLUMNS
        }
        if any(cells.values()):
            rows.append(ResultRow(f"paper, {place}", None, cells))
    trained = data.get("trained_on")
    trained_on = None if trained is None else [str(w.get("world", "")) for w in trained]
    return ResultTable(rows, str(data.get("geometry_note") or ""), trained_on, Path(eval_dir) / "report.html")
