"""`drivesim build-world`: the simulatable world from the trace and the preprocessed artifact."""

from __future__ import annotations

from drivesim.cli.common import ConfigOption, ForceOption, SetOption
from drivesim.pipeline.errors import NotBuiltError


def build_world_command(config: ConfigOption = None, set_: SetOption = None, force: ForceOption = False) -> None:
    """Build the simulatable world from the trace and the preprocessed poses and depth."""
    raise NotBuiltError("`drivesim build-world` is not built yet")
