"""The preprocess stage under the stage contract: `SPEC`, its typed summary and `run_preprocess`.

Light to import (the registry and `--help` read it); the work is in `stages/preprocess/run.py`, imported when the
stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess.config import PreprocessConfig
from drivesim.stages.preprocess.summary import PreprocessSummary


def _build(ctx: BuildContext) -> PreprocessSummary:
    from drivesim.stages.preprocess.run import build_preprocessed  # numpy, scipy, torch: only when it runs

    return build_preprocessed(ctx)


SPEC: StageSpec[PreprocessSummary] = StageSpec(
    name="preprocess",
    artifact="preprocessed",
    command="drivesim preprocess",
    config_model=PreprocessConfig,
    preset="preprocess",
    summary_model=PreprocessSummary,
    requires=("trace",),
    upstream_hints={"trace": "drivesim ingest PATH"},
    build=_build,
)


def run_preprocess(ws: Workspace, cfg: PreprocessConfig, force: bool = False) -> StageResult[PreprocessSummary]:
    """Fuse poses and estimate per-frame depth for the workspace's trace into `<ws>/preprocessed/`.

    Does nothing when the artifact is fresh for this config and trace, unless `force`.
    """
    return run_stage(ws, SPEC, cfg, force=force)
