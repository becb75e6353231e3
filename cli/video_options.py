"""The plain-video options of `drivesim ingest` and `drivesim run` (issue 23), turned into config overrides so
that they are part of the trace's config hash."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

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


@dataclass(frozen=True)
class VideoOptions:
    """The plain-video options of one command as given (None: not given)."""

    camera_height_m: float | None = None
    hfov_deg: float | None = None
    calibration: Path | None = None
    gps: str | None = None
    video_start_utc: str | None = None
    start_s: float | None = None
    end_s: float | None = None
    fps: float | None = None

    def overrides(self, prefix: str = "") -> list[str]:
        """The given options as `--set` overrides (`prefix` "ingest." for `drivesim run`); paths made absolute."""
        gps = self.gps
        if gps is not None and gps.lower() != "none":
            gps = str(Path(gps).resolve())
        values = {
            "extrinsics.camera_height_m": self.camera_height_m,
            "video.hfov_deg": self.hfov_deg,
            "video.calibration_file": str(self.calibration.resolve()) if self.calibration is not None else None,
            "video.gps_file": gps,
            "video.start_time_utc": self.video_start_utc,
            "video.start_s": self.start_s,
            "video.end_s": self.end_s,
            "video.fps": self.fps,
        }
        return [f"{prefix}{key}={value}" for key, value in values.items() if value is not None]


NO_VIDEO = VideoOptions()
"""No video option given: the default of a command's `video` parameter."""

# The options in the order `--help` lists them, by VideoOptions field.
_OPTIONS = {
    "camera_height_m": CameraHeightOption,
    "hfov_deg": HfovOption,
    "calibration": CalibrationOption,
    "gps": GpsOption,
    "video_start_utc": VideoStartOption,
    "start_s": StartOption,
    "end_s": EndOption,
    "fps": FpsOption,
}


def with_video_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """`command` with the video options in its signature where its `video: VideoOptions` parameter stands (so typer
    lists them there); it is called with them gathered into that one VideoOptions."""
    signature = inspect.signature(command, eval_str=True)
    parameters: list[inspect.Parameter] = []
    for param in signature.parameters.values():
        if param.name != "video":
            parameters.append(param)
            continue
        parameters += [inspect.Parameter(name, param.kind, default=None, annotation=a) for name, a in _OPTIONS.items()]

    @functools.wraps(command)
    def wrapper(**kwargs: Any) -> Any:
        video = VideoOptions(**{name: kwargs.pop(name) for name in _OPTIONS})
        return command(**kwargs, video=video)

    wrapper.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters} | {"return": signature.return_annotation}
    return wrapper
