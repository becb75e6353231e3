"""Handing freed heap memory back to the operating system."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys


@functools.cache
def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.malloc_trim  # noqa: B018  (glibc only: musl has no malloc_trim)
    except (OSError, AttributeError, TypeError):
        return None
    return libc


def release_freed_memory() -> bool:
    """Return the heap pages freed by a large build back to the OS (glibc's malloc_trim); False where unsupported.

    glibc keeps the pages of many freed medium-sized arrays (under its mmap threshold, which rises as arrays are freed)
    in the process, so a build's temporaries stay in its resident memory for its whole life; numpy and Python offer no
    call for this, hence ctypes."""
    libc = _libc()
    return bool(libc is not None and libc.malloc_trim(0))
