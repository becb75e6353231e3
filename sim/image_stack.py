"""Per-frame arrays stored as one compressed image per frame (an image stack), decoded one frame at a time on read.

The storage of the trace's frames, the preprocessed depth and the world's frames and depth; it lives in `sim` because
the simulator's loader (`sim/world.py`) reads it and `sim` imports only itself.

A drive's frames and depth maps are the bulk of a workspace: raw, a 640x400 RGB frame is 768 KB; as a JPEG at
quality 97 (4:4:4, no chroma subsampling) it is a seventh of that, and a depth map stored as the bit patterns of its
float16 values in a 16-bit PNG is lossless and, for smooth depth, a few KB. Readers get frames back one at a time
(`ImageStack[i]`), so memory stays flat in the drive's length and a random frame costs one decode.

File layout (`<name>.imgs`, little-endian):
    b"DSIMGS1\\n"                       magic
    the encoded images, back to back    frame i = bytes offsets[i]:offsets[i+1]
    offsets   uint64 (N + 1,)           from the start of the file
    meta      UTF-8 JSON                {"shape": [N, ...], "dtype": "uint8" | "float16", "codec": "jpeg" | "png",
                                         "quality": int | null}
    trailer   uint64 offsets position, uint64 meta length, b"DSIMGEND"
A file without its trailer (a write that did not finish) is refused when opened.

Codecs: "jpeg" for uint8 (H, W, 3) RGB frames (lossy, `quality`); "png" for uint8 (H, W, 3) RGB or (H, W) frames
and for float16 (H, W) depth (lossless: the float16 bits as a 16-bit grey PNG, so NaN and inf survive).
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np

SUFFIX = ".imgs"
_MAGIC = b"DSIMGS1\n"
_END = b"DSIMGEND"
_TRAILER_BYTES = 24
CODECS = ("jpeg", "png")
DTYPES = (np.dtype(np.uint8), np.dtype(np.float16))
# The JPEG quality of stored frames (the ingest and build-world config defaults say the same): novel views warped
# from frames stored at it stay within 0.1 dB of lossless frames (benchmarks/bench_frame_storage.py).
DEFAULT_JPEG_QUALITY = 97
# zlib level of the PNGs: level 1 is within a few % of level 3's size on depth maps and several times faster to write
_PNG_LEVEL = 1
_OPEN_LOCK = threading.Lock()


class ImageStackError(ValueError):
    """An image stack that cannot be read (truncated, not an image stack, a frame that does not decode)."""


def _check_layout(frame_shape: tuple[int, ...], dtype: np.dtype, codec: str) -> None:
    if codec not in CODECS:
        raise ValueError(f"codec {codec!r}: expected one of {CODECS}")
    if dtype == np.uint8 and (len(frame_shape) == 2 or (len(frame_shape) == 3 and frame_shape[2] == 3)):
        if codec == "jpeg" and len(frame_shape) != 3:
            raise ValueError("jpeg stores RGB frames (H, W, 3)")
        return
    if dtype == np.float16 and len(frame_shape) == 2 and codec == "png":
        return
    raise ValueError(f"{codec} cannot store {dtype} frames of shape {frame_shape} (uint8 RGB, or float16 (H, W) png)")


def encode_frame(frame: np.ndarray, codec: str, quality: int = DEFAULT_JPEG_QUALITY) -> bytes:
    """One frame's bytes: uint8 RGB (or grey) as JPEG/PNG, float16 (H, W) as its bits in a 16-bit PNG."""
    frame = np.ascontiguousarray(frame)
    if frame.dtype == np.float16:
        image = frame.view(np.uint16)
    elif frame.ndim == 3:
        image = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
    else:
        image = frame
    if codec == "jpeg":
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
        params += [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
        ok, buf = cv2.imencode(".jpg", image, params)
    else:
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, _PNG_LEVEL])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {frame.dtype} {frame.shape} frame as {codec}")
    return buf.tobytes()


