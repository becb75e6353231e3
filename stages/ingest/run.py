"""`drivesim ingest` as a library call: any supported recording -> a trace folder.

The formats are one table, `FORMATS`: format name -> `RecordingFormat(matches, read)`, tried in order, the first
whose `matches(path)` is true reads the recording. Every reader has one signature,
`read(path, cfg, trace) -> None`: it hands the frames, their stamps, the camera, the extrinsics and its sensors to
the `TraceWriter` (writer.py), which checks them and writes the trace's calibration and sources once.

Adding a format (a plain video, ...) is its module plus one line here:
    1. `stages/ingest/<name>.py` with `matches(path: Path) -> bool` (cheap: a suffix, magic bytes, file names) and
       `read(path: Path, cfg: IngestConfig, trace: TraceWriter) -> None` (kitti.py is a short example; write frames
       with `FrameStore` + `writer.FrameStream`, then `trace.set_camera`, `set_extrinsics`, `set_times`,
       `add_sensor`);
    2. one entry in FORMATS, above any entry that would also match its recordings (e.g. a stereo folder before the
       mono one);
    3. its name in trace.py's `sources.json:format` list.
A recording nothing matches gets the one-line explanation of `sources.unrecognised`.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.native_log import native_messages_to
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.kitti import (
    ingest_kitti_odometry,
    ingest_kitti_raw,
    ingest_kitti_stereo,
    is_kitti_odometry,
    is_kitti_raw_drive,
    is_kitti_stereo,
)
from drivesim.stages.ingest.output import IngestResult
from drivesim.stages.ingest.ros import ingest_ros
from drivesim.stages.ingest.sources import is_mcap_file, is_ros1_bag, is_rosbag2_folder, unrecognised
from drivesim.stages.ingest.trace import validate_trace
from drivesim.stages.ingest.video_trace import ingest_video, is_video
from drivesim.stages.ingest.writer import TraceWriter

Reader = Callable[[Path, IngestConfig, TraceWriter], None]


@dataclass(frozen=True)
class RecordingFormat:
    """One kind of recording: how to recognise it and how to read it into a trace."""

    matches: Callable[[Path], bool]
    """True when the file or folder at the path is this kind of recording (cheap: no decoding)."""
    read: Reader
    """Reads the recording into the TraceWriter; InputError (one line) for what it cannot use."""


FORMATS: dict[str, RecordingFormat] = {
    "mcap": RecordingFormat(is_mcap_file, ingest_ros),
    "ros1": RecordingFormat(is_ros1_bag, ingest_ros),
    "rosbag2": RecordingFormat(is_rosbag2_folder, ingest_ros),
    "kitti_raw": RecordingFormat(is_kitti_raw_drive, ingest_kitti_raw),
    "kitti_odometry_stereo": RecordingFormat(is_kitti_stereo, ingest_kitti_stereo),
    "kitti_odometry": RecordingFormat(is_kitti_odometry, ingest_kitti_odometry),
    "video": RecordingFormat(is_video, ingest_video),  # a video file, or a folder of images only
}


def detect_format(path: Path) -> str:
    """The name in FORMATS of the recording at `path`; InputError saying what it looks like when none matches."""
    for name, fmt in FORMATS.items():
        if fmt.matches(path):
            return name
    raise unrecognised(path)


def ingest_recording(path: Path, cfg: IngestConfig, out_dir: Path, native_log: Path | None = None) -> IngestResult:
    """Read the recording at `path` (any format of FORMATS) into the trace folder `out_dir`.

    What the image and video decoders print (libjpeg, libpng, FFmpeg) goes to `native_log` (appended; a temporary
    file when None), not the terminal; a frame they report damaged is left out and counted (writer.FrameStream).
    Raises InputError/ConfigError with one line naming the file and the problem; `out_dir` is then incomplete
    and must be discarded (Workspace.write_artifact does that). What is written has passed `validate_trace`.
    """
    path = Path(path)
    fmt = detect_format(path)
    trace = TraceWriter(Path(out_dir), path, fmt, (cfg.image.codec, cfg.image.jpeg_quality))
    with (
        tempfile.TemporaryDirectory(prefix="drivesim-decoders-") as tmp,
        native_messages_to(native_log or Path(tmp) / "decoders.log") as log,
    ):
        try:
            FORMATS[fmt].read(path, cfg, trace)
        except InputError as e:
            if e.path is not None:
                raise
            raise InputError(e.message, path) from e  # every ingest error names the recording
    if log.lines and native_log is not None:
        trace.notes.append(f"the image and video decoders printed {log.lines} line(s), kept in {log.path}")
    result = trace.finish()
    validate_trace(out_dir)
    return result
