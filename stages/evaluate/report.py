"""The evaluation's outputs: `metrics.json`, `episodes.csv`, the figures (`*.png`) and one self-contained
`report.html` (images inlined as base64, no external resources) with the metrics beside the paper's Table I."""

from __future__ import annotations

import base64
import csv
import html
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.sim.envs.registry import task_spec
from drivesim.stages.evaluate import plots
from drivesim.stages.evaluate.metrics import (
    LEVELS,
    STATIC_SPEED_MPS,
    EpisodeResult,
    Estimate,
    aggregate,
    along_track,
    breakdowns,
    scenario_table,
    winnable_table,
)
from drivesim.stages.evaluate.record import recording_link, recordings_html

# Paper Table I (offline overtaking, 1000 episodes each): garage / outdoor.
PAPER_TABLE_I = {
    "intervention": (0.129, 0.167),
    "min_clearance_m": (0.216, 0.240),
    "max_deviation_m": (0.361, 0.360),
    "max_yaw_rad": (0.112, 0.082),
}
PAPER_SETUP = {"front_distance_m": (6.0, 15.0), "front_lateral_m": (1.0, 2.0), "collision_overlap_train": 0.05}
"""The paper's Table I setup (§IV-A): the front car 6-15 m ahead and 1-2 m aside of the ego, with a random heading;
a collision at 5 % overlap in training, 0 % in evaluation. It gives no Z_pass, Z_lat or car sizes."""
TABLE_ROWS = (
    ("intervention", "average intervention ↓", "{:.3f}"),
    ("min_clearance_m", "minimum clearance over all episodes (m) ↑", "{:.3f}"),
    ("max_deviation_m", "maximum deviation (m) ↓", "{:.3f}"),
    ("max_yaw_rad", "maximum yaw (rad) ↓", "{:.3f}"),
)
CAUSE_ROWS = (
    ("collision", "collision (polygon overlap > 0)"),
    ("off_lane", "off lane (|q_lat| > Z_lat)"),
    ("over_rotation", "over-rotation (|q_rot| > Z_rot)"),
    ("success", "success"),
    ("end_of_data", "ended at the end of the recorded data"),
)


@dataclass
class Track:
    """The world's reference path, for the plots along the track.

    :param x_m: (N,) frame positions. :param y_m: (N,). :param arc_length_m: (N,) distance along the path.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    arc_length_m: np.ndarray

    @classmethod
    def load(cls, world_dir: Path) -> Track:
        """From the world's path.npz."""
        with np.load(Path(world_dir) / "path.npz") as path:
            return cls(np.asarray(path["x_m"]), np.asarray(path["y_m"]), np.asarray(path["arc_length_m"]))


def geometry_note(task: str, env_overrides: dict[str, Any]) -> str:
    """One line: where the task's geometry (its env config with `env_overrides`) differs from the paper's Table I
    setup; "" for a task without a front car to pass."""
    spec = task_spec(task)
    if not spec.env_class().has_other or "pass_distance_m" not in spec.env_class().task_keys:
        return ""
    c = spec.config_with(env_overrides)
    near, far = c.front_distance_m
    low, high = c.front_lateral_m
    ahead = "" if (near, far) == PAPER_SETUP["front_distance_m"] else f"{near:g}-{far:g} m ahead (paper 6-15 m), "
    side = "" if c.front_side == "either" else f", on the {c.front_side}"
    parts = [
        f"the front car {ahead}{low:g}-{high:g} m from the lane centre{side}, heading along the road (paper: 1-2 m "
        "from the ego, a random heading)"
    ]
    overlap = c.collision_overlap_train
    if overlap != PAPER_SETUP["collision_overlap_train"]:
        at = "at any overlap" if overlap == 0 else f"above {100 * overlap:g} % overlap"
        parts.append(f"a training collision {at} (paper 5 %)")
    parts.append(
        f"not given by the paper: the front car at {c.other_speed_mps[0]:g}-{c.other_speed_mps[1]:g} m/s, the ego "
        f"at {c.ego_speed_mps[0]:g}-{c.ego_speed_mps[1]:g} m/s and {c.ego_length_m:g} x {c.ego_width_m:g} m, "
        f"passed {c.pass_distance_m:g} m ahead and back within {c.return_lateral_m:g} m of the centre, off lane "
        f"beyond {c.max_lateral_m:g} m"
    )
    return "Our task's geometry where it differs from the paper's: " + "; ".join(parts) + "."


