"""Writing a benchmark's results: the markdown table and, beside it, the raw figures as JSON."""

from __future__ import annotations

import json
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivesim.bench.machine import machine_line


def measured_now() -> dict[str, Any]:
    """When and where a measurement ran: UTC date and time, the machine line, the 1/5/15-min load average."""
    return {
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": machine_line(),
        "load_average_1_5_15_min": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
    }


def write_json(path: Path, raw: dict[str, Any]) -> None:
    """Write the raw figures `raw` to `path` (its folder made if needed), with a "measured" entry (date, machine,
    load at writing) unless `raw` already has one."""
    data = raw if "measured" in raw else {"measured": measured_now(), **raw}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, default=str) + "\n")


def write_markdown(path: Path, lines: list[str], raw: dict[str, Any] | None = None) -> None:
    """Write the report's lines to `path` (its folder made if needed) and print them; with `raw`, also write the raw
    figures to the same name with .json (see `write_json`)."""
    text = "\n".join(lines)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(text)
    if raw is not None:
        write_json(path.with_suffix(".json"), raw)


def update_json(path: Path, key: str, raw: dict[str, Any]) -> None:
    """Set `key` of the JSON object in `path` (created when absent) to `raw` with its "measured" entry (date, machine,
    load), keeping the other keys: the raw figures of one section of a report written in parts."""
    data = json.loads(path.read_text()) if path.is_file() else {}
    data[key] = raw if "measured" in raw else {"measured": measured_now(), **raw}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, default=str) + "\n")


def table_records(header: str, rows: list[str]) -> list[dict[str, str]]:
    """The markdown table rows a script just formatted, as records keyed by the header's cells (the figures as the
    table shows them), for a script whose measuring code formats its rows directly."""
    names = [cell.strip() for cell in header.strip().strip("|").split("|")]
    return [dict(zip(names, (cell.strip() for cell in row.strip().strip("|").split("|")), strict=True)) for row in rows]
