"""The paper cuts a new user hit, each as the user types it: the command in a subprocess, its output read from a pipe
(as in a log file), never a terminal."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TESTS_DIR = Path(__file__).parent


def drivesim(
    ws: Path, *args: str, env: dict[str, str] | None = None, timeout_s: float = 120
) -> subprocess.CompletedProcess[str]:
    """`drivesim --workspace ws ARGS...` in a subprocess, stdout and stderr read from pipes (not a terminal)."""
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**os.environ, "PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", **(env or {})},
    )


def make_dry_run(target: str, venv: Path) -> list[str]:
    """The commands `make TARGET` would run with the venv at `venv` (absent, so its set-up is due)."""
    done = subprocess.run(
        ["make", "-n", target, f"VENV={venv}"], cwd=REPO, capture_output=True, text=True, timeout=30, check=True
    )
    return [line for line in done.stdout.splitlines() if line.strip()]


# ---------------------------------------------------------------- 1. a set-up-only command


def test_make_install_sets_up_and_runs_nothing_else(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    setup = [f"VENV={venv} bash scripts/setup.sh", f"touch {venv}/.drivesim-installed"]
    assert make_dry_run("install", venv) == setup
    # demo and test still set up first, then do their work.
    assert make_dry_run("demo", venv)[:2] == setup and "run --preset demo" in make_dry_run("demo", venv)[2]
    assert make_dry_run("test", venv) == [*setup, f"{venv}/bin/python -m pytest -q"]
