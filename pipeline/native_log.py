"""Native libraries' messages (libjpeg's "Corrupt JPEG data", libpng warnings, FFmpeg's decoder errors, OpenCV's
log) kept out of the user's terminal and in a log file.

Those libraries write straight to file descriptor 2, not through Python, so the only way to move them is to point
descriptor 2 at the log while they run. Python's own `sys.stderr` (progress, warnings, drivesim's one error line)
is given a duplicate of the terminal's descriptor meanwhile, so it still reaches the user.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any


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
    _REDIRECTS.append(log.path)
    try:
        yield log
    finally:
        _REDIRECTS.pop()
        sys.stderr.flush()
        os.dup2(terminal_fd, 2)
        sys.stderr.close()
        sys.stderr = python_stderr
        os.close(terminal_fd)
        os.close(log_fd)
        log.lines = _lines_after(log.path, start)


_REDIRECTS: list[Path] = []  # the logs descriptor 2 points at, innermost last


class _Gate:
    """Many shared holders or one exclusive holder at a time, a waiting exclusive one served first."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._shared = 0
        self._exclusive = False
        self._waiting = 0

    @contextmanager
    def shared(self) -> Iterator[None]:
        with self._cond:
            self._cond.wait_for(lambda: not self._exclusive and not self._waiting)
            self._shared += 1
        try:
            yield
        finally:
            with self._cond:
                self._shared -= 1
                self._cond.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        with self._cond:
            self._waiting += 1
            self._cond.wait_for(lambda: not self._exclusive and not self._shared)
            self._waiting -= 1
            self._exclusive = True
        try:
            yield
        finally:
            with self._cond:
                self._exclusive = False
                self._cond.notify_all()


_GATE = _Gate()


def _stderr_size() -> int | None:
    """Bytes in the log descriptor 2 points at, or None when no `native_messages_to` block is in force."""
    return os.fstat(2).st_size if _REDIRECTS else None


def call_watched(native_call: Callable[..., Any], *args: Any) -> tuple[Any, str]:
    """(the call's result, what native code wrote to stderr during it) inside a `native_messages_to` block; outside
    one the text is always "".

    Watched calls run side by side (the common case: nothing is written); when the log grew meanwhile, the call is
    run again alone, so the text is this call's own and not a concurrent one's.
    """
    with _GATE.shared():
        before = _stderr_size()
        result = native_call(*args)
        quiet = before is None or _stderr_size() == before
    if quiet:
        return result, ""
    with _GATE.exclusive():
        start = _stderr_size() or 0
        result = native_call(*args)
        with open(_REDIRECTS[-1], "rb") as f:
            f.seek(start)
            said = f.read().decode("utf-8", "replace")
    return result, said


def _lines_after(path: Path, offset: int) -> int:
    """Lines written to `path` after byte `offset`."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            return f.read().count(b"\n")
    except OSError:
        return 0
