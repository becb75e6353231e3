"""Hardening of the chain's inputs: a full disk under memmapped writes, bad pose timing, damaged worlds and config
files, damaged frames and videos, files that are not regular files, names that would forge a line, and native
libraries' chatter. Each case ends in one clear line (exit 2, or 1 for a full disk) and no half-written artifact.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
from test_preprocess_stage_fakes import install_fake_poses, make_trace

from drivesim.cli.main import main
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess import stage as preprocess_stage
from drivesim.stages.preprocess.config import PreprocessConfig


def _cli(ws: Path, *args: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> tuple[int, str]:
    """Run `drivesim --workspace ws ARGS` through `main` (the error boundary); returns (exit code, stderr)."""
    previous = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(sys, "argv", ["drivesim", "--workspace", str(ws), *args])
    capsys.readouterr()
    code = 0
    try:
        main()
    except SystemExit as e:
        code = 0 if e.code is None else int(e.code)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return code, capsys.readouterr().err


def _error_lines(err: str) -> list[str]:
    """The error lines of stderr (asserting there is no traceback among the rest)."""
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line.startswith("error:")]


# ---------------------------------------------------------------- a full disk under memmapped writes


def _disk_full(monkeypatch: pytest.MonkeyPatch) -> None:
    """The kernel refuses to allocate: what posix_fallocate says on a full disk."""

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)


@pytest.mark.parametrize("stage", ["preprocess", "build-world"])
def test_full_disk_under_a_memmap_is_one_line_and_keeps_nothing(tmp_path, monkeypatch, capsys, stage) -> None:
    """The depth and frame memmaps of preprocess and build-world reserve their space first: a full disk is the
    one-line disk-full error (exit 1), not a SIGBUS, and no temporary folder or artifact is left."""
    ws = Workspace(tmp_path / "ws")
    make_trace(ws)
    install_fake_poses(monkeypatch)
    if stage == "build-world":
        preprocess_stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
    _disk_full(monkeypatch)
    args = [stage, "--set", "depth.method=plane"] if stage == "preprocess" else [stage]
    code, err = _cli(ws.root, *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 1 and len(lines) == 1 and "disk full" in lines[0] and str(ws.root) in lines[0], err
    artifact = "preprocessed" if stage == "preprocess" else "world"
    assert not list(ws.root.glob(".tmp-*")) and not ws.artifact_dir(artifact).exists()


def test_reserved_memmap_falls_back_to_zeros_where_the_file_system_cannot_allocate(tmp_path, monkeypatch) -> None:
    """Where posix_fallocate is unsupported the space is still claimed, by writing zeros through the file."""
    from drivesim.pipeline.npy_files import open_reserved_memmap

    def unsupported(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.EOPNOTSUPP, "Operation not supported")

    monkeypatch.setattr(os, "posix_fallocate", unsupported)
    out = open_reserved_memmap(tmp_path / "a.npy", np.float32, (3, 64, 64))
    out[1] = 2.5
    out.flush()
    del out
    back = np.load(tmp_path / "a.npy")
    assert back.shape == (3, 64, 64) and back[1].min() == 2.5 and back[0].max() == 0.0
    assert os.stat(tmp_path / "a.npy").st_blocks * 512 >= back.nbytes  # allocated, not sparse
