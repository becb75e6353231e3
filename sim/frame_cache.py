"""The view's prepared source frames stored once beside the world, so that a view never prepares a frame again.

The CPU view warps each recorded frame from a prepared form (`ViewSynthesizer._frame_arrays`): reduced to the warp's
source resolution and widened left and right from neighbouring frames. Preparing a frame costs about a millisecond,
several times an env step; a world of more frames than the view keeps in memory would pay it at nearly every step.
This module writes every frame's prepared form to a file once; views read a frame when they need it (one read from
the page cache that all env processes on the machine share, then an LZ4 decode: tens of microseconds), and a process
keeps in memory only the frames it holds.

Files, in `<world>/view_cache/<key>/` (key: `cache_key`):
    frames.bin   per frame, one LZ4 block of
                 rgb       uint8   (H, W + 2m, 3)  the widened frame
                 depth     float16 (H, W + 2m)     its depth (m); the view rounds a prepared frame's depth to
                                                   float16 itself (`ViewSynthesizer._frame_arrays`), so this loses
                                                   nothing
    offsets.npy  int64 (N + 1,): where frame i's block starts (i) and ends (i + 1)
    stats.npy    float64 (N, 4): the frame's own mean colour in [0, 1] (3) and its smallest finite depth (m)
    layout.json  H, W, m, the frame count and what the key was made from
LZ4 (the block format of the `lz4` package, which the bag and MCAP readers already use) stores a frame in about 40 %
of its bytes on synthetic drives and 55 % on real ones and decodes it in tens of microseconds: a read costs a few
percent of a car-drawn env step, where preparing the frame again costs a millisecond.
The folder appears by one rename once complete, so a reader never sees a half-written cache; builders of one key
take turns on `<key>.lock`. The reader returns the arrays the view prepares itself, to the bit (tested).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import lz4.block
import numpy as np

__all__ = ["CACHE_DIR_NAME", "FrameLayout", "PreparedFrames", "cache_key", "open_prepared_frames"]

CACHE_DIR_NAME = "view_cache"
# Raised whenever what a record holds or how a frame is prepared changes, so that older caches are never read.
FORMAT_VERSION = 5
_WRITE_CHUNK_FRAMES = 64  # frames encoded per write call while building
_LOG = logging.getLogger(__name__)

Prepare = Callable[[int], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""A frame index -> (rgb (H, W + 2m, 3) uint8, depth (H, W + 2m) in m, mean colour (3,)), as the view prepares it."""


