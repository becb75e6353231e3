"""The plain-video options of `drivesim ingest` and `drivesim run` (issue 23), turned into config overrides so
that they are part of the trace's config hash."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

CameraHeightOption = Annotated[
    float | None,
    typer.Option(
        "--camera-height-m",
        help="Camera height above the road (m); a video's metric scale when no GPS track is given.",
        show_default=False,
    ),
]
HfovOption = Annotated[
    float | None,
    typer.Option(
        "--hfov-deg", help="Video: horizontal field of view (deg); default: SfM estimates it.", show_default=False
    ),
]
CalibrationOption = Annotated[
    Path | None,
    typer.Option("--calibration", help="Video: camera intrinsics (OpenCV or ROS CameraInfo YAML).", show_default=False),
]
GpsOption = Annotated[
    str | None,
    typer.Option(
        "--gps",
        help="Video: GPS track (.gpx, .nmea, .csv) for the metric scale; default: one named like the video beside "
        "it, else the GPS a GoPro recorded inside the video; 'none' ignores both.",
        show_default=False,
    ),
]
VideoStartOption = Annotated[
    str | None,
    typer.Option(
        "--video-start-utc",
        help="Video: UTC time of its first frame (ISO 8601), to match the GPS track (a GoPro's own GPS gives it).",
        show_default=False,
    ),
]
StartOption = Annotated[
    float | None, typer.Option("--start-s", help="Video: skip before this time (s).", show_default=False)
]
EndOption = Annotated[float | None, typer.Option("--end-s", help="Video: stop at this time (s).", show_default=False)]
FpsOption = Annotated[
    float | None, typer.Option("--fps", help="Image folder: its frame rate (Hz).", show_default=False)
]


def video_overrides(
    camera_height_m: float | None = None,
    hfov_deg: float | None = None,
    calibration: Path | None = None,
    gps: str | None = None,
    video_start_utc: str | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    fps: float | None = None,
    prefix: str = "",
) -> list[str]:
    """The given options as `--set` overrides (`prefix` "ingest." for `drivesim run`); paths made absolute."""
    if gps is not None and gps.lower() != "none":
        gps = str(Path(gps).resolve())
    values = {
        "extrinsics.camera_height_m": camera_height_m,
        "video.hfov_deg": hfov_deg,
        "video.calibration_file": str(calibration.resolve()) if calibration is not None else None,
        "video.gps_file": gps,
        "video.start_time_utc": video_start_utc,
        "video.start_s": start_s,
        "video.end_s": end_s,
        "video.fps": fps,
    }
    return [f"{prefix}{key}={value}" for key, value in values.items() if value is not None]
