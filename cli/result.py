"""The result `drivesim run` and `drivesim eval` end with: the Table I rows (the policy, the expert and the warm start
on the same seeds, the paper's columns), the note on the task's geometry, the worlds trained on, the report."""

from __future__ import annotations

from pathlib import Path

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
