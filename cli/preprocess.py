"""`drivesim preprocess`: poses and per-frame depth from the trace."""

from __future__ import annotations

from drivesim.cli.common import ConfigOption, ForceOption, SetOption
from drivesim.pipeline.errors import NotBuiltError


def preprocess_command(config: ConfigOption = None, set_: SetOption = None, force: ForceOption = False) -> None:
    """Fuse poses and estimate per-frame depth."""
    raise NotBuiltError("`drivesim preprocess` is not built yet")
