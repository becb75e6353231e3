"""The preprocess stage under the stage contract: `SPEC`, its typed summary and `run_preprocess`.

Light to import (the registry and `--help` read it); the work is in `stages/preprocess/run.py`, imported when the
stage runs.
"""

from __future__ import annotations

from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, StageSummary, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess.config import PreprocessConfig


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
    build=_build,
)


def run_preprocess(ws: Workspace, cfg: PreprocessConfig, force: bool = False) -> StageResult[PreprocessSummary]:
    """Fuse poses and estimate per-frame depth for the workspace's trace into `<ws>/preprocessed/`.

    Does nothing when the artifact is fresh for this config and trace, unless `force`.
    """
    from drivesim.stages.chain import make_hints

    return run_stage(ws, SPEC, cfg, force=force, make_hints=make_hints())
