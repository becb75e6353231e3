"""Worker processes that never outlive their parent: whatever ends the parent (Ctrl-C, SIGTERM, SIGHUP, SIGKILL, a
crash), its workers end too, so no orphan keeps writing into a work folder after the command is gone."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable
from typing import Any

PR_SET_PDEATHSIG = 1
"""prctl(2) option: the signal the kernel sends this process when its parent thread ends (Linux)."""
GROUP_SIGNALS = (signal.SIGINT, signal.SIGHUP)
"""Signals a terminal sends to the whole process group, which the parent handles for its workers."""
WATCHDOG_POLL_S = 0.5
"""How often the fallback watchdog (not Linux) checks that the parent is still there [s]."""


def end_with_parent(parent_pid: int) -> None:
    """Call first thing in a worker process: it gets SIGKILL the moment `parent_pid` ends, whatever killed it.

    Linux: the kernel's parent-death signal (prctl PR_SET_PDEATHSIG), which also fires on the parent's SIGKILL.
    Elsewhere: a daemon thread that polls the parent's pid. Ctrl-C and a hang-up are ignored here: the parent stops
    its workers itself (a terminal sends SIGINT, and SIGHUP when it closes, to the whole process group), so the
    episode in flight is not left half-written with a traceback.
    """
    for signum in GROUP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent_pid,), name="drivesim-parent-watch", daemon=True).start()
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(WATCHDOG_POLL_S)
    os._exit(1)


def stop_processes(processes: Iterable[Any], grace_s: float = 3.0) -> None:
    """Terminate `multiprocessing.Process`es (SIGTERM), then kill the ones still alive after `grace_s`."""
    processes = [p for p in processes if p is not None]
    for p in processes:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + grace_s
    for p in processes:
        p.join(timeout=max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(timeout=1.0)
