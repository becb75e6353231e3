"""The preprocess stage under the stage contract: `SPEC`, its typed summary and `run_preprocess`.

Light to import (the registry and `--help` read it); the work is in `stages/preprocess/run.py`, imported when the
stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageResult, StageSpec, deferred_build, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess.config import PreprocessConfig
from drivesim.stages.preprocess.summary import PreprocessSummary

SPEC: StageSpec[PreprocessSummary] = StageSpec(
    name="preprocess",
    artifact="preprocessed",
    config_model=PreprocessConfig,
    summary_model=PreprocessSummary,
    requires=("trace",),
    upstream_hints={"trace": "drivesim ingest PATH"},
    build=deferred_build("drivesim.stages.preprocess.run:build_preprocessed"),  # numpy, scipy, torch
)


def run_preprocess(ws: Workspace, cfg: PreprocessConfig, force: bool = False) -> StageResult[PreprocessSummary]:
    """Fuse poses and estimate per-frame depth for the workspace's trace into `<ws>/preprocessed/`.

    Does nothing when the artifact is fresh for this config and trace, unless `force`.
    """
    return run_stage(ws, SPEC, cfg, force=force)
