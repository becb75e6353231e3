"""The `drivesim preprocess` config: which frames, pose fusion and depth estimation (preset configs/preprocess.yaml)."""

from __future__ import annotations

from pydantic import Field, model_validator

from drivesim.pipeline.config import StageConfig
from drivesim.stages.preprocess.depth import DepthConfig
from drivesim.stages.preprocess.poses import PoseConfig


class FrameSelection(StageConfig):
    """Which frames of the trace are preprocessed (and so become the world): trace indices start:stop:step."""

    start: int = Field(0, ge=0)
    """First trace frame used (index)."""
    stop: int | None = Field(None, ge=1)
    """One past the last trace frame used (index); null = to the end of the trace."""
    step: int = Field(1, ge=1)
    """Use every step-th frame (2 halves the frame rate, the depth work and the world's size)."""


class PreviewConfig(StageConfig):
    """The depth preview image written for people (depth_preview.png)."""

    frame_count: int = Field(4, ge=1, le=12)
    """How many frames, evenly spaced over the drive, the preview shows."""


class PreprocessConfig(StageConfig):
    """Poses and per-frame depth from the trace."""

    frames: FrameSelection = Field(default_factory=FrameSelection)
    """Which trace frames to use."""
    poses: PoseConfig = Field(default_factory=PoseConfig)
    """Pose fusion (GPS + IMU + speed, odometry, or visual SfM)."""
    depth: DepthConfig = Field(default_factory=DepthConfig)
    """Per-frame depth estimation."""
    preview: PreviewConfig = Field(default_factory=PreviewConfig)
    """The depth preview image."""

    @model_validator(mode="after")
    def _check(self) -> PreprocessConfig:
        if self.frames.stop is not None and self.frames.stop <= self.frames.start:
            raise ValueError("frames.stop must be after frames.start")
        return self
