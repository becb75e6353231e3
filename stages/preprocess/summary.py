"""The preprocess stage's typed summary: the figures it records in its manifest and `drivesim status` shows.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSummary


class PreprocessSummary(StageSummary):
    """What preprocess records in its manifest (and `drivesim status` shows)."""

    pose_source: str
    """Where the poses came from (gps_imu, odometry, sfm, ...)."""
    frame_count: int
    """Frames preprocessed."""
    path_length_m: float
    """Length of the fused path [m]."""
    residual_m: float | None
    """RMS residual of the pose fit [m] (None when the source has none)."""
    depth_method: str
    """plane, mvs or lidar."""
    width_px: int
    """Frame width [px]."""
    height_px: int
    """Frame height [px]."""
    depth_median_m: float | None
    """Median estimated (non-far) depth over up to 50 frames [m]."""
    depth_p95_m: float | None
    """95th percentile of the estimated depth [m]."""
    depth_far_fraction: float
    """Fraction of pixels at the far depth (sky, nothing estimated)."""
    depth_seconds_per_frame: float | None
    """Depth estimation time per frame [s]."""
    seconds: float
    """Wall time of the stage [s]."""
