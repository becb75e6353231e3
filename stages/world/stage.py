"""The build-world stage under the stage contract: `SPEC`, its typed summary and `run_build_world`.

Light to import; the work is in `stages/world/build.py`, imported when the stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, StageSummary, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.world.config import WorldConfig


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


def _build(ctx: BuildContext) -> WorldSummary:
    from drivesim.stages.world.build import build_world  # cv2, numpy, open3d: only when it runs

    return build_world(ctx)


SPEC: StageSpec[WorldSummary] = StageSpec(
    name="build-world",
    artifact="world",
    command="drivesim build-world",
    config_model=WorldConfig,
    preset="world",
    summary_model=WorldSummary,
    requires=("trace", "preprocessed"),
    build=_build,
)


def run_build_world(ws: Workspace, cfg: WorldConfig, force: bool = False) -> StageResult[WorldSummary]:
    """Build `<ws>/world/` from the trace and the preprocessed poses and depth; no-op when fresh unless `force`."""
    from drivesim.stages.chain import make_hints

    return run_stage(ws, SPEC, cfg, force=force, make_hints=make_hints())
