"""The build-world stage under the stage contract: `SPEC`, its typed summary and `run_build_world`.

Light to import; the work is in `stages/world/build.py`, imported when the stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageResult, StageSpec, deferred_build, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.world.config import WorldConfig
from drivesim.stages.world.summary import WorldSummary

SPEC: StageSpec[WorldSummary] = StageSpec(
    name="build-world",
    artifact="world",
    config_model=WorldConfig,
    preset="world",
    summary_model=WorldSummary,
    requires=("trace", "preprocessed"),
    upstream_hints={"trace": "drivesim ingest PATH", "preprocessed": "drivesim preprocess"},
    build=deferred_build("drivesim.stages.world.build:build_world"),  # cv2, numpy, open3d
)


def run_build_world(ws: Workspace, cfg: WorldConfig, force: bool = False) -> StageResult[WorldSummary]:
    """Build `<ws>/world/` from the trace and the preprocessed poses and depth; no-op when fresh unless `force`."""
    return run_stage(ws, SPEC, cfg, force=force)
