"""What every CLI command shares: the workspace option, config options, and one-line error reporting."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from drivesim.pipeline.workspace import DEFAULT_WORKSPACE, Workspace

console = Console()
err_console = Console(stderr=True)


class CliState:
    """Options given before the command name (`drivesim --workspace W ingest ...`)."""

    workspace: Path = DEFAULT_WORKSPACE


state = CliState()

ConfigOption = Annotated[
    Path | None, typer.Option("--config", help="YAML file of config values for this stage.", show_default=False)
]
SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override one config value, e.g. --set image.width_px=640 (repeatable)."),
]
ForceOption = Annotated[bool, typer.Option("--force", help="Redo the stage even when its artifact is fresh.")]


def workspace() -> Workspace:
    """The workspace chosen with `--workspace` (default ./drivesim-work)."""
    return Workspace(state.workspace)
