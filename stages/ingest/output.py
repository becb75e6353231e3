"""Writing the trace files: frames streamed into image stacks, arrays into .npy, growable series arrays, JSON (the
trace's calibration and sources are assembled by writer.TraceWriter)."""

from __future__ import annotations

import json
import re
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from drivesim.sim.image_stack import DEFAULT_JPEG_QUALITY, ImageStackWriter, stack_path
from drivesim.stages.ingest.stamps import ordered_series


@dataclass
class IngestResult:
    """What an ingest produced: the manifest summary and notes for the user (e.g. which camera was chosen)."""

    summary: dict[str, Any]
    notes: list[str] = field(default_factory=list)


_NUMBER_LIST = re.compile(r"\[\s*((?:-?[\d.eE+-]+|null)(?:,\s*(?:-?[\d.eE+-]+|null))*)\s*\]")


def npy_header(shape: tuple[int, ...], dtype: np.dtype, size_bytes: int) -> bytes:
    """An .npy version 1.0 header for `shape` and `dtype`, padded to exactly `size_bytes` (a multiple of 64).

    numpy's own writer pads to the next multiple of 64, so a header rewritten with a smaller row count could change
    length and move the data; a fixed size lets a stream writer announce its rows up front and correct them at the end.
    """
    text = repr({"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}).encode()
    padding = size_bytes - 10 - len(text) - 1
    if padding < 0:
        raise ValueError(f"an .npy header for {shape} does not fit in {size_bytes} bytes")
    return b"\x93NUMPY\x01\x00" + (size_bytes - 10).to_bytes(2, "little") + text + b" " * padding + b"\n"


def npy_header_size(shape: tuple[int, ...], dtype: np.dtype) -> int:
    """The fixed header size (a multiple of 64 bytes) that fits `shape` and any smaller row count."""
    return -(-(len(npy_header(shape, dtype, 4096).rstrip(b" \n")) + 1) // 64) * 64


class NpyStreamWriter:
    """Writes an (N, ...) array into an .npy file one row at a time, N announced up front.

    The header is written first and rows appended with plain file writes: a writable memmap would do the same
    I/O, but its dirty pages count toward the process's resident memory until the kernel writes them back,
    which for an hour of frames is gigabytes; file writes keep memory flat. When fewer rows than announced were
    written (frames skipped as unreadable), `close()` rewrites the header with the real row count.

    :param path: the .npy file to create.
    :param shape: full array shape, first axis = the most rows that will be written.
    :param dtype: element type.
    """

    def __init__(self, path: Path, shape: tuple[int, ...], dtype: np.dtype | type) -> None:
        self.path = path
        self.shape = shape
        self.dtype = np.dtype(dtype)
        self.row_shape = shape[1:]
        self.rows_written = 0
        self._header_bytes = npy_header_size(shape, self.dtype)
        self._file: BinaryIO = open(path, "wb")  # noqa: SIM115 (closed by close())
        self._file.write(npy_header(shape, self.dtype, self._header_bytes))

    def write(self, row: np.ndarray) -> None:
        """Append the next row (must have the row shape and dtype)."""
        if row.shape != self.row_shape or row.dtype != self.dtype:
            raise ValueError(f"row {row.shape} {row.dtype} does not match {self.row_shape} {self.dtype}")
        if self.rows_written >= self.shape[0]:
            raise ValueError(f"more rows than the {self.shape[0]} announced")
        self._file.write(memoryview(np.ascontiguousarray(row)).cast("B"))
        self.rows_written += 1

    def close(self) -> None:
        """Close the file; the header then says how many rows were written."""
        if self._file.closed:
            return
        if self.rows_written != self.shape[0]:
            self._file.seek(0)
            shape = (self.rows_written, *self.row_shape)
            self._file.write(npy_header(shape, self.dtype, self._header_bytes))
        self._file.close()


class GrowableArray:
    """A numpy array that grows by doubling: series accumulate without lists of Python objects.

    :param row_shape: shape of one row.
    :param dtype: element type.
    """

    def __init__(self, row_shape: tuple[int, ...] = (), dtype: np.dtype | type = np.float64) -> None:
        self._data = np.empty((64, *row_shape), dtype=dtype)
        self._size = 0

    def append(self, row: Any) -> None:
        """Add one row."""
        if self._size == len(self._data):
            grown = np.empty((2 * len(self._data), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size] = row
        self._size += 1

    def __len__(self) -> int:
        return self._size

    def array(self) -> np.ndarray:
        """The rows so far as one array (a copy)."""
        return self._data[: self._size].copy()


class Series:
    """Named growable columns of one time series, saved as an .npz sorted by time.

    :param columns: column name -> (row shape, dtype); `t_ns` (int64) is always added.
    """

    def __init__(self, columns: dict[str, tuple[tuple[int, ...], np.dtype | type]]) -> None:
        self.columns = {"t_ns": GrowableArray((), np.int64)}
        for name, (shape, dtype) in columns.items():
            self.columns[name] = GrowableArray(shape, dtype)

    def append(self, **values: Any) -> None:
        """Add one sample: every column must be given."""
        for name, column in self.columns.items():
            column.append(values[name])

    def __len__(self) -> int:
        return len(self.columns["t_ns"])

    def save(self, path: Path) -> int:
        """Write the series as .npz sorted by time, one sample per stamp (`stamps.ordered_series`: a position stream
        named by the file, e.g. odometry.npz, whose stamps cannot time it is refused); the samples written."""
        arrays = ordered_series({name: col.array() for name, col in self.columns.items()}, Path(path).stem)
        np.savez(path, **arrays)
        return len(arrays["t_ns"])


def empty_gps_series() -> Series:
    """Columns of gps.npz (see trace.py)."""
    return Series(
        {
            "lat_deg": ((), np.float64),
            "lon_deg": ((), np.float64),
            "alt_m": ((), np.float64),
            "status": ((), np.int8),
            "covariance_m2": ((3, 3), np.float64),
            "covariance_type": ((), np.uint8),
        }
    )


def empty_imu_series() -> Series:
    """Columns of imu.npz (see trace.py)."""
    return Series(
        {
            "angular_velocity_radps": ((3,), np.float64),
            "linear_acceleration_mps2": ((3,), np.float64),
            "orientation_xyzw": ((4,), np.float64),
        }
    )


def empty_speed_series() -> Series:
    """Columns of speed.npz (see trace.py)."""
    return Series({"speed_mps": ((), np.float64)})


def empty_odometry_series() -> Series:
    """Columns of odometry.npz (see trace.py)."""
    return Series(
        {
            "position_m": ((3,), np.float64),
            "orientation_xyzw": ((4,), np.float64),
            "linear_velocity_mps": ((3,), np.float64),
            "angular_velocity_radps": ((3,), np.float64),
        }
    )


def write_json(path: Path, value: dict[str, Any]) -> None:
    """Pretty JSON with numpy values turned into lists/floats."""

    def default(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            return obj.tolist()
        if isinstance(obj, np.generic):
            return obj.item()
        raise TypeError(f"not JSON serialisable: {type(obj).__name__}")

    text = json.dumps(value, indent=2, default=default)
    # matrix rows on one line each: [[fx, 0, cx], ...] stays readable
    text = _NUMBER_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    path.write_text(text + "\n")


class OrderedPipeline:
    """Runs `work(item)` on worker threads and hands the results to `sink` in submission order.

    Frame decoding, undistortion and resizing are OpenCV calls that release the GIL, so they overlap with reading
    the next messages; at most `max_in_flight` items are held, keeping memory bounded.

    :param work: item -> result, run on a worker thread.
    :param sink: result -> None, run on the caller's thread in order.
    :param workers: worker threads.
    :param max_in_flight: items submitted but not yet sunk.
    """

    def __init__(
        self, work: Callable[[Any], Any], sink: Callable[[Any], None], workers: int = 2, max_in_flight: int = 6
    ) -> None:
        self._work = work
        self._sink = sink
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ingest")
        self._pending: deque[Future[Any]] = deque()
        self._max = max_in_flight

    def submit(self, item: Any) -> None:
        """Queue one item; sinks finished results first when too many are in flight."""
        self._pending.append(self._pool.submit(self._work, item))
        while len(self._pending) >= self._max or (self._pending and self._pending[0].done()):
            self._sink(self._pending.popleft().result())

    def finish(self) -> None:
        """Sink every remaining result."""
        while self._pending:
            self._sink(self._pending.popleft().result())

    def close(self) -> None:
        """Stop the workers (pending work is cancelled; used on errors and Ctrl-C)."""
        for future in self._pending:
            future.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)


class FrameStore:
    """frames.imgs (working resolution) and, when asked, frames_original.imgs (recorded resolution), frame by frame,
    each frame one compressed image (`sim/image_stack.py`).

    :param out_dir: the trace folder.
    :param n_frames: frame count (the most frames that will be written).
    :param size: (width, height) of frames.imgs.
    :param original_size: (width, height) of frames_original.imgs, or None to not keep originals.
    :param stem: file name stem: "frames", or "frames_right" for a stereo rig's second camera.
    :param storage: (codec, JPEG quality) of the frames: ("jpeg", 95) or ("png", ...) for lossless.
    """

    def __init__(
        self,
        out_dir: Path,
        n_frames: int,
        size: tuple[int, int],
        original_size: tuple[int, int] | None,
        stem: str = "frames",
        storage: tuple[str, int] = ("jpeg", DEFAULT_JPEG_QUALITY),
    ) -> None:
        codec, quality = storage
        self.n_frames = n_frames
        self.frames = ImageStackWriter(stack_path(out_dir, stem), (size[1], size[0], 3), np.uint8, codec, quality)
        self.originals = None
        if original_size is not None:
            shape = (original_size[1], original_size[0], 3)
            self.originals = ImageStackWriter(stack_path(out_dir, f"{stem}_original"), shape, np.uint8, codec, quality)

    def write(self, frames: tuple[np.ndarray, np.ndarray | None]) -> None:
        """Append (working frame, original frame or None)."""
        if self.frames.rows_written >= self.n_frames:
            raise ValueError(f"more frames than the {self.n_frames} announced")
        self.frames.write(frames[0])
        if self.originals is not None:
            self.originals.write(frames[1])

    def close(self) -> None:
        """Finish the files."""
        self.frames.close()
        if self.originals is not None:
            self.originals.close()
