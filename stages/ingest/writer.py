"""The one writer of trace folders: every reader (ROS, KITTI, ...) hands it the frames, their stamps, the camera, the
extrinsics and its sensors; `finish()` checks them and writes frame_times_ns.npy, calibration.json and sources.json
(layout: trace.py).

Nothing is called a trace before it passed these checks (issue 22: never written silently wrong):
- intrinsics finite with positive focal lengths, at the working and the recorded resolution;
- T_vehicle_camera a finite rigid 4x4 (orthonormal rotation, det +1, last row 0 0 0 1);
- frame stamps strictly increasing, one per written frame;
- the counts of messages skipped as unreadable or non-finite are in the summary (`skipped`) and in a note.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.sim.image_stack import DEFAULT_JPEG_QUALITY, open_frames, stored_file
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.images import DamagedImageError, FrameProcessor
from drivesim.stages.ingest.output import FrameStore, IngestResult, OrderedPipeline, write_json
from drivesim.stages.ingest.trace import rigid_problem

# A recording whose camera loses more than this fraction of its messages is refused rather than ingested with gaps:
# a few dropped frames happen on real drives; more means the stream itself is broken or not what it claims to be.
MAX_SKIPPED_FRAME_FRACTION = 0.25
# Frames that decode but whose decoder reported damaged data (grey or smeared blocks) are left out too; more than this
# fraction of them means the recording itself is damaged (a bad copy, a failing disk), which is refused.
MAX_DAMAGED_FRAME_FRACTION = 0.10
# A camera picture narrower or wider than these (width / height) is not a driving camera (a line scan, a strip of a
# panorama, a mis-read size); nor is one with a side under MIN_SIDE_PX or over MAX_SIDE_PX.
MIN_ASPECT, MAX_ASPECT = 0.25, 8.0
MIN_SIDE_PX, MAX_SIDE_PX = 16, 20_000
# A frame shows nothing when the spread of its grey levels (1st to 99th percentile) is under NO_SIGNAL_SPREAD of 255:
# all black, all white or one colour. A camera showing nothing on more than MAX_BLANK_FRACTION of its frames (a
# covered lens, a dead sensor, the wrong topic) is refused; BLANK_SAMPLE_FRAMES evenly spaced frames are looked at.
NO_SIGNAL_SPREAD = 8
MAX_BLANK_FRACTION = 0.5
BLANK_SAMPLE_FRAMES = 64


@dataclass(frozen=True)
class Extrinsics:
    """Where the camera sits on the vehicle.

    :param T_vehicle_camera: 4x4 camera optical frame -> vehicle frame (m).
    :param camera_height_m: optical centre above the ground (m), or None when unknown.
    :param source: "tf_static", "kitti_calib", "config" or "default".
    """

    T_vehicle_camera: np.ndarray
    camera_height_m: float | None
    source: str


def config_extrinsics(cfg: IngestConfig) -> Extrinsics | None:
    """The extrinsics set in the config (`extrinsics.T_vehicle_camera`), or None when it sets none."""
    if cfg.extrinsics.T_vehicle_camera is None:
        return None
    T = np.asarray(cfg.extrinsics.T_vehicle_camera, dtype=float)
    return Extrinsics(T, cfg.extrinsics.camera_height_m, "config")


def intrinsics_problem(K: np.ndarray) -> str | None:
    """Why `K` is not a finite 3x3 pinhole matrix with positive focal lengths, or None when it is."""
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return "is not a finite 3x3 matrix"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return "has no positive focal length (uncalibrated camera)"
    return None


def image_size_problem(width_px: int, height_px: int) -> str | None:
    """Why a camera picture of this size is not one drivesim can use (too small, too large, absurd aspect), or None."""
    if min(width_px, height_px) < MIN_SIDE_PX or max(width_px, height_px) > MAX_SIDE_PX:
        return f"pictures of {width_px}x{height_px} px: each side must be {MIN_SIDE_PX} to {MAX_SIDE_PX} px"
    if not MIN_ASPECT <= width_px / height_px <= MAX_ASPECT:
        return (
            f"pictures of {width_px}x{height_px} px (aspect {width_px / height_px:.3g}): a driving camera's width / "
            f"height is {MIN_ASPECT:g} to {MAX_ASPECT:g}"
        )
    return None


def blank_frames(trace_dir: Path) -> tuple[int, int]:
    """(frames that show no picture, frames looked at) among BLANK_SAMPLE_FRAMES evenly spaced frames of the trace."""
    frames_path = stored_file(trace_dir, "frames")
    if frames_path is None:
        return 0, 0
    frames = open_frames(frames_path)
    n = frames.shape[0]
    if n == 0:
        return 0, 0
    rows = np.unique(np.linspace(0, n - 1, min(n, BLANK_SAMPLE_FRAMES)).round().astype(int))
    blank = 0
    for i in rows:
        grey = np.asarray(frames[i, ::2, ::2], dtype=np.float32).mean(axis=2)
        low, high = np.percentile(grey, (1, 99))
        blank += bool(high - low < NO_SIGNAL_SPREAD)
    return blank, len(rows)


class TraceWriter:
    """Collects what a reader found and writes the trace's calibration and sources once, checked.

    :param out_dir: the (empty) trace folder.
    :param recording: the recording being read (named in errors).
    :param fmt: its format name (a key of run.FORMATS).
    :param frame_storage: (codec, JPEG quality) of the stored frames.
    """

    def __init__(
        self, out_dir: Path, recording: Path, fmt: str, frame_storage: tuple[str, int] = ("jpeg", DEFAULT_JPEG_QUALITY)
    ) -> None:
        self.out_dir = Path(out_dir)
        self.frame_storage = frame_storage
        """(codec, JPEG quality) the frames are stored with (output.FrameStore)."""
        self.recording = Path(recording)
        self.format = fmt
        self.notes: list[str] = []
        self.sensors: dict[str, dict[str, Any]] = {}
        self.skipped: dict[str, int] = {}
        self._camera: tuple[str, FrameProcessor, tuple[int, int], str] | None = None
        self._extrinsics: Extrinsics | None = None
        self._times: tuple[np.ndarray, str] | None = None
        self._extra: dict[str, Any] = {}
        self._frame_rows: int | None = None

    def fail(self, problem: str) -> InputError:
        """An InputError naming the recording."""
        return InputError(problem, self.recording)

    def set_camera(
        self, topic: str, processor: FrameProcessor, source_size: tuple[int, int], distortion_model: str = "none"
    ) -> None:
        """The trace's camera: its topic (or folder), the processor that made the frames, the recorded size."""
        problem = image_size_problem(*source_size) or image_size_problem(processor.out_width, processor.out_height)
        if problem:
            raise self.fail(f"camera {topic}: {problem}")
        for name, K in (("K", processor.K_source), ("K at the working resolution", processor.K_out)):
            problem = intrinsics_problem(K)
            if problem:
                raise self.fail(f"camera {topic}: the intrinsics {name} {problem}")
        self._camera = (topic, processor, source_size, distortion_model)

    def set_extrinsics(self, extrinsics: Extrinsics) -> None:
        """Where the camera sits; refused unless T_vehicle_camera is a finite rigid transform."""
        problem = rigid_problem(extrinsics.T_vehicle_camera)
        if problem:
            where = extrinsics.source
            raise self.fail(f"T_vehicle_camera (from {where}) {problem}; fix it or set extrinsics.T_vehicle_camera")
        height = extrinsics.camera_height_m
        if height is not None and not np.isfinite(height):
            raise self.fail(f"camera height (from {extrinsics.source}) is not finite")
        self._extrinsics = extrinsics

    def set_times(self, times_ns: np.ndarray, time_base: str, frame_rows: int) -> None:
        """The stamps of the `frame_rows` frames written to frames.imgs ("unix" or "relative" time base)."""
        self._times = (np.asarray(times_ns, dtype=np.int64), time_base)
        self._frame_rows = frame_rows

    def add_sensor(self, role: str, topic: str, msgtype: str, message_count: int) -> None:
        """One sensor stream read from the recording (listed in sources.json and the summary in call order)."""
        self.sensors[role] = {"topic": topic, "type": msgtype, "message_count": int(message_count)}

    def skip(self, role: str, count: int = 1) -> None:
        """Count messages of `role` left out as unreadable or non-finite."""
        if count:
            self.skipped[role] = self.skipped.get(role, 0) + int(count)

    def add_calibration(self, **values: Any) -> None:
        """Extra calibration.json keys (e.g. the stereo camera's), documented in trace.py."""
        self._extra.update(values)

    def _checked_times(self) -> tuple[np.ndarray, str]:
        if self._times is None or self._frame_rows is None:
            raise self.fail("no camera frames were read")
        times, time_base = self._times
        if len(times) != self._frame_rows:
            raise self.fail(f"{self._frame_rows} frames written for {len(times)} stamps")
        if len(times) == 0:
            raise self.fail("no readable camera frames")
        bad = np.flatnonzero(np.diff(times) <= 0)
        if bad.size:
            raise self.fail(f"camera stamps not strictly increasing at frame {int(bad[0]) + 1}")
        return times, time_base

    def finish(self) -> IngestResult:
        """Check everything and write frame_times_ns.npy, calibration.json, sources.json; the manifest summary."""
        times, time_base = self._checked_times()
        if self._camera is None or self._extrinsics is None:
            raise self.fail("the reader set no camera or extrinsics")
        topic, processor, (source_w, source_h), distortion = self._camera
        blank, looked_at = blank_frames(self.out_dir)
        if blank > MAX_BLANK_FRACTION * looked_at:
            raise self.fail(
                f"camera {topic} shows no picture: {blank} of {looked_at} frames looked at are one flat colour (all "
                "black, white or grey: a covered lens, a dead camera or the wrong topic; --topic camera=... picks "
                "another)"
            )
        ext = self._extrinsics
        np.save(self.out_dir / "frame_times_ns.npy", times)
        calibration = {
            "width_px": processor.out_width,
            "height_px": processor.out_height,
            "K": processor.K_out,
            "K_source": processor.K_source,
            "source_width_px": source_w,
            "source_height_px": source_h,
            "distortion_model": distortion,
            "T_vehicle_camera": ext.T_vehicle_camera,
            "camera_height_m": ext.camera_height_m,
            "extrinsics_source": ext.source,
            "time_base": time_base,
            **self._extra,
        }
        write_json(self.out_dir / "calibration.json", calibration)
        sources = {"recording": str(self.recording), "format": self.format, "camera_topic": topic}
        write_json(self.out_dir / "sources.json", {**sources, "sensors": self.sensors})
        for role, count in self.skipped.items():
            self.notes.append(f"skipped {count} unreadable or non-finite {role} message(s)")
        summary = {
            "frame_count": len(times),
            "duration_s": round(float(times[-1] - times[0]) / 1e9, 3) if len(times) > 1 else 0.0,
            "width_px": processor.out_width,
            "height_px": processor.out_height,
            "sensors": self.sensors,
            "skipped": dict(self.skipped),
        }
        return IngestResult(summary=summary, notes=self.notes)


