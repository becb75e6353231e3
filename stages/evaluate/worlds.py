"""An evaluation over several worlds (`drivesim eval --world A --world B`): the same seeds in each world, a row per
world, the pooled figures, and, for a run folder's policy, which worlds it trained on and the train-vs-unseen gap.

Layout of `eval/<name>/` with several worlds: `worlds/<label>/` holds each world's complete single-world output
(metrics.json, episodes/, recordings/, figures, report.html); the top level holds the pooled metrics.json (with
`per_world`, `groups` and `gap`), episodes.csv (a `world` column first), the pooled figures and report.html with the
per-world table. Labels name the world (`world_label`), made unique with a suffix.
"""

from __future__ import annotations

import html
import json
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drivesim.stages.evaluate.metrics import EpisodeResult, aggregate

TRAIN, UNSEEN = "train", "unseen"
WORLD_METRICS = (
    "success",
    "intervention",
    "collision",
    "off_lane",
    "over_rotation",
    "min_clearance_m",
    "min_clearance_no_collision_m",
    "max_deviation_m",
    "max_yaw_rad",
)
"""The figures every row of the per-world table carries (each an estimate with its 95 % interval)."""
GAP_METRICS = ("success", "intervention", "collision", "off_lane", "min_clearance_m")
"""The figures whose unseen-minus-train difference is reported."""
TABLE_COLUMNS = (
    ("success", "success"),
    ("intervention", "intervention"),
    ("collision", "collision"),
    ("off_lane", "off lane"),
    ("min_clearance_m", "min clearance (m, all episodes)"),
)
"""The per-world table's columns after the world and its episode count: (metric, heading)."""


def world_label(world: Path) -> str:
    """A short folder-safe name for a world: for a workspace's `world/`, the name of the recording it was built from
    (`drive_0005.bag` -> `drive_0005`; a town's `towns/seed3/world` -> `seed3`), else the folder's own name."""
    world = Path(world)
    name = world.name
    if world.name == "world" and world.parent.name:
        name = _recording_name(world.parent) or world.parent.name
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "world"


def _recording_name(workspace: Path) -> str | None:
    """The stem of the recording a workspace's trace was read from (trace/sources.json), or None: none is recorded,
    or the workspace is a procedural town's (`towns/seed<N>`), whose drive is synthesized and named by its seed."""
    if workspace.parent.name == "towns":
        return None
    try:
        recording = json.loads((workspace / "trace" / "sources.json").read_text()).get("recording")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(recording, str) or not recording.strip():
        return None
    path = Path(recording.rstrip("/"))
    return path.stem or None  # `drive.bag` -> drive; a folder (KITTI drive, rosbag2, images) keeps its whole name


def world_labels(worlds: Sequence[Path]) -> list[str]:
    """`world_label` of each world, a `-2`, `-3`, ... suffix on repeats so every label is unique."""
    labels: list[str] = []
    for world in worlds:
        base = world_label(world)
        label, n = base, 2
        while label in labels:
            label, n = f"{base}-{n}", n + 1
        labels.append(label)
    return labels


def training_worlds(policy_kind: str, policy_path: str | None) -> set[Path] | None:
    """The worlds a run folder's policy (or one of its checkpoints) trained on: its config.json `worlds`, resolved;
    None for the expert or an ONNX file (no record of its training worlds)."""
    if policy_kind != "run" or policy_path is None:
        return None
    path = Path(policy_path)
    # A checkpoint file (`<run>/checkpoints/<name>.pt`) trained on its run's worlds.
    run_dir = next((p for p in (path, *path.parents[:2]) if (p / "config.json").is_file()), path)
    try:
        data = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return None
    worlds = data.get("worlds") if isinstance(data, dict) else None
    if not isinstance(worlds, list):
        return None
    return {Path(w).resolve() for w in worlds if isinstance(w, str)}


def group_of(world: Path, trained_on: set[Path] | None) -> str | None:
    """`train` when the policy trained on this world, `unseen` when not, None when that is not known."""
    if trained_on is None:
        return None
    return TRAIN if Path(world).resolve() in trained_on else UNSEEN