def write_outputs(
    out_dir: Path,
    results: Sequence[EpisodeResult],
    track: Track | None,
    task: str,
    header: dict[str, Any],
    clearance_max_m: float = 2.0,
    extra: dict[str, Any] | None = None,
    extra_html: str = "",
    world_column: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Write metrics.json, episodes.csv, the PNGs and report.html into `out_dir`; returns the metrics dict.

    :param results: the evaluated episodes, in seed order.
    :param track: the world's path; None (episodes of several worlds) leaves out the figures along the track.
    :param task: the task evaluated.
    :param header: what was evaluated (policy, world, seeds, ...), recorded in metrics.json and the report.
    :param clearance_max_m: upper end of the per-step clearance histogram [m].
    :param extra: more keys for metrics.json (the per-world table of `stages.evaluate.worlds`).
    :param extra_html: a report section shown right after the header table.
    :param world_column: each episode's world, written as episodes.csv's first column (None: no such column).
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = [r.metrics for r in results]
    agg = aggregate(metrics)
    levels = breakdowns(metrics)
    # The Table II split, for a task that has those scenarios (overtake's `scenarios()`).
    scenarios = scenario_table(metrics) if task_spec(task).env_class().scenarios() else []
    tracking = agg["mean_tracking_error_m"].n > 0  # the task measures a tracking error (follow)
    figures = {
        "breakdown.png": plots.plot_breakdowns(levels, out_dir / "breakdown.png"),
        "clearance.png": plots.plot_clearance(results, out_dir / "clearance.png", clearance_max_m),
    }
    if track is not None:
        along = along_track(results, len(track.x_m))
        figures["track.png"] = plots.plot_track(track.x_m, track.y_m, along, out_dir / "track.png", tracking=tracking)
    figures["relative.png"] = plots.plot_relative(results, out_dir / "relative.png")
    if tracking and track is not None:
        figures["tracking.png"] = plots.plot_tracking(track.arc_length_m, along, out_dir / "tracking.png")
    data = {
        "format": 1,
        **header,
        "task": task,
        "episodes": len(results),
        "aggregate": {k: v.to_json() for k, v in agg.items()},
        "intervention_causes": {k: int(sum(getattr(m, k) for m in metrics)) for k, _ in CAUSE_ROWS},
        "breakdowns": [b.to_json() for b in levels],
        "scenarios": scenarios,
        "starts": winnable_table(metrics),
        "paper_table_i": {k: {"garage": g, "outdoor": o} for k, (g, o) in PAPER_TABLE_I.items()},
        **(extra or {}),
    }
    (out_dir / "metrics.json").write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    write_csv(out_dir / "episodes.csv", results, world_column)
    (out_dir / "report.html").write_text(_html(data, agg, levels, figures, results, out_dir, extra_html))
    return data


def write_csv(path: Path, results: Sequence[EpisodeResult], worlds: Sequence[str] | None = None) -> None:
    """One row per episode with its metrics and initial conditions (its world first, when `worlds` is given)."""
    rows = [r.metrics.row() for r in results]
    if worlds is not None:
        rows = [{"world": w, **row} for w, row in zip(worlds, rows, strict=True)]
    if not rows:
        path.write_text("")
        return
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _csv_value(v) for k, v in row.items()})


def _csv_value(value: Any) -> Any:
    if isinstance(value, float):
        return "" if not math.isfinite(value) else round(value, 5)
    return value


def _fmt(e: Estimate, pattern: str = "{:.3f}") -> str:
    if e.n == 0 or not math.isfinite(e.value):
        return "—"
    return f"{pattern.format(e.value)} <span class=ci>[{pattern.format(e.ci_low)}, {pattern.format(e.ci_high)}]</span>"