class FrameStream:
    """Camera frames made on worker threads, written to frames.imgs in order with their stamps.

    `work(item)` returns (working frame, recorded-size frame or None); when it raises one of `skippable`, the
    message is left out (frame and stamp) and counted; more than MAX_SKIPPED_FRAME_FRACTION left out refuses the
    recording.

    :param writer: the trace writer (errors name its recording; skipped frames are counted there as "camera").
    :param store: where frames go.
    :param work: item -> frames, run on a worker thread.
    :param advance: called once per finished item (progress).
    :param skippable: exceptions that mean "this one message is damaged".
    """

    def __init__(
        self,
        writer: TraceWriter,
        store: FrameStore,
        work: Callable[[Any], tuple[np.ndarray, np.ndarray | None]],
        advance: Callable[[], None],
        skippable: tuple[type[BaseException], ...] = (),
    ) -> None:
        self.writer = writer
        self.store = store
        self._work = work
        self._advance = advance
        self._skippable = skippable
        self.kept_times: list[int] = []
        self.skipped = 0
        self.damaged = 0
        self.first_problem = ""
        self._pipeline = OrderedPipeline(self._safe_work, self._sink)

    def _safe_work(self, item: tuple[Any, int]) -> tuple[int, Any]:
        payload, t_ns = item
        try:
            return t_ns, self._work(payload)
        except self._skippable as e:
            return t_ns, e
        except cv2.error as e:  # OpenCV on bytes that passed the checks: the message is damaged
            if not self._skippable:
                raise
            return t_ns, e

    def _sink(self, result: tuple[int, Any]) -> None:
        t_ns, frames = result
        self._advance()
        if isinstance(frames, BaseException):
            self.skipped += 1
            self.damaged += isinstance(frames, DamagedImageError)
            self.first_problem = self.first_problem or str(frames).splitlines()[0]
            return
        self.store.write(frames)
        self.kept_times.append(t_ns)

    def submit(self, item: Any, t_ns: int) -> None:
        """Queue one camera message (or file) and its stamp."""
        self._pipeline.submit((item, t_ns))

    def finish(self, camera: str) -> np.ndarray:
        """Write what remains; the stamps of the written frames. InputError when too many were unreadable."""
        self._pipeline.finish()
        total = self.skipped + len(self.kept_times)
        if self.damaged > MAX_DAMAGED_FRAME_FRACTION * total:
            raise self.writer.fail(
                f"camera {camera}: {self.damaged} of {total} frames are damaged (the image decoder reported corrupt "
                f"data; more than {MAX_DAMAGED_FRAME_FRACTION:.0%} of a drive cannot be left out); the recording "
                "itself is damaged: copy it again from its source"
            )
        if self.skipped and (self.skipped > MAX_SKIPPED_FRAME_FRACTION * total or not self.kept_times):
            raise self.writer.fail(
                f"camera {camera}: {self.skipped} of {total} messages are unreadable (first: {self.first_problem})"
            )
        if self.damaged:
            self.writer.notes.append(
                f"left out {self.damaged} damaged camera frame(s) of {total} (the image decoder reported corrupt data)"
            )
        self.writer.skip("camera", self.skipped)
        return np.asarray(self.kept_times, dtype=np.int64)

    def close(self) -> None:
        """Stop the workers and close the frame files (also on errors and Ctrl-C)."""
        self._pipeline.close()
        self.store.close()
