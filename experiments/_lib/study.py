"""What the studies' scripts share: their result arguments (--name, --notes, repeatable KEY=VALUE settings) and
writing a result's JSON beside the study's markdown table.

A study script puts this folder on `sys.path` and imports `study`.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any


def add_result_arguments(parser: argparse.ArgumentParser, study: str) -> None:
    """--name (the result's file: <study>_<name>.json) and --notes (a paragraph printed under the table)."""
    parser.add_argument("--name", required=True, help=f"name of the result ({study}_<name>.json)")
    parser.add_argument("--notes", default="", help="a paragraph printed under the table")


def add_settings_argument(parser: argparse.ArgumentParser, flag: str, help_text: str) -> None:
    """A repeatable `flag KEY=VALUE` option collected into a list (empty when not given)."""
    parser.add_argument(flag, action="append", default=[], metavar="KEY=VALUE", help=help_text)


def save_result(results: Path, study: str, result: dict[str, Any], write_markdown: Callable[[], None]) -> Path:
    """Write `result` as <results>/<study>_<name>.json, remake the study's markdown and say where both are."""
    path = results / f"{study}_{result['name']}.json"
    path.write_text(json.dumps(result, indent=1))
    write_markdown()
    print(f"wrote {path} and {results / f'{study}.md'}")
    return path