def decode_frame(data: bytes, frame_shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """The frame `encode_frame` stored (a new, writable array of `frame_shape` and `dtype`)."""
    flags = cv2.IMREAD_UNCHANGED if len(frame_shape) == 2 else cv2.IMREAD_COLOR
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise ImageStackError("a frame does not decode (damaged data)")
    if dtype == np.float16:
        frame = image.view(np.float16) if image.dtype == np.uint16 else None
    elif image.ndim == 3:
        frame = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        frame = image
    if frame is None or frame.shape != tuple(frame_shape) or frame.dtype != dtype:
        got = "?" if frame is None else f"{frame.dtype} {frame.shape}"
        raise ImageStackError(f"a frame decodes to {got}, expected {dtype} {tuple(frame_shape)}")
    return frame


class ImageStackWriter:
    """Writes an (N, ...) array as an image stack one frame at a time with plain file writes (memory stays flat).

    :param path: the file to create (SUFFIX by convention).
    :param frame_shape: shape of one frame: (H, W, 3) or (H, W).
    :param dtype: uint8 or float16.
    :param codec: "jpeg" (uint8 RGB) or "png".
    :param quality: JPEG quality (1-100).
    """

    def __init__(
        self,
        path: Path,
        frame_shape: tuple[int, ...],
        dtype: np.dtype | type,
        codec: str,
        quality: int = DEFAULT_JPEG_QUALITY,
    ) -> None:
        self.path = Path(path)
        self.frame_shape = tuple(int(s) for s in frame_shape)
        self.dtype = np.dtype(dtype)
        self.codec = codec
        self.quality = int(quality)
        _check_layout(self.frame_shape, self.dtype, codec)
        self._offsets = [len(_MAGIC)]
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 (closed by close())
        self._file.write(_MAGIC)

    @property
    def rows_written(self) -> int:
        """Frames written so far."""
        return len(self._offsets) - 1

    def write(self, frame: np.ndarray) -> None:
        """Append the next frame (must have the frame shape and dtype)."""
        if frame.shape != self.frame_shape or frame.dtype != self.dtype:
            raise ValueError(f"frame {frame.shape} {frame.dtype} does not match {self.frame_shape} {self.dtype}")
        data = encode_frame(frame, self.codec, self.quality)
        self._file.write(data)
        self._offsets.append(self._offsets[-1] + len(data))

    def write_rows(self, frames: np.ndarray) -> None:
        """Append several frames (B, ...)."""
        for frame in frames:
            self.write(frame)

    def close(self) -> None:
        """Write the index and the trailer and close the file (the stack is readable only after this)."""
        if self._file.closed:
            return
        meta = {
            "shape": [self.rows_written, *self.frame_shape],
            "dtype": self.dtype.name,
            "codec": self.codec,
            "quality": self.quality if self.codec == "jpeg" else None,
        }
        meta_bytes = json.dumps(meta).encode()
        index_at = self._offsets[-1]
        self._file.write(np.asarray(self._offsets, dtype="<u8").tobytes())
        self._file.write(meta_bytes)
        self._file.write(np.asarray([index_at, len(meta_bytes)], dtype="<u8").tobytes() + _END)
        self._file.close()

    def abort(self) -> None:
        """Close without finishing (the file stays unreadable as a stack)."""
        self._file.close()


def read_meta(path: Path) -> tuple[dict[str, Any], np.ndarray]:
    """(meta, offsets) of the image stack at `path`, reading only its index; ImageStackError when it is not one."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            if size < len(_MAGIC) + _TRAILER_BYTES:
                raise ImageStackError(f"{path}: too short for an image stack (truncated)")
            f.seek(0)
            magic = f.read(len(_MAGIC))
            f.seek(size - _TRAILER_BYTES)
            trailer = f.read(_TRAILER_BYTES)
            if magic != _MAGIC or trailer[16:] != _END:
                raise ImageStackError(f"{path}: not a finished image stack (truncated or another kind of file)")
            index_at, meta_len = (int(v) for v in np.frombuffer(trailer[:16], "<u8"))
            f.seek(index_at)
            index_bytes = f.read(size - _TRAILER_BYTES - meta_len - index_at)
            meta = json.loads(f.read(meta_len).decode())
    except (UnicodeDecodeError, json.JSONDecodeError, OverflowError, ValueError) as e:
        if isinstance(e, ImageStackError):
            raise
        raise ImageStackError(f"{path}: damaged image stack index ({e})") from e
    offsets = np.frombuffer(index_bytes, "<u8").astype(np.int64)
    _check_meta(path, meta, offsets, index_at)
    return meta, offsets


def _check_meta(path: Path, meta: Any, offsets: np.ndarray, index_at: int) -> None:
    try:
        shape = tuple(int(s) for s in meta["shape"])
        dtype = np.dtype(meta["dtype"])
        _check_layout(shape[1:], dtype, meta["codec"])
    except (KeyError, TypeError, ValueError) as e:
        raise ImageStackError(f"{path}: damaged image stack header ({e})") from e
    if len(offsets) != shape[0] + 1 or offsets[0] != len(_MAGIC) or offsets[-1] != index_at:
        raise ImageStackError(f"{path}: damaged image stack index (offsets do not match {shape[0]} frames)")
    if np.any(np.diff(offsets) <= 0):
        raise ImageStackError(f"{path}: damaged image stack index (offsets not increasing)")


class ImageStack:
    """A read-only (N, ...) array backed by an image stack: `stack[i]` decodes frame i; `stack[a:b:c]` is a lazy
    view; `stack[[i, j]]` and `np.asarray(stack)` decode the frames asked for into one array.

    Safe to share between threads (reads are positioned) and to pickle (the file is reopened by path).

    :param path: the `.imgs` file.
    """

    def __init__(self, path: Path | str, _rows: np.ndarray | None = None, _meta: tuple | None = None) -> None:
        self._fd: int | None = None
        self.path = Path(path)
        meta, offsets = _meta if _meta is not None else read_meta(self.path)
        self._meta = (meta, offsets)
        self.codec: str = meta["codec"]
        self.dtype = np.dtype(meta["dtype"])
        self.frame_shape = tuple(int(s) for s in meta["shape"][1:])
        self._offsets = offsets
        self._rows = np.arange(len(offsets) - 1) if _rows is None else _rows

    @property
    def shape(self) -> tuple[int, ...]:
        """(N, *frame shape) of this view."""
        return (len(self._rows), *self.frame_shape)

    @property
    def ndim(self) -> int:
        """Number of dimensions."""
        return 1 + len(self.frame_shape)

    def __len__(self) -> int:
        return len(self._rows)

    def encoded_bytes(self, i: int) -> bytes:
        """The stored bytes of frame i of this view."""
        row = int(self._rows[i])
        start, stop = int(self._offsets[row]), int(self._offsets[row + 1])
        if self._fd is None:
            with _OPEN_LOCK:  # threads reading a fresh stack at once open it once
                if self._fd is None:
                    self._fd = os.open(self.path, os.O_RDONLY)
        data = os.pread(self._fd, stop - start, start)
        if len(data) != stop - start:
            raise ImageStackError(f"{self.path}: frame {row} is cut short (truncated file)")
        return data

    def frame(self, i: int) -> np.ndarray:
        """Frame i of this view, decoded."""
        try:
            return decode_frame(self.encoded_bytes(i), self.frame_shape, self.dtype)
        except ImageStackError as e:
            raise ImageStackError(f"{self.path}: frame {int(self._rows[i])}: {e}") from None

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, tuple):  # (frames, then indices within each frame), as on an ndarray
            head = self[key[0]]
            if isinstance(key[0], int | np.integer):
                return head[key[1:]]
            frame_axes = np.asarray(head).ndim - len(self.frame_shape)
            return np.asarray(head)[(slice(None),) * frame_axes + tuple(key[1:])]
        if isinstance(key, int | np.integer):
            n = len(self._rows)
            if not -n <= key < n:
                raise IndexError(f"index {key} is out of bounds for {n} frames")
            return self.frame(int(key) % n)
        if isinstance(key, slice):
            return ImageStack(self.path, self._rows[key], self._meta)
        index = np.asarray(key)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        return self._decode_many(index.astype(np.int64).ravel()).reshape(*index.shape, *self.frame_shape)

    def _decode_many(self, index: np.ndarray) -> np.ndarray:
        out = np.empty((len(index), *self.frame_shape), self.dtype)
        for k, i in enumerate(index):
            out[k] = self[int(i)]
        return out

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self._rows)):
            yield self.frame(i)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = self._decode_many(np.arange(len(self._rows)))
        return out if dtype is None else out.astype(dtype)

    def close(self) -> None:
        """Close the file (reopened on the next read)."""
        if getattr(self, "_fd", None) is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:
        with contextlib.suppress(OSError):
            self.close()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_fd": None}

    def __repr__(self) -> str:
        return f"ImageStack({str(self.path)!r}, shape={self.shape}, dtype={self.dtype}, codec={self.codec!r})"


def stack_path(folder: Path, stem: str) -> Path:
    """Where the image stack of `stem` lives in `folder` (`<stem>.imgs`)."""
    return Path(folder) / f"{stem}{SUFFIX}"


def stored_file(folder: Path, stem: str) -> Path | None:
    """The file holding `stem` in `folder`: its image stack, or an .npy array written by an older version; None."""
    for path in (stack_path(folder, stem), Path(folder) / f"{stem}.npy"):
        if path.is_file():
            return path
    return None


def open_frames(path: Path) -> np.ndarray | ImageStack:
    """The per-frame array in `path`: an ImageStack for `.imgs`, a read-only memmap for `.npy`.

    :raises ImageStackError: (a ValueError) a damaged stack; ValueError/OSError from numpy for a damaged .npy.
    """
    path = Path(path)
    if path.suffix == SUFFIX:
        return ImageStack(path)
    return np.load(path, mmap_mode="r")


def stored_layout(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of the per-frame array in `path` (.imgs or .npy), reading only its header or index."""
    path = Path(path)
    if path.suffix == SUFFIX:
        meta, _ = read_meta(path)
        return tuple(int(s) for s in meta["shape"]), np.dtype(meta["dtype"])
    array = np.load(path, mmap_mode="r")
    return tuple(array.shape), array.dtype
