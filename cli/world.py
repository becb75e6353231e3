"""`drivesim build-world` and `drivesim bench fidelity`."""

from __future__ import annotations

import typer

from drivesim.cli.common import ConfigOption, ForceOption, SetOption
from drivesim.pipeline.errors import NotBuiltError

bench_app = typer.Typer(no_args_is_help=True)


def build_world_command(config: ConfigOption = None, set_: SetOption = None, force: ForceOption = False) -> None:
    """Build the simulatable world from the trace and the preprocessed poses and depth."""
    raise NotBuiltError("`drivesim build-world` is not built yet")


@bench_app.command("fidelity")
def fidelity_command() -> None:
    """Depth and view-synthesis fidelity against ground truth on a synthetic drive."""
    raise NotBuiltError("`drivesim bench fidelity` is not built yet")
