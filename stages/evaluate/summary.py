"""The eval stage's typed summary: the figures it records in its manifest and `drivesim status` shows.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSummary


class EvalSummary(StageSummary):
    """A finished evaluation: the headline metrics (means and rates over its episodes)."""

    task: str
    """lane, follow or overtake."""
    policy: str
    """expert, a run folder's name or an ONNX file's name."""
    episodes: int
    """Episodes evaluated."""
    intervention: float
    """Intervention rate (collision, off lane or over-rotation)."""
    collision: float
    """Rate of episodes with a polygon overlap > 0."""
    off_lane: float
    """Rate of episodes that left the lane."""
    over_rotation: float
    """Rate of episodes that turned too far from the road heading."""
    success: float
    """Success rate."""
    min_clearance_m: float | None
    """Mean minimum clearance over all episodes with another car, collisions (0) included [m]."""
    max_deviation_m: float | None
    """Mean maximum |lateral deviation| [m]."""
    max_yaw_rad: float | None
    """Mean maximum |yaw relative to the road| [rad]."""
    episodes_resumed: int
    """Episodes found on disk from an interrupted evaluation."""
    episodes_per_min: float | None
    """Episodes run per minute in this session (None when all were resumed) [1/min]."""
    workers: int
    """Worker processes used (Ray actors with the ray backend)."""
    videos: list[str] = []
    """MP4 files rendered."""
