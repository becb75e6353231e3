"""Configuration of plain-video ingest (`drivesim ingest drive.mp4`): the `video` section of IngestConfig."""

from __future__ import annotations

import datetime as dt

from pydantic import Field

from drivesim.pipeline.config import StageConfig


class VideoConfig(StageConfig):
    """A video (or image folder) in: trimming, intrinsics, SfM and the metric scale (the camera height is
    `extrinsics.camera_height_m`, `--camera-height-m`)."""

    start_s: float | None = Field(None, ge=0.0)
    """Skip the video before this time (s since its first frame)."""
    end_s: float | None = Field(None, gt=0.0)
    """Stop the video at this time (s since its first frame)."""
    fps: float | None = Field(None, gt=0.0, le=1000.0)
    """Frame rate of an image folder (Hz); videos carry their own times."""
    start_time_utc: dt.datetime | None = None
    """UTC time of the video's first frame (ISO 8601); needed to match a GPS track's times (default for a GoPro video
    with GPS: its first fix's time)."""
    gps_file: str | None = None
    """GPS track (.gpx, .nmea, .csv) giving the metric scale; default: a file with the video's name beside it, else
    the GPS a GoPro recorded inside the video (GPMF telemetry); "none" ignores both."""
    calibration_file: str | None = None
    """Camera intrinsics (OpenCV YAML or ROS CameraInfo YAML); without it and `hfov_deg`, SfM estimates the focal."""
    hfov_deg: float | None = Field(None, gt=10.0, lt=170.0)
    """Horizontal field of view (deg) of a distortion-free camera, instead of a calibration file."""
    sfm_rate_hz: float | None = Field(10.0, gt=0.0)
    """Frames per second given to SfM (the others get interpolated poses); None gives it every frame."""
    sfm_width_px: int = Field(640, ge=160, le=4096)
    """Width of the images SfM works on (px)."""
    sfm_window: int = Field(20, ge=2, le=100)
    """Each SfM frame is matched with this many following frames (2 s at 10 Hz: tracks that span more of a turn
    pin the estimated focal length better)."""
    sfm_loop_keyframes: int = Field(15, ge=0, le=200)
    """Evenly spaced keyframes matched with each other for loop closure (0: off)."""
    sfm_max_features: int = Field(4096, ge=256, le=32768)
    """SIFT features per SfM image."""
    sfm_threads: int = Field(2, ge=1, le=256)
    """CPU threads SfM uses."""
    min_registered_fraction: float = Field(0.5, gt=0.0, le=1.0)
    """Refuse the video when SfM's kept piece registers fewer of its frames than this."""
