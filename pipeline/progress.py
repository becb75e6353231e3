"""Progress bars for long work, shared by every stage so they look the same.

On a terminal: a rich progress bar on stderr. Elsewhere (a log file, CI, `nohup`, Slurm): one plain line on stderr
every `PROGRESS_LOG_INTERVAL_S` seconds (`DRIVESIM_PROGRESS_S` overrides it), so a logged run is never silent for
long; stdout stays clean for what a command prints for scripts (`--json`).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskID,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(stderr=True)

PROGRESS_LOG_INTERVAL_S = 5.0
"""Seconds between two progress lines when stderr is not a terminal."""


def _log_interval_s() -> float:
    try:
        return max(0.05, float(os.environ.get("DRIVESIM_PROGRESS_S", PROGRESS_LOG_INTERVAL_S)))
    except ValueError:
        return PROGRESS_LOG_INTERVAL_S


def progress_line(progress: Progress, task: TaskID, began_s: float) -> str:
    """One plain line for a log: description, done / total with percent, elapsed and remaining time."""
    t = next(t for t in progress.tasks if t.id == task)
    elapsed_s = time.monotonic() - began_s
    line = f"{t.description}: {t.completed:.0f}"
    if t.total:
        line += f"/{t.total:.0f} ({100 * t.completed / t.total:.0f} %)"
    line += f", {elapsed_s:.0f} s elapsed"
    if t.fields.get("left_s") is not None:  # the caller's own estimate (e.g. training's, which has a time limit)
        line += f", about {t.fields['left_s']:.0f} s left"
    elif t.total and 0 < t.completed < t.total:
        line += f", about {elapsed_s * (t.total - t.completed) / t.completed:.0f} s left"
    return line


class _LineLogger:
    """Prints `progress_line` every `interval_s` from a daemon thread until stopped, and once more at the end."""

    def __init__(self, progress: Progress, task: TaskID, interval_s: float) -> None:
        self.progress, self.task, self.interval_s = progress, task, interval_s
        self.began_s = time.monotonic()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="drivesim-progress", daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(self.interval_s):
            console.print(progress_line(self.progress, self.task, self.began_s), highlight=False, soft_wrap=True)

    def __enter__(self) -> _LineLogger:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=1.0)
        if exc[0] is None:
            console.print(progress_line(self.progress, self.task, self.began_s), highlight=False, soft_wrap=True)


@contextmanager
def progress_bar(description: str, total: float | None) -> Iterator[tuple[Progress, TaskID]]:
    """A rich progress bar on stderr (a line every few seconds off a terminal); yields (progress, task id) that
    users advance with `progress.advance(task)`."""
    progress = Progress(
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TaskProgressColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal,
    )
    with progress:
        task = progress.add_task(description, total=total)
        if console.is_terminal:
            yield progress, task
        else:
            with _LineLogger(progress, task, _log_interval_s()):
                yield progress, task
