"""Frames of a plain video (MP4/MOV/MKV/AVI, anything OpenCV's FFmpeg backend decodes) or of a folder of images with
a frame rate, with their times, trimmed to a window and thinned for SfM.

Times are int64 ns since the first frame of the file (the container's presentation times; evenly spaced at the
container's frame rate when it gives none or non-increasing ones). Frames come out as RGB uint8.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.stages.ingest.images import CorruptImageError, decode_image_bytes

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".m4v", ".webm", ".mpg", ".mpeg", ".ts")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class FrameSource:
    """A video file or an image folder: where the frames are and when each was taken.

    :param path: the video file or image folder.
    :param kind: "video" or "image_folder".
    :param times_ns: (N,) time of every frame of the file since its first frame, strictly increasing.
    :param width_px, height_px: decoded frame size.
    :param fps: nominal frame rate (Hz).
    :param files: the image files of an image folder (empty for a video).
    :param note: how the times were obtained, for the user.
    :param announced_frames: the frame count the video's container announces (0: it announces none; an image folder).
    """

    path: Path
    kind: str
    times_ns: np.ndarray
    width_px: int
    height_px: int
    fps: float
    files: tuple[Path, ...] = ()
    note: str = ""
    announced_frames: int = 0

    @property
    def duration_s(self) -> float:
        """From the first to the last frame (s)."""
        return float(self.times_ns[-1] - self.times_ns[0]) * 1e-9 if len(self.times_ns) > 1 else 0.0


def is_video_file(path: Path) -> bool:
    """True for a file whose suffix names a video container."""
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def image_files(folder: Path) -> list[Path]:
    """The PNG/JPEG files directly in `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise InputError("cannot open the video (unknown container or codec; re-encode it to H.264 MP4)", path)
    return cap


def probe_video(path: Path) -> FrameSource:
    """Every frame's time of a video file (one pass that demuxes without colour conversion).

    :raises InputError: the file cannot be opened or has no decodable frame.
    """
    cap = _open(path)
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        announced = max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        stamps_ms = []
        while cap.grab():
            stamps_ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
    finally:
        cap.release()
    if not stamps_ms or width <= 0 or height <= 0:
        raise InputError("the video has no decodable frame (unreadable codec? re-encode it to H.264 MP4)", path)
    stamps = np.asarray(stamps_ms)
    times_ns = np.round((stamps - stamps[0]) * 1e6).astype(np.int64)
    note = f"video {width}x{height}, {len(stamps)} frames, times from the container"
    if len(times_ns) > 1 and np.any(np.diff(times_ns) <= 0):
        if fps <= 0:
            raise InputError("the video gives neither increasing frame times nor a frame rate", path)
        times_ns = np.round(np.arange(len(stamps)) * 1e9 / fps).astype(np.int64)
        note = f"video {width}x{height}, {len(stamps)} frames, times from the frame rate {fps:g} Hz"
    if fps <= 0 and len(times_ns) > 1:
        fps = (len(times_ns) - 1) / (times_ns[-1] * 1e-9)
    return FrameSource(path, "video", times_ns, width, height, fps, note=note, announced_frames=announced)


def probe_image_folder(folder: Path, fps: float | None) -> FrameSource:
    """An image folder as frames evenly spaced at `fps`.

    :raises InputError: no images, no frame rate, or the first image is unreadable.
    """
    files = image_files(folder)
    if not files:
        raise InputError("no PNG or JPEG images in the folder", folder)
    if fps is None:
        raise InputError("an image folder needs its frame rate: give --fps (e.g. --fps 10)", folder)
    first = read_image_file(files[0])
    times_ns = np.round(np.arange(len(files)) * 1e9 / fps).astype(np.int64)
    note = f"image folder {first.shape[1]}x{first.shape[0]}, {len(files)} frames at {fps:g} Hz"
    return FrameSource(folder, "image_folder", times_ns, first.shape[1], first.shape[0], fps, tuple(files), note)


def read_image_file(path: Path) -> np.ndarray:
    """BGR pixels of one PNG/JPEG file; InputError when it cannot be read, decoded, or decodes with damage."""
    try:
        return decode_image_bytes(path.read_bytes())
    except OSError as e:
        raise InputError(f"cannot read the image file: {e.strerror or e}", path) from e
    except CorruptImageError as e:
        raise InputError(f"unreadable image file: {e}", path) from e


def select_frames(times_ns: np.ndarray, start_s: float | None, end_s: float | None) -> np.ndarray:
    """Indices of the frames inside [start_s, end_s] (seconds since the first frame; None = open end)."""
    t_s = (times_ns - times_ns[0]) * 1e-9
    keep = np.ones(len(t_s), dtype=bool)
    if start_s is not None:
        keep &= t_s >= start_s - 1e-6
    if end_s is not None:
        keep &= t_s <= end_s + 1e-6
    return np.flatnonzero(keep)


def thin_to_rate(times_ns: np.ndarray, rate_hz: float | None) -> np.ndarray:
    """Positions (into `times_ns`) of the frames kept when thinning to at most `rate_hz`: a frame is kept when at
    least 1/rate_hz (less a 10 % slack for jitter) has passed since the last kept one; None keeps all."""
    if rate_hz is None or len(times_ns) == 0:
        return np.arange(len(times_ns))
    min_step_ns = 0.9e9 / rate_hz
    kept = [0]
    for i in range(1, len(times_ns)):
        if times_ns[i] - times_ns[kept[-1]] >= min_step_ns:
            kept.append(i)
    return np.asarray(kept, dtype=np.int64)


def iter_frames(source: FrameSource, indices: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(frame index, RGB frame) for the given increasing frame indices, decoding the file once.

    :raises InputError: a frame cannot be decoded.
    """
    wanted = set(int(i) for i in indices)
    if source.kind == "image_folder":
        for i in indices:
            bgr = read_image_file(source.files[int(i)])
            if bgr.shape[:2] != (source.height_px, source.width_px):
                raise InputError(f"image is {bgr.shape[1]}x{bgr.shape[0]}, the first one differs", source.files[i])
            yield int(i), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return
    last = int(indices[-1]) if len(indices) else -1
    cap = _open(source.path)
    try:
        for i in range(last + 1):
            if not cap.grab():
                raise InputError(f"the video ends at frame {i}, expected {last + 1} frames", source.path)
            if i not in wanted:
                continue
            ok, bgr = cap.retrieve()
            if not ok or bgr is None:
                raise InputError(f"cannot decode frame {i} of the video", source.path)
            yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    finally:
        cap.release()