def _img(path: Path, alt: str) -> str:
    encoded = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    image = f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{encoded}">'
    return f"<figure>{image}<figcaption>{html.escape(alt)}</figcaption></figure>"


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1150px;color:#222}
h1{font-size:1.5em} h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0} td,th{border:1px solid #ccc;padding:.3em .7em;text-align:right}
th{background:#f3f3f3} td:first-child,th:first-child{text-align:left} .ci{color:#777;font-size:.85em}
figure{margin:1em 0} img{max-width:100%;border:1px solid #eee} figcaption{color:#555;font-size:.9em}
.meta td{text-align:left} code{background:#f5f5f5;padding:0 .2em}
"""


def _html(
    data: dict[str, Any],
    agg: dict[str, Estimate],
    levels: Sequence[Any],
    figures: dict[str, Path],
    results: Sequence[EpisodeResult],
    out_dir: Path | None = None,
    extra_html: str = "",
) -> str:
    esc = html.escape
    meta_keys = ("task", "policy", "episodes", "seed", "world", "meshes", "created_utc")
    meta = "".join(f"<tr><th>{esc(k)}</th><td>{esc(str(data.get(k, '')))}</td></tr>" for k in meta_keys if k in data)
    n = max(len(results), 1)
    counts = data["intervention_causes"]
    causes = "".join(
        f"<tr><td>{label}</td><td>{counts[k]}</td><td>{counts[k] / n:.3f}</td></tr>" for k, label in CAUSE_ROWS
    )
    worst_rows = "".join(
        f"<tr><td>{r.metrics.seed}</td><td>{_winnable(r)}</td><td>{'yes' if r.metrics.intervention else 'no'}</td>"
        f"<td>{_causes(r)}</td><td>{_number(r.metrics.pass_shortfall_m)}</td>"
        f"<td>{_number(r.metrics.min_clearance_m)}</td><td>{_number(r.metrics.max_deviation_m)}</td>"
        f"<td>{_number(r.metrics.max_yaw_rad)}</td><td>{r.metrics.steps}</td>"
        f"<td>{recording_link(out_dir, r.metrics.seed) if out_dir else '—'}</td></tr>"
        for r in worst_episodes(results)
    )
    captions = {
        "breakdown.png": "Fig. 4: intervention rate and maximum deviation by trial difficulty (95 % CI)",
        "clearance.png": "Fig. 5: clearance of the steps (histogram), and the recall of trials by minimum clearance",
        "track.png": "Fig. 6 (left, middle): intervention rate and deviation from the centre along the track",
        "relative.png": "Fig. 6 (right): trajectories relative to the front car, last polygons of interventions",
        "tracking.png": "car following: tracking error by track position",
    }
    images = "".join(_img(p, captions[name]) for name, p in figures.items())
    level_head = "".join(f"<th>{lv}</th>" for lv in LEVELS)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>drivesim evaluation: {esc(str(data.get("policy", "")))}</title>
<style>{_CSS}</style></head><body>
<h1>drivesim evaluation — {esc(str(data.get("task", "")))}, policy {esc(str(data.get("policy", "")))}</h1>
<table class=meta>{meta}{_trained_on_html(data.get("trained_on"))}</table>{extra_html}
<h2>Metrics beside the paper's Table I</h2>
<table><tr><th>metric</th><th>this evaluation [95 % CI]</th><th>paper, garage</th><th>paper, outdoor</th></tr>
{_table_i_rows(agg)}</table>
{f"<p class=ci>{esc(data['geometry_note'])}</p>" if data.get("geometry_note") else ""}
<p class=ci>Intervention: polygon overlap &gt; 0, off lane or over-rotation. Minimum clearance: mean over all
episodes (a collision counts 0) of the smallest distance between the two footprints. Maximum deviation / yaw: mean
over the episodes of the largest |q_lat| / |q_rot|. Rates: Wilson interval; means: percentile bootstrap (2000
resamples). Definitions: <code>drivesim.stages.evaluate.metrics</code>.</p>
{_baselines_html(data.get("baselines") or [])}
<h2>Interventions by cause, and outcomes</h2>
<table><tr><th>cause</th><th>episodes</th><th>rate</th></tr>{causes}</table>
<p class=ci>An episode may have more than one cause.</p>
{_scenario_html(data["scenarios"])}{_starts_html(data["starts"])}
<h2>Breakdown by trial difficulty</h2>
<table><tr><th>factor</th>{level_head}</tr>{_level_rows(levels)}</table>
<p class=ci>Each cell: intervention rate, mean maximum deviation, episodes. Levels are the quartiles of the factor over
these episodes (initial lateral difference: the smallest is the most challenging).</p>
<h2>Figures</h2>
{images}
<h2>Worst episodes</h2>
<table><tr><th>seed</th><th>winnable start</th><th>intervention</th><th>causes</th><th>still to pass (m)</th>
<th>min clearance (m)</th><th>max deviation (m)</th><th>max yaw (rad)</th><th>steps</th><th>recording</th></tr>
{worst_rows}</table>
<p class=ci>The failed episodes: those whose start can be won first, then the farthest from success (the distance
still needed to pass the front car by Z_pass; without a pass, the fewest steps driven), then by seed.</p>
<p class=ci>Every episode: <code>episodes.csv</code>, per-step trajectories in <code>episodes/&lt;seed&gt;.json</code>;
aggregates in <code>metrics.json</code>.</p>
{recordings_html(out_dir, results) if out_dir else ""}
</body></html>
"""


def _table_i_rows(agg: dict[str, Estimate]) -> str:
    """The rows of the metrics beside the paper's Table I, then the metrics the paper has no figure for (those
    this evaluation measured)."""
    rows = []
    for key, label, pattern in TABLE_ROWS:
        garage, outdoor = PAPER_TABLE_I[key]
        rows.append(
            f"<tr><td>{label}</td><td>{_fmt(agg[key], pattern)}</td>"
            f"<td>{pattern.format(garage)}</td><td>{pattern.format(outdoor)}</td></tr>"
        )
    for key, label in (
        ("success", "success rate"),
        ("min_clearance_no_collision_m", "minimum clearance, episodes without a collision only (m)"),
        ("mean_tracking_error_m", "mean tracking error (m)"),
    ):
        if agg[key].n:
            rows.append(f"<tr><td>{label}</td><td>{_fmt(agg[key])}</td><td>—</td><td>—</td></tr>")
    return "".join(rows)


def _level_rows(levels: Sequence[Any]) -> str:
    """The breakdown's rows: per factor, each quartile's intervention rate, mean maximum deviation and episodes."""
    rows = []
    for b in levels:
        cells = "".join(
            f"<td>{_fmt(i)}<br>{_fmt(d)} m<br><span class=ci>n={i.n}</span></td>"
            for i, d in zip(b.intervention, b.max_deviation_m, strict=True)
        )
        edges = ", ".join(f"{e:.3g}" for e in b.edges)
        name = html.escape(plots.FACTOR_LABELS[b.factor])
        rows.append(f"<tr><td>{name}<br><span class=ci>quartiles {edges}</span></td>{cells}</tr>")
    return "".join(rows)


def _ci_cell(e: dict[str, Any]) -> str:
    """A rate with its 95 % interval as an HTML table cell ("—" without episodes)."""
    if not e["n"]:
        return "—"
    return f"{e['value']:.3f} <span class=ci>[{e['ci_low']:.3f}, {e['ci_high']:.3f}]</span>"


def _rows_html(rows: Sequence[dict[str, Any]], label: str, cells: Sequence[Callable[[dict[str, Any]], str]]) -> str:
    """HTML table rows: each row's `label` (escaped), its episodes, then one cell per function of `cells`."""
    return "".join(
        f"<tr><td>{html.escape(r[label])}</td><td>{r['episodes']}</td>{''.join(f'<td>{c(r)}</td>' for c in cells)}</tr>"
        for r in rows
    )


def _scenario_html(rows: Sequence[dict[str, Any]]) -> str:
    """The scenario table (the paper's Table II, offline) as HTML; empty without another car."""
    if not rows:
        return ""

    body = _rows_html(rows, "scenario", [lambda r: _ci_cell(r["success"]), lambda r: _ci_cell(r["intervention"])])
    return (
        "<h2>Scenarios (the paper's Table II, offline)</h2>"
        "<table><tr><th>scenario</th><th>episodes</th><th>success [95 % CI]</th><th>intervention [95 % CI]</th>"
        f"</tr>{body}</table><p class=ci>Static: the front car slower than {STATIC_SPEED_MPS} m/s. "
        "<code>drivesim eval --scenario static --scenario pass-left</code> evaluates one scenario alone.</p>"
    )


def _starts_html(rows: Sequence[dict[str, Any]]) -> str:
    """The winnable / unwinnable starts table as HTML; empty when the env labels no start."""
    if not rows:
        return ""

    rates = [lambda r, k=k: _ci_cell(r[k]) for k in ("success", "intervention", "collision")]
    body = _rows_html(rows, "starts", [lambda r: f"{r['share']:.3f}", *rates])
    return (
        "<h2>Starts that can be won</h2><table><tr><th>starts</th><th>episodes</th><th>share</th>"
        "<th>success [95 % CI]</th><th>intervention [95 % CI]</th><th>collision [95 % CI]</th></tr>"
        f"{body}</table><p class=ci>Unwinnable: the front car so close and closing so fast that even the hardest "
        "swerve within the ego's steering limits does not get clear of it (<code>drivesim.sim.envs.winnable</code>; "
        "the privileged expert fails most such starts); the headline figures above include them. "
        "<code>--set env.redraw_unwinnable=true</code> draws such starts again.</p>"
    )


WORST_EPISODES = 10


def worst_key(r: EpisodeResult) -> tuple[bool, bool, float, int, int]:
    """Sort key of the worst episodes: failures first, those whose start can be won (or is not labelled) before
    the unwinnable, then the farthest from success (the distance still needed to pass; without a pass, the fewest
    steps driven), then the seed: no two episodes tie."""
    m = r.metrics
    shortfall = m.pass_shortfall_m if math.isfinite(m.pass_shortfall_m) else 0.0
    return (m.success, m.winnable is False, -shortfall, m.steps, m.seed)


def worst_episodes(results: Sequence[EpisodeResult], count: int = WORST_EPISODES) -> list[EpisodeResult]:
    """The `count` worst episodes (`worst_key`), failures only."""
    return sorted((r for r in results if not r.metrics.success), key=worst_key)[:count]


def _baselines_html(rows: Sequence[dict[str, Any]]) -> str:
    """The policy beside its baselines (the expert, the warm start) on the same seeds; empty without baselines."""
    if not rows:
        return ""
    heads = "".join(f"<th>{html.escape(label)}</th>" for _, label in BASELINE_COLUMNS)
    body = "".join(
        f"<tr><td>{html.escape(r['row'])}</td><td>{r['episodes']}</td>"
        + "".join(f"<td>{_json_cell(r[k])}</td>" for k, _ in BASELINE_COLUMNS)
        + "</tr>"
        for r in rows
    )
    first, last = rows[0].get("seeds") or (None, None)
    return (
        "<h2>Beside the expert and the warm start, on the same seeds</h2>"
        f"<table><tr><th>policy</th><th>episodes</th>{heads}</tr>{body}</table>"
        f"<p class=ci>Seeds {first} to {last}: the evaluation's first <code>baseline_episodes</code>. The expert "
        "steers with the privileged state; the warm start is the run's policy before any PPO update "
        "(<code>checkpoints/warm_start.pt</code>).</p>"
    )


BASELINE_COLUMNS = (
    ("intervention", "intervention"),
    ("success", "success"),
    ("collision", "collision"),
    ("off_lane", "off lane"),
    ("over_rotation", "over-rotation"),
    ("min_clearance_m", "min clearance (m)"),
    ("max_deviation_m", "max deviation (m)"),
    ("max_yaw_rad", "max yaw (rad)"),
)


def _json_cell(e: dict[str, Any]) -> str:
    """An estimate from metrics.json with its 95 % interval ("—" without a value)."""
    if not e.get("n") or e.get("value") is None:
        return "—"
    return f"{e['value']:.3f} <span class=ci>[{e['ci_low']:.3f}, {e['ci_high']:.3f}]</span>"


def _trained_on_html(worlds: Sequence[dict[str, Any]] | None) -> str:
    """A header row naming the worlds the policy trained on; empty when that is not known."""
    if worlds is None:
        return ""
    names = ", ".join(html.escape(w["world"]) for w in worlds) or "—"
    return f"<tr><th>trained on</th><td>{names}</td></tr>"


def _winnable(r: EpisodeResult) -> str:
    return "—" if r.metrics.winnable is None else "yes" if r.metrics.winnable else "no"


def _number(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else "—"


def _causes(r: EpisodeResult) -> str:
    names = [k for k in ("collision", "off_lane", "over_rotation") if getattr(r.metrics, k)]
    return ", ".join(names) or "—"