@dataclass(frozen=True)
class FrameLayout:
    """The shape of one prepared frame and how it is encoded in frames.bin.

    :param height_px: H. :param width_px: W, the recorded frame at the source resolution. :param margin_px: m, added
    on each side.
    """

    height_px: int
    width_px: int
    margin_px: int

    @cached_property
    def wide_width_px(self) -> int:
        """W + 2m."""
        return self.width_px + 2 * self.margin_px

    @cached_property
    def rgb_bytes(self) -> int:
        """Bytes of the widened rgb."""
        return self.height_px * self.wide_width_px * 3

    @cached_property
    def depth_bytes(self) -> int:
        """Bytes of its float16 depth."""
        return self.height_px * self.wide_width_px * 2

    @cached_property
    def depth_offset(self) -> int:
        """Where the depth starts in a decoded frame (after the rgb, 8-byte aligned)."""
        return -(-self.rgb_bytes // 8) * 8

    def encode(self, rgb: np.ndarray, depth_m: np.ndarray) -> bytes:
        """One prepared frame (rgb uint8, depth in m, both (H, W + 2m)) as one LZ4 block: the rgb's bytes, then the
        depth's as float16."""
        shape = (self.height_px, self.wide_width_px)
        if rgb.shape != (*shape, 3) or depth_m.shape != shape:
            raise ValueError(f"a prepared frame of {rgb.shape} / {depth_m.shape}, the layout says {shape}")
        rgb_bytes = np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()
        depth_bytes = np.ascontiguousarray(depth_m, dtype=np.float16).tobytes()
        return lz4.block.compress(rgb_bytes + depth_bytes, store_size=False)

    def decode(self, block: bytes) -> tuple[np.ndarray, np.ndarray]:
        """The (rgb (H, W + 2m, 3) uint8, depth (H, W + 2m) float16) arrays of a frame's block: views of one new
        writable buffer."""
        H, wide = self.height_px, self.wide_width_px
        size = self.rgb_bytes + self.depth_bytes
        decoded = lz4.block.decompress(block, uncompressed_size=size, return_bytearray=True)
        if len(decoded) != size:
            raise OSError(f"a frame of {len(decoded)} bytes, the layout says {size}")
        raw = np.frombuffer(decoded, np.uint8)
        if self.depth_offset == self.rgb_bytes:  # the depth already starts 8-byte aligned: no copy (a read's ~10 %)
            frame = raw
        else:
            frame = np.empty(self.depth_offset + self.depth_bytes, dtype=np.uint8)
            frame[: self.rgb_bytes] = raw[: self.rgb_bytes]
            frame[self.depth_offset :] = raw[self.rgb_bytes :]
        rgb = frame[: self.rgb_bytes].reshape(H, wide, 3)
        return rgb, frame[self.depth_offset :].view(np.float16).reshape(H, wide)


class PreparedFrames:
    """A built cache folder opened for reading (module docstring): `read(i)` gives frame i as the view prepares it,
    as new arrays decoded from its LZ4 block in the file."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        info = json.loads((self.folder / "layout.json").read_text())
        self.layout = FrameLayout(**info["layout"])
        self.frame_count = int(info["frame_count"])
        self.stats = np.load(self.folder / "stats.npy")
        self.offsets = np.load(self.folder / "offsets.npy")
        self._file = open(self.folder / "frames.bin", "rb")  # noqa: SIM115 (open while the cache is read)
        size = os.fstat(self._file.fileno()).st_size
        if self.offsets.shape != (self.frame_count + 1,) or size != int(self.offsets[-1]):
            raise OSError(f"{self.folder / 'frames.bin'}: {size} bytes, its offsets say {self.offsets[-1]}")

    def read(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Frame `index`: (rgb (H, W + 2m, 3) uint8, depth (H, W + 2m) float16, mean colour (3,) in [0, 1], smallest
        finite depth in m). rgb and depth are new arrays."""
        if not 0 <= index < self.frame_count:
            raise IndexError(f"frame {index} is outside the cache's {self.frame_count} frames")
        start, end = int(self.offsets[index]), int(self.offsets[index + 1])
        block = os.pread(self._file.fileno(), end - start, start)
        if len(block) != end - start:
            raise OSError(f"{self.folder / 'frames.bin'}: frame {index} is {len(block)} bytes, not {end - start}")
        rgb, depth = self.layout.decode(block)
        stats = self.stats[index]
        return rgb, depth, stats[:3].copy(), float(stats[3])

    @property
    def disk_bytes(self) -> int:
        """Bytes of the cache's files."""
        return sum(p.stat().st_size for p in self.folder.iterdir() if p.is_file())


def _world_fingerprint(root: Path, sample: dict[str, Any]) -> list:
    """What identifies a world's content: name, size and mtime of every file of its folder (not the cache), and the
    `sample` the caller reads from the loaded world's arrays (so an in-memory world differing from its folder's files
    gets another key)."""
    files = []
    for entry in sorted(os.scandir(root), key=lambda e: e.name):
        if entry.is_file() and entry.name != CACHE_DIR_NAME:
            info = entry.stat()
            files.append([entry.name, info.st_size, info.st_mtime_ns])
    return [files, sample]


def cache_key(root: Path, recipe: dict[str, Any], sample: dict[str, Any]) -> str:
    """The folder name of a cache: a hash of the format version, the view settings that shape a prepared frame
    (`recipe`: source factor, margin, margin frames, intrinsics, the preparing code), and the world's identity
    (`_world_fingerprint`). Any change of these gives a new key, so a stale cache is never read."""
    identity = {"format": FORMAT_VERSION, "recipe": recipe, "world": _world_fingerprint(root, sample)}
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def open_prepared_frames(
    root: Path,
    frame_count: int,
    recipe: dict[str, Any],
    sample: dict[str, Any],
    layout: FrameLayout,
    prepare: Prepare,
) -> PreparedFrames | None:
    """The prepared frames of the world in folder `root` (module docstring), built now by `prepare` when no process
    has built them for this key yet; None where the folder holds no world.json (an in-memory world) or cannot be
    written (the view then prepares frames itself, as without a cache)."""
    root = Path(root)
    if not (root / "world.json").is_file():
        return None
    key = cache_key(root, recipe, sample)
    cache_dir = root / CACHE_DIR_NAME
    folder = cache_dir / key
    if (folder / "layout.json").is_file():
        return PreparedFrames(folder)
    try:
        cache_dir.mkdir(exist_ok=True)
        lock = open(cache_dir / f"{key}.lock", "a+b")  # noqa: SIM115 (held until the build ends)
    except OSError as e:
        _LOG.info("view cache: %s cannot be written (%s); frames are prepared in memory", cache_dir, e)
        return None
    with lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)  # another process building this key: wait for it, then read
        if not (folder / "layout.json").is_file():
            for stale in cache_dir.glob(f".tmp-{key}-*"):  # left by a builder that died: only the lock holder builds
                shutil.rmtree(stale, ignore_errors=True)
            try:
                _build(cache_dir, key, frame_count, {"recipe": recipe, "sample": sample}, layout, prepare)
            except OSError as e:  # a full or read-only disk: nothing half-written stays, the view prepares in memory
                _LOG.info("view cache: could not be written in %s (%s); frames are prepared in memory", cache_dir, e)
                return None
    return PreparedFrames(folder)


