"""`drivesim synth`: a procedural drive with ground truth, written as a ROS2 MCAP recording."""

from __future__ import annotations

from drivesim.cli.common import ConfigOption, SetOption
from drivesim.pipeline.errors import NotBuiltError


def synth_command(config: ConfigOption = None, set_: SetOption = None) -> None:
    """Render a procedural drive and write it as an MCAP recording."""
    raise NotBuiltError("`drivesim synth` is not built yet")
