"""The ingest stage under the stage contract: `SPEC`, its typed summary and `run_ingest`.

Light to import; the readers are in `stages/ingest/run.py` and the modules it dispatches to.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, StageSummary, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.ingest.config import IngestConfig


class SensorSummary(BaseModel):
    """One sensor stream read from the recording."""

    topic: str
    """The topic (or KITTI folder) it came from."""
    type: str
    """Its message type."""
    message_count: int
    """Messages read."""


class IngestSummary(StageSummary):
    """What ingest records in its manifest (and `drivesim status` shows)."""

    frame_count: int
    """Camera frames in the trace."""
    duration_s: float
    """From the first to the last frame [s]."""
    width_px: int
    """Working frame width [px]."""
    height_px: int
    """Working frame height [px]."""
    sensors: dict[str, SensorSummary]
    """Sensor name -> where it came from and how many messages."""
    skipped: dict[str, int] = {}
    """Sensor name -> messages left out as unreadable or non-finite (a damaged frame, a NaN GPS fix)."""


# Where the decoders' own messages (libjpeg, libpng, FFmpeg, OpenCV) go instead of the terminal.
NATIVE_LOG = Path("logs") / "ingest-decoders.log"


def _build(ctx: BuildContext) -> IngestSummary:
    from drivesim.stages.ingest.run import ingest_recording  # rosbags, mcap, cv2: only when it runs

    recording, log = ctx.external["recording"], ctx.workspace.root / NATIVE_LOG
    result = ingest_recording(recording, ctx.config, ctx.dir, native_log=log)  # type: ignore[arg-type]
    ctx.notes.extend(result.notes)
    return IngestSummary.model_validate(result.summary)


SPEC: StageSpec[IngestSummary] = StageSpec(
    name="ingest",
    artifact="trace",
    command="drivesim ingest PATH",
    config_model=IngestConfig,
    summary_model=IngestSummary,
    build=_build,
)


def run_ingest(ws: Workspace, recording: Path, cfg: IngestConfig, force: bool = False) -> StageResult[IngestSummary]:
    """Read the recording (ROS1 bag, rosbag2 folder, MCAP file, KITTI folder) into `<ws>/trace/`.

    Does nothing when the trace is fresh for this config and recording, unless `force`.
    """
    return run_stage(ws, SPEC, cfg, force=force, external={"recording": Path(recording)})
