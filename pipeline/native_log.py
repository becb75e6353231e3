"""Native libraries' messages (libjpeg's "Corrupt JPEG data", libpng warnings, FFmpeg's decoder errors, OpenCV's
log) kept out of the user's terminal and in a log file.

Those libraries write straight to file descriptor 2, not through Python, so the only way to move them is to point
descriptor 2 at the log while they run. Python's own `sys.stderr` (progress, warnings, drivesim's one error line)
is given a duplicate of the terminal's descriptor meanwhile, so it still reaches the user.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


@dataclass
class NativeLog:
    """The log the native messages went to and how many lines they were (known once the block has ended)."""

    path: Path
    lines: int = 0


@contextmanager
def native_messages_to(log_path: Path) -> Iterator[NativeLog]:
    """Within the block, what native code writes to stderr goes to `log_path` (appended to); Python's stderr does not.

    Where descriptor 2 cannot be redirected (it is closed, or the log cannot be created) the block runs unchanged.
    """
    log = NativeLog(Path(log_path))
    try:
        log.path.parent.mkdir(parents=True, exist_ok=True)
        log_fd = os.open(log.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        start = os.fstat(log_fd).st_size
        terminal_fd = os.dup(2)
    except OSError:
        yield log
        return
    python_stderr = sys.stderr
    python_stderr.flush()
    sys.stderr = os.fdopen(os.dup(terminal_fd), "w", buffering=1, encoding="utf-8", errors="backslashreplace")
    os.dup2(log_fd, 2)
    try:
        yield log
    finally:
        sys.stderr.flush()
        os.dup2(terminal_fd, 2)
        sys.stderr.close()
        sys.stderr = python_stderr
        os.close(terminal_fd)
        os.close(log_fd)
        log.lines = _lines_after(log.path, start)


def _lines_after(path: Path, offset: int) -> int:
    """Lines written to `path` after byte `offset`."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            return f.read().count(b"\n")
    except OSError:
        return 0