def _figures(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    agg = aggregate([r.metrics for r in results])
    return {"episodes": len(results), **{k: agg[k].to_json() for k in WORLD_METRICS}}


def world_tables(
    labels: Sequence[str],
    worlds: Sequence[Path],
    groups: Sequence[str | None],
    results: Sequence[Sequence[EpisodeResult]],
) -> dict[str, Any]:
    """`per_world` (a row per world: label, path, group, episodes and `WORLD_METRICS`), `groups` (the same figures
    pooled over the train worlds and over the unseen ones, when known), `gap` (unseen minus train of `GAP_METRICS`;
    empty unless both groups have episodes) and `pooled` (the same figures over every episode)."""
    per_world = [
        {"world": label, "path": str(world), "group": group, "report": f"worlds/{label}/report.html", **_figures(res)}
        for label, world, group, res in zip(labels, worlds, groups, results, strict=True)
    ]
    pooled: dict[str, Any] = {}
    for name in (TRAIN, UNSEEN):
        members = [r for g, res in zip(groups, results, strict=True) if g == name for r in res]
        if members:
            pooled[name] = _figures(members)
    gap: dict[str, float | None] = {}
    if TRAIN in pooled and UNSEEN in pooled:
        for key in GAP_METRICS:
            train, unseen = pooled[TRAIN][key]["value"], pooled[UNSEEN][key]["value"]
            gap[key] = None if train is None or unseen is None else round(unseen - train, 5)
    every = [r for res in results for r in res]
    return {"per_world": per_world, "groups": pooled, "gap": gap, "pooled": _figures(every)}


def write_world_outputs(
    out_dir: Path, cfg: Any, jobs: Sequence[Any], results: Sequence[Sequence[EpisodeResult]], header: dict[str, Any]
) -> tuple[dict[str, Any], list[EpisodeResult], list[Path]]:
    """Each world's single-world output in `worlds/<label>/`, then the pooled one with the per-world table at the top
    level; returns (the top-level metrics, every episode pooled, the videos written).

    :param cfg: the eval config. :param jobs: the worlds (`stages.evaluate.stage.WorldJob`), in order.
    :param results: each world's episodes, in seed order. :param header: what was evaluated (metrics.json's header).
    """
    from drivesim.stages.evaluate.replay import finish_recordings
    from drivesim.stages.evaluate.report import Track, write_outputs
    from drivesim.stages.evaluate.rollout import PolicySpec
    from drivesim.stages.evaluate.video import render_videos

    policy_spec = PolicySpec.parse(cfg.policy)
    trained_on = training_worlds(policy_spec.kind, policy_spec.path)
    groups = [group_of(job.world, trained_on) for job in jobs]
    videos: list[Path] = []
    for job, res in zip(jobs, results, strict=True):
        folder = out_dir / "worlds" / job.label
        (folder / "episodes").mkdir(parents=True)
        for r in res:
            shutil.copy2(job.episodes_dir / f"{r.metrics.seed}.json", folder / "episodes" / f"{r.metrics.seed}.json")
        finish_recordings(job.recording, res, job.factory, policy_spec, cfg.task, folder)  # before the report
        world_header = {**header, "world": str(job.world)}
        write_outputs(folder, res, Track.load(job.world), cfg.task, world_header, cfg.clearance_histogram_max_m)
        videos += render_videos(res, cfg.video, job.factory, policy_spec, folder)
    labels = [job.label for job in jobs]
    tables = world_tables(labels, [job.world for job in jobs], groups, results)
    pooled = [r for res in results for r in res]
    top_header = {**header, "world": ", ".join(str(job.world) for job in jobs), "worlds": len(jobs)}
    data = write_outputs(
        out_dir,
        pooled,
        None,
        cfg.task,
        top_header,
        cfg.clearance_histogram_max_m,
        extra=tables,
        extra_html=worlds_html(tables),
        world_column=[label for label, res in zip(labels, results, strict=True) for _ in res],
    )
    return data, pooled, videos


def _cell(estimate: dict[str, Any]) -> str:
    if not estimate.get("n") or estimate.get("value") is None:
        return "—"
    return (
        f"{estimate['value']:.3f} <span class=ci>[{estimate['ci_low']:.3f}, {estimate['ci_high']:.3f}]</span>"
        if estimate.get("ci_low") is not None
        else f"{estimate['value']:.3f}"
    )


def worlds_html(tables: dict[str, Any]) -> str:
    """The report's per-world table: a row per world (linked to its own report), the pooled train and unseen rows
    and the gap between them, when the policy's training worlds are known."""
    esc = html.escape
    known = any(row["group"] is not None for row in tables["per_world"])
    heads = "".join(f"<th>{esc(h)}</th>" for _, h in TABLE_COLUMNS)
    group_head = "<th>trained on</th>" if known else ""
    rows = []
    for row in tables["per_world"]:
        group = f"<td>{esc(row['group'])}</td>" if known else ""
        cells = "".join(f"<td>{_cell(row[k])}</td>" for k, _ in TABLE_COLUMNS)
        link = f'<a href="{esc(row["report"])}">{esc(row["world"])}</a>'
        rows.append(f"<tr><td>{link}</td>{group}<td>{row['episodes']}</td>{cells}</tr>")
    for name, figures in tables["groups"].items():
        group = f"<td>{esc(name)}</td>" if known else ""
        cells = "".join(f"<td>{_cell(figures[k])}</td>" for k, _ in TABLE_COLUMNS)
        rows.append(f"<tr><th>{esc(name)} worlds, pooled</th>{group}<td>{figures['episodes']}</td>{cells}</tr>")
    every = tables["pooled"]
    cells = "".join(f"<td>{_cell(every[k])}</td>" for k, _ in TABLE_COLUMNS)
    blank = "<td></td>" if known else ""
    rows.append(f"<tr><th>all worlds, pooled</th>{blank}<td>{every['episodes']}</td>{cells}</tr>")
    if tables["gap"]:
        gap = tables["gap"]
        cells = "".join(
            f"<td>{'—' if gap.get(k) is None else f'{gap[k]:+.3f}'}</td>" if k in gap else "<td></td>"
            for k, _ in TABLE_COLUMNS
        )
        rows.append(f"<tr><th>gap: unseen − train</th>{'<td></td>' if known else ''}<td></td>{cells}</tr>")
    note = (
        "Trained on: the worlds in the run's config.json (<code>train</code>) or not (<code>unseen</code>). "
        if known
        else ""
    )
    return (
        f"<h2>Worlds</h2><table><tr><th>world</th>{group_head}<th>episodes</th>{heads}</tr>{''.join(rows)}</table>"
        f"<p class=ci>The same seeds in every world. {note}Each world's own report: <code>worlds/&lt;world&gt;/"
        "report.html</code>. The figures below pool every world's episodes.</p>"
    )
