"""Paths the user names (a recording, a --config file, the workspace) checked for what they are before anything
opens them: a FIFO would block the first read forever, a device such as /dev/zero never ends or is not a folder."""

from __future__ import annotations

import stat
from pathlib import Path

from drivesim.pipeline.errors import InputError


def special_kind(path: Path) -> str | None:
    """What a FIFO, socket or device path is ("a FIFO (named pipe)", "a socket", "a device"); None for a regular
    file, a folder or nothing."""
    try:
        mode = Path(path).stat().st_mode
    except OSError:
        return None
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return None


def refuse_special_file(path: Path, expected: str) -> None:
    """InputError (one line, exit 2) when `path` is a FIFO, socket or device; `expected` says what to give instead
    ("a recording file or folder")."""
    kind = special_kind(path)
    if kind is not None:
        raise InputError(f"is {kind}, not a regular file or folder; give {expected}", path)
