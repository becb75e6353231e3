"""Repository folders a benchmark script imports modules from by name: `tests/` (the recording writers and the
moderngl reference renderer the tests use) and a research probe's folder under `experiments/`."""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def use_folder(relative: str) -> Path:
    """Put the repository folder `relative` (e.g. "tests") first on the import path; returns it."""
    folder = REPO / relative
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder {folder}")
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    return folder
