"""The build-world stage under the stage contract: `SPEC`, its typed summary and `run_build_world`.

Light to import; the work is in `stages/world/build.py`, imported when the stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.world.config import WorldConfig
from drivesim.stages.world.summary import WorldSummary


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
    upstream_hints={"trace": "drivesim ingest PATH", "preprocessed": "drivesim preprocess"},
    build=_build,
)


def run_build_world(ws: Workspace, cfg: WorldConfig, force: bool = False) -> StageResult[WorldSummary]:
    """Build `<ws>/world/` from the trace and the preprocessed poses and depth; no-op when fresh unless `force`."""
    return run_stage(ws, SPEC, cfg, force=force)
