"""The build-world stage's typed summary: the figures it records in its manifest and `drivesim status` shows.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSummary


class WorldSummary(StageSummary):
    """What build-world records in its manifest (and `drivesim status` shows)."""

    frame_count: int
    """Frames in the world."""
    path_length_m: float
    """Length of the recorded path [m]."""
    curvature_min_1pm: float
    """Smallest path curvature [1/m]."""
    curvature_max_1pm: float
    """Largest path curvature [1/m]."""
    sim_width_px: int
    """Simulated image width [px]."""
    sim_height_px: int
    """Simulated image height [px]."""
    pointcloud_points: int
    """Points in the fused point cloud (0 when disabled)."""
    pose_source: str | None
    """Where the preprocessed poses came from."""
    depth_method: str | None
    """How the preprocessed depth was estimated."""
    seconds: float
    """Wall time of the stage [s]."""
