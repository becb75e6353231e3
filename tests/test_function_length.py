"""No function of the product is longer than `MAX_LINES` lines: a reader sees each one whole.

Counted from its `def` line (decorators aside) to its last line, docstring and comments included, nested functions
inside their parent. The simulator's envs are skipped while their tasks are split into classes (`SKIPPED`).

Run alone: `.venv/bin/pytest -q tests/test_function_length.py`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("cli", "pipeline", "stages", "sim", "policy", "chain", "bench")
MAX_LINES = 80
SKIPPED = ("sim/envs/",)


def long_functions(source: str, max_lines: int = MAX_LINES) -> list[tuple[str, int]]:
    """(qualified name, lines) of every function in `source` longer than `max_lines`."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = (child.end_lineno or child.lineno) - child.lineno + 1
                if lines > max_lines:
                    found.append((f"{prefix}{child.name}", lines))
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")

    visit(ast.parse(source), "")
    return found


def product_files() -> list[Path]:
    """The product's Python files under `FOLDERS`, less `SKIPPED`."""
    files = [f for folder in FOLDERS for f in sorted((REPO / folder).rglob("*.py"))]
    return [f for f in files if not str(f.relative_to(REPO)).startswith(SKIPPED)]


def test_no_product_function_is_over_the_limit() -> None:
    over = [
        f"{file.relative_to(REPO)}::{name} ({lines} lines)"
        for file in product_files()
        for name, lines in long_functions(file.read_text())
    ]
    assert over == [], f"{len(over)} functions over {MAX_LINES} lines:\n" + "\n".join(over)


def test_the_count_sees_methods_and_nested_functions() -> None:
    body = "\n".join(f"        x{i} = {i}" for i in range(80))
    source = f"class A:\n    def m(self):\n{body}\n\ndef f():\n    def g():\n{body}\n"
    assert long_functions(source) == [("A.m", 81), ("f", 82), ("f.g", 81)]
    assert long_functions("def short():\n    return 1\n") == []


@pytest.mark.parametrize("folder", FOLDERS)
def test_every_folder_has_code(folder: str) -> None:
    assert any((REPO / folder).rglob("*.py")), folder
