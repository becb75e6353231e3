"""`drivesim bench ...`: measure the simulator against ground truth."""

from __future__ import annotations

import typer

from drivesim.pipeline.errors import NotBuiltError

bench_app = typer.Typer(no_args_is_help=True)


@bench_app.command("fidelity")
def fidelity_command() -> None:
    """Depth and view-synthesis fidelity against ground truth on a synthetic drive."""
    raise NotBuiltError("`drivesim bench fidelity` is not built yet")
