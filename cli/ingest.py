"""`drivesim ingest`: a recording in, the trace artifact out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import ConfigOption, ForceOption, SetOption
from drivesim.pipeline.errors import NotBuiltError


def ingest_command(
    path: Annotated[Path, typer.Argument(help="ROS1 .bag, rosbag2 folder, .mcap file or KITTI raw drive folder.")],
    topic: Annotated[
        list[str] | None, typer.Option("--topic", help="Pick a topic by role, e.g. --topic camera=/cam/image_raw.")
    ] = None,
    config: ConfigOption = None,
    set_: SetOption = None,
    force: ForceOption = False,
) -> None:
    """Read a recording into the trace artifact."""
    raise NotBuiltError("`drivesim ingest` is not built yet")
