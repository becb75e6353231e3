"""Shared by the tests: where the real recordings are, and running `drivesim` as a user would."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

# ../shared beside the checkout (tests skip, saying so, where it is absent).
REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


TESTS_DIR = Path(__file__).resolve().parent


def drivesim_ok(ws: Path, *args: str, timeout_s: float = 300) -> subprocess.CompletedProcess[str]:
    """Run `drivesim --workspace ws ARGS...` in a subprocess and assert it succeeded (showing its output if not)."""
    result = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert result.returncode == 0, f"drivesim {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}"
    return result


def drivesim_with_fakes(ws: Path, *args: str, timeout_s: float = 600, **env: str) -> subprocess.CompletedProcess[str]:
    """Run `drivesim --workspace ws ARGS...` in a subprocess that can import the tests' fake envs (tests/ on its
    PYTHONPATH), with `env` added to its environment; returns the finished process, whatever its exit code."""
    path = os.pathsep.join([str(TESTS_DIR), os.environ.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**os.environ, "PYTHONPATH": path, **env},
    )


def interruptible() -> None:
    """Popen's preexec_fn for a child the test will Ctrl-C: SIGINT back to its default. A shell starting a job in the
    background (`cmd &` without job control) ignores SIGINT in it, and an ignored signal stays ignored across exec,
    so the child would never see the test's SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_main(ws: Path, *args: str, monkeypatch: Any, capsys: Any) -> tuple[int, str]:
    """Run `drivesim --workspace ws ARGS` through `main` in this process (the CLI's error boundary, as a user meets
    it); returns (exit code, stderr). The signal handlers `main` installs are put back."""
    code, _, err = run_main_captured(ws, *args, monkeypatch=monkeypatch, capsys=capsys)
    return code, err


def run_main_captured(ws: Path, *args: str, monkeypatch: Any, capsys: Any) -> tuple[int, str, str]:
    """`run_main`, returning (exit code, stdout, stderr)."""
    from drivesim.cli.main import main

    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGTERM, signal.SIGHUP)}
    monkeypatch.setattr(sys, "argv", ["drivesim", "--workspace", str(ws), *args])
    capsys.readouterr()
    code = 0
    try:
        main()
    except SystemExit as e:
        code = 0 if e.code is None else int(e.code)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    out, err = capsys.readouterr()
    return code, out, err
