"""`drivesim status`: each stage's artifact as fresh / stale / missing."""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer
from rich.table import Table

from drivesim.chain.registry import CHAIN
from drivesim.cli.common import console, workspace
from drivesim.pipeline.status import status_report

_STATE_STYLE = {"fresh": "green", "stale": "yellow", "missing": "dim"}


def _summary_text(summary: dict[str, Any]) -> str:
    parts = []
    for key, value in summary.items():
        if value in ({}, [], None, ""):  # nothing to say (an ingest that skipped no message): no empty "skipped:"
            continue
        if isinstance(value, dict):
            inner = ", ".join(
                f"{k} ({v.get('message_count', '?')})" if isinstance(v, dict) else f"{k}={v}" for k, v in value.items()
            )
            parts.append(f"{key}: {inner}")
        elif isinstance(value, float):
            parts.append(f"{key}={value:.3g}")
        else:
            parts.append(f"{key}={value}")
    return "; ".join(parts)


def status_command(
    as_json: Annotated[bool, typer.Option("--json", help="Print the stable JSON form (format 1) for scripts.")] = False,
) -> None:
    """Show every stage of the chain as fresh, stale or missing, with a summary of each artifact."""
    report = status_report(workspace(), CHAIN)
    if as_json:
        print(json.dumps(report, indent=2))
        return
    table = Table(title=f"workspace {report['workspace']}", show_lines=False)
    table.add_column("stage")
    table.add_column("state")
    table.add_column("summary / reason", overflow="fold")
    for row in report["stages"]:
        style = _STATE_STYLE[row["state"]]
        detail = _summary_text(row["summary"]) if row["state"] == "fresh" else "; ".join(row["reasons"])
        if row["state"] == "stale" and row["summary"]:
            detail += " | " + _summary_text(row["summary"])
        table.add_row(row["stage"], f"[{style}]{row['state']}[/]", detail)
    console.print(table)
