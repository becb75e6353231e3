"""The meshes stage's typed summary: the figures it records in its manifest and `drivesim status` shows.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSummary


class MeshesSummary(StageSummary):
    """What the meshes stage records in its manifest (and `drivesim status` shows)."""

    model_count: int
    """Vehicles in the library."""
    imported_count: int
    """Of which imported from user mesh files."""
    full_triangles_mean: float
    """Mean triangles per vehicle at the full level of detail."""
    light_triangles_mean: float
    """Mean triangles per vehicle at the light level of detail."""
    seconds: float
    """Wall time of the stage [s]."""
