"""Configuration of `drivesim ingest` (preset: configs/ingest.yaml)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from drivesim.pipeline.config import StageConfig
from drivesim.stages.ingest.trace import rigid_problem
from drivesim.stages.ingest.video_config import VideoConfig

TOPIC_ROLES = ("camera", "camera_info", "gps", "imu", "twist", "odometry", "lidar", "gt_depth", "gt_pose")


class ImageConfig(StageConfig):
    """How frames are stored."""

    width_px: int = Field(640, ge=16, le=8192)
    """Working width of the stored frames (px); the height follows the recorded aspect ratio."""
    upscale: bool = False
    """Allow a working width larger than the recorded one (otherwise the recorded width is the maximum)."""
    interpolation: Literal["area", "linear"] = "area"
    """Downscaling filter: "area" (cv2.INTER_AREA, averages every source pixel: no aliasing) or "linear"
    (cv2.INTER_LINEAR: 3-5x faster for non-integer factors such as 960->640, slight aliasing)."""
    keep_original: bool = False
    """Also store the undistorted frames at the recorded resolution (frames_original.imgs; intrinsics K_source)."""
    codec: Literal["jpeg", "png"] = "jpeg"
    """How each stored frame is compressed: "jpeg" (lossy, `jpeg_quality`, 4:4:4) or "png" (lossless, ~3x larger)."""
    jpeg_quality: int = Field(97, ge=50, le=100)
    """JPEG quality of the stored frames (with codec jpeg)."""
    reduced_jpeg_decode: bool = True
    """Decode jpeg frames at 1/2, 1/4 or 1/8 size when that still covers the working width (faster)."""


class TopicsConfig(StageConfig):
    """Topics by role; unset roles are found by message type (`--topic ROLE=/name` sets one)."""

    camera: str | None = None
    """Camera image topic (sensor_msgs/Image or CompressedImage); KITTI: the image folder, e.g. image_02."""
    camera_info: str | None = None
    """CameraInfo topic of that camera (default: the one in the camera's namespace)."""
    gps: str | None = None
    """NavSatFix topic."""
    imu: str | None = None
    """Imu topic."""
    twist: str | None = None
    """TwistStamped topic giving the forward speed."""
    odometry: str | None = None
    """nav_msgs/Odometry topic."""
    lidar: str | None = None
    """sensor_msgs/PointCloud2 topic (stored as lidar_points.npy in the vehicle frame)."""
    gt_depth: str | None = None
    """Ground-truth depth image topic of synthetic recordings (default /ground_truth/depth)."""
    gt_pose: str | None = None
    """Ground-truth PoseStamped topic of synthetic recordings (default /ground_truth/pose)."""


class ExtrinsicsConfig(StageConfig):
    """Where the camera sits on the vehicle."""

    vehicle_frames: list[str] = ["base_footprint", "base_link"]
    """tf frames tried in order as the vehicle frame; base_footprint (on the ground) also gives the camera height."""
    T_vehicle_camera: list[list[float]] | None = None
    """4x4 camera optical -> vehicle transform (m) used instead of /tf_static or KITTI calibration."""
    camera_height_m: float | None = Field(None, gt=0.0, lt=10.0)
    """Camera height above the ground (m) when the recording does not give it (no base_footprint frame)."""

    @field_validator("T_vehicle_camera")
    @classmethod
    def _rigid(cls, value: list[list[float]] | None) -> list[list[float]] | None:
        if value is None:
            return value
        problem = rigid_problem(np.asarray(value, dtype=float))
        if problem:
            raise ValueError(f"must be a finite rigid 4x4 transform (camera optical -> vehicle, metres); it {problem}")
        return value


class IngestConfig(StageConfig):
    """`drivesim ingest`: recording -> trace artifact."""

    image: ImageConfig = ImageConfig()
    """Stored frame format."""
    topics: TopicsConfig = TopicsConfig()
    """Topic choice by role."""
    extrinsics: ExtrinsicsConfig = ExtrinsicsConfig()
    """Camera mounting."""
    ground_truth_depth: bool = False
    """Keep a synthetic recording's ground-truth depth as gt_depth.npy (float32: 4 bytes per pixel and frame); no stage
    reads it, it is for comparing depth estimates with the truth."""
    require_pose_source: bool = True
    """Refuse recordings without GPS or odometry (set false to let preprocess use visual SfM alone)."""
    kitti_time_step_s: float = Field(0.1, gt=0.0)
    """Frame interval (s) of KITTI folders without timestamps files."""
    video: VideoConfig = VideoConfig()
    """Plain video or image folder: trimming, intrinsics, SfM, GPS track (stages/ingest/video_config.py)."""
