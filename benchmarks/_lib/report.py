"""Writing a benchmark's markdown report."""

from __future__ import annotations

from pathlib import Path


def write_markdown(path: Path, lines: list[str]) -> None:
    """Write the report's lines to `path` (its folder made if needed) and print them."""
    text = "\n".join(lines)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(text)