def _build(cache_dir: Path, key: str, frame_count: int, made_from: dict, layout: FrameLayout, prepare: Prepare) -> None:
    """Write every frame's prepared form into a temporary folder, then rename it to `cache_dir / key`."""
    start = time.perf_counter()
    tmp = cache_dir / f".tmp-{key}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        _write_frames(tmp, frame_count, layout, prepare)
        info = {"layout": asdict(layout), "frame_count": frame_count, "format": FORMAT_VERSION, "made_from": made_from}
        (tmp / "layout.json").write_text(json.dumps(info, default=str))
        os.rename(tmp, cache_dir / key)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _LOG.info(
        "view cache: %d frames prepared into %s in %.1f s (%d bytes)",
        frame_count, cache_dir / key, time.perf_counter() - start, (cache_dir / key / "frames.bin").stat().st_size,
    )  # fmt: skip


def _write_frames(folder: Path, frame_count: int, layout: FrameLayout, prepare: Prepare) -> None:
    """frames.bin, offsets.npy and stats.npy of every frame in `folder`, in chunks (memory flat in the drive's
    length)."""
    stats = np.empty((frame_count, 4), dtype=np.float64)
    offsets = np.zeros(frame_count + 1, dtype=np.int64)
    with open(folder / "frames.bin", "wb") as f:
        for first in range(0, frame_count, _WRITE_CHUNK_FRAMES):
            blocks = []
            for index in range(first, min(first + _WRITE_CHUNK_FRAMES, frame_count)):
                rgb, depth, mean_rgb = prepare(index)
                blocks.append(layout.encode(rgb, depth))
                offsets[index + 1] = offsets[index] + len(blocks[-1])
                finite = depth[(depth > 0) & np.isfinite(depth)]
                stats[index, :3] = mean_rgb
                stats[index, 3] = float(finite.min()) if finite.size else float("inf")
            f.write(b"".join(blocks))
        f.flush()
        os.fsync(f.fileno())
    np.save(folder / "stats.npy", stats)
    np.save(folder / "offsets.npy", offsets)
