"""The `drivesim build-world` config (preset configs/world.yaml)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivesim.pipeline.config import StageConfig


class PointCloudConfig(StageConfig):
    """The fused coloured point cloud of the drive (pointcloud.ply, for people to look at)."""

    enabled: bool = True
    """Write pointcloud.ply (the simulator does not need it)."""
    frame_step: int = Field(5, ge=1)
    """Back-project every frame_step-th frame."""
    pixel_step: int = Field(2, ge=1)
    """Back-project every pixel_step-th pixel in each direction, at the preprocessed (working) resolution."""
    max_depth_m: float = Field(30.0, gt=0.0)
    """Only pixels nearer than this (m) are kept: far depth is unreliable and smears the cloud."""
    voxel_size_m: float = Field(0.2, gt=0.0)
    """Voxel edge (m) of the down-sampling that merges the frames' points (0.2 m: about 6 MB per minute of a
    synthetic drive)."""


class WorldConfig(StageConfig):
    """The simulatable world: frames and depth at the simulation resolution, camera, reference path, lane geometry."""

    sim_width_px: int = Field(320, ge=16, le=4096)
    """Width of the simulated camera image (px); the height keeps the recording's aspect ratio."""
    depth_resize: Literal["min", "nearest"] = "min"
    """How depth is resized to the simulation resolution: min keeps each block's nearest surface (thin objects and edges
    survive); nearest picks one source pixel."""
    lane_width_m: float = Field(3.5, gt=0.0)
    """Width of the ego lane, centred on the recorded path (m)."""
    road_width_m: float = Field(7.0, gt=0.0)
    """Width of the drivable road around the recorded path (m)."""
    pointcloud: PointCloudConfig = Field(default_factory=PointCloudConfig)
    """The fused point cloud written for people."""
    frame_codec: Literal["jpeg", "png"] = "jpeg"
    """How each world frame is compressed: "jpeg" (lossy, `jpeg_quality`, 4:4:4) or "png" (lossless, ~2.5x larger)."""
    jpeg_quality: int = Field(97, ge=50, le=100)
    """JPEG quality of the world frames (with frame_codec jpeg)."""

    @model_validator(mode="after")
    def _check(self) -> WorldConfig:
        if self.road_width_m < self.lane_width_m:
            raise ValueError("road_width_m must be at least lane_width_m")
        return self
