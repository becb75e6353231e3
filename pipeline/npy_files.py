"""Writable .npy memmaps whose disk space is reserved before the first write.

A memmap created with `np.lib.format.open_memmap` is a sparse file: the kernel finds the blocks only when a page is
written back, and on a full disk it has no error code to give, so the process dies of SIGBUS with no message and its
temporary folder left behind. Reserving the blocks up front (`posix_fallocate`, or zeros written with plain file
writes where the file system cannot allocate) turns a full disk into an ordinary OSError(ENOSPC) before anything is
written, which the workspace reports as its one disk-full line.

A memmap's pages stay in the process's resident memory once touched (read or written) until the kernel needs the
memory back, so a pass over an hour of frames would show gigabytes of RSS; `release_pages` after each chunk keeps a
streaming pass's memory flat (the data stays in the file and the page cache).
"""

from __future__ import annotations

import errno
import mmap
import os
from pathlib import Path

import numpy as np

_ZERO_CHUNK_BYTES = 1 << 22
# errors meaning "this file system cannot preallocate", where zeros written through the file are the fallback
_NO_FALLOCATE = {errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}


def reserve_file_space(path: Path) -> None:
    """Allocate every block of the file at `path` up to its current size.

    :raises OSError: ENOSPC (with the file name) when the disk cannot hold it.
    """
    size_bytes = os.path.getsize(path)
    with open(path, "r+b") as f:
        try:
            _allocate(f.fileno(), size_bytes)
        except OSError as e:
            if e.errno not in _NO_FALLOCATE:
                raise OSError(e.errno, os.strerror(e.errno or 0), str(path)) from e
            _write_zeros(f, size_bytes, path)


def _allocate(fd: int, size_bytes: int) -> None:
    if not hasattr(os, "posix_fallocate"):  # macOS, Windows: let the caller write zeros
        raise OSError(errno.ENOSYS, "posix_fallocate is not available")
    os.posix_fallocate(fd, 0, size_bytes)


def _write_zeros(f, size_bytes: int, path: Path) -> None:
    """Fill the file with zeros through ordinary writes, which report ENOSPC instead of raising SIGBUS later."""
    f.seek(0, os.SEEK_SET)
    first = f.read(_ZERO_CHUNK_BYTES)  # the .npy header and the start of the (still sparse) data
    zeros = bytes(_ZERO_CHUNK_BYTES)
    try:
        f.seek(0, os.SEEK_SET)
        f.write(first)
        done = len(first)
        while done < size_bytes:
            step = min(_ZERO_CHUNK_BYTES, size_bytes - done)
            f.write(zeros[:step])
            done += step
        f.flush()
        os.fsync(f.fileno())
    except OSError as e:
        raise OSError(e.errno, os.strerror(e.errno or 0), str(path)) from e


def open_reserved_memmap(path: Path, dtype: np.dtype | type, shape: tuple[int, ...]) -> np.memmap:
    """A new writable .npy memmap of `shape` and `dtype` at `path`, its disk space reserved.

    :raises OSError: ENOSPC when the disk cannot hold the whole array; the file is removed then.
    """
    out = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    try:
        reserve_file_space(Path(path))
    except BaseException:
        del out
        Path(path).unlink(missing_ok=True)
        raise
    return out


def release_pages(array: np.ndarray) -> None:
    """Drop the pages of a memory-mapped `array` (or a view of one) from this process's resident memory.

    The data is kept: a read-only mapping rereads the file, and written pages of a shared (w+ or r+) mapping stay in
    the page cache until they are written back. Arrays that are not memory-mapped are left alone.
    """
    mapping = getattr(array, "_mmap", None)
    if isinstance(mapping, mmap.mmap) and hasattr(mmap, "MADV_DONTNEED") and not mapping.closed:
        mapping.madvise(mmap.MADV_DONTNEED)
