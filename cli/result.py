"""The result `drivesim run` and `drivesim eval` end with: the Table I rows (the policy, the expert and the warm start
on the same seeds, the paper's columns), the note on the task's geometry, the worlds trained on, the report; with
several worlds, a row per world and the pooled rows."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from drivesim.cli.common import console


def print_result(eval_dir: Path, report_line: bool = True) -> bool:
    """Print the evaluation's Table I rows from its metrics.json; False (nothing printed) when it has none.

    :param eval_dir: the evaluation's folder (`eval/<name>/`).
    :param report_line: end with `report: <path>` (off where the caller prints that line itself).
    """
    from rich.table import Table

    from drivesim.stages.evaluate.summary import RESULT_COLUMNS, result_table

    table_data = result_table(eval_dir)
    if table_data is None:
        return False
    table = Table(title="result (Table I)", title_justify="left")
    table.add_column("policy")
    table.add_column("episodes", justify="right")
    for _, heading in RESULT_COLUMNS:
        table.add_column(heading, justify="right")
    for row in table_data.rows:
        episodes = "" if row.episodes is None else str(row.episodes)
        table.add_row(row.name, episodes, *(row.cells[key] for key, _ in RESULT_COLUMNS))
    console.print(table)
    if table_data.note:
        console.print(table_data.note, highlight=False, soft_wrap=True, style="dim")
    if table_data.trained_on is not None:
        worlds = ", ".join(table_data.trained_on) or "none recorded"
        console.print(f"trained on: {worlds}", highlight=False, soft_wrap=True)
    if report_line:
        console.print(f"report: {table_data.report}", highlight=False, soft_wrap=True)
    return True


def print_worlds(metrics_path: Path) -> None:
    """With several worlds: the table of metrics.json's `per_world` rows, the pooled rows and the train-unseen gap."""
    from rich.table import Table

    from drivesim.stages.evaluate.worlds import TABLE_COLUMNS

    try:
        data = json.loads(metrics_path.read_text())
    except (OSError, ValueError):
        return
    if "per_world" not in data:
        return
    known = any(row.get("group") for row in data["per_world"])

    def value(estimate: dict[str, Any]) -> str:
        return "n/a" if estimate.get("value") is None else f"{estimate['value']:.3f}"

    table = Table(title="per world (same seeds in each)", title_justify="left")
    table.add_column("world")
    if known:
        table.add_column("trained on")
    for heading in ("episodes", *(h for _, h in TABLE_COLUMNS)):
        table.add_column(heading, justify="right")
    rows = [(row["world"], row.get("group") or "", row) for row in data["per_world"]]
    rows += [(f"{name} worlds, pooled", name, figures) for name, figures in data.get("groups", {}).items()]
    rows.append(("all worlds, pooled", "", data["pooled"]))
    for name, group, figures in rows:
        cells = [str(figures["episodes"]), *(value(figures[k]) for k, _ in TABLE_COLUMNS)]
        table.add_row(name, *([group] if known else []), *cells)
    gap = data.get("gap") or {}
    if gap:
        cells = [
            "" if gap.get(k) is None and k not in gap else "n/a" if gap.get(k) is None else f"{gap[k]:+.3f}"
            for k, _ in TABLE_COLUMNS
        ]
        table.add_row("gap: unseen - train", *([""] if known else []), "", *cells)
    console.print(table)
