"""What every CLI command shares: the workspace option, config options, and one-line error reporting."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

from drivesim.pipeline.workspace import DEFAULT_WORKSPACE, Workspace

# Piped into a file or another program there is no window to fit: tables and lines keep their full width there
# instead of rich's 80 columns, which cut table cells ("episod…") in a log.
PIPED_WIDTH = 100_000
console = Console(width=None if sys.stdout.isatty() else PIPED_WIDTH)
err_console = Console(stderr=True)


class CliState:
    """Options given before the command name (`drivesim --workspace W ingest ...`)."""

    workspace: Path = DEFAULT_WORKSPACE


state = CliState()

ConfigOption = Annotated[
    Path | None, typer.Option("--config", help="YAML file of config values for this stage.", show_default=False)
]


def set_option(example: str) -> Any:
    """The `--set KEY=VALUE` option of a command, its help showing `example` (one of that command's own keys)."""
    return Annotated[
        list[str] | None,
        typer.Option(
            "--set", help=f"Override one config value, e.g. --set {example} (repeatable; `drivesim config` lists keys)."
        ),
    ]


SetOption = set_option("KEY=VALUE")
ForceOption = Annotated[bool, typer.Option("--force", help="Redo the stage even when its artifact is fresh.")]


def said_fresh(result: Any, name: str, path: Path | None = None, plural: bool = False) -> bool:
    """True, after one line saying so, when the stage skipped its artifact `name` as fresh (`path`: the file to name,
    default the artifact's folder)."""
    if not result.skipped:
        return False
    verb, pronoun = ("are", "them") if plural else ("is", "it")
    shown = path if path is not None else result.path
    console.print(f"{name} {verb} fresh, nothing to do ({shown}); --force redoes {pronoun}", soft_wrap=True)
    return True


def workspace() -> Workspace:
    """The workspace chosen with `--workspace` (default ./drivesim-work); one line (exit 2) when that path is a
    file, a FIFO or a device rather than a folder."""
    from drivesim.pipeline.errors import InputError

    root = Path(state.workspace)
    if root.exists() and not root.is_dir():
        raise InputError("is not a folder; --workspace takes a folder (made when it does not exist)", root)
    return Workspace(root)


def backend_option(local: str, ray: str, more: str = "") -> Any:
    """The `--backend local|ray` option of a command, its help saying what `local` and `ray` run (`more` after it)."""
    return Annotated[
        str | None,
        typer.Option(
            "--backend",
            help=f"local: {local} (default); ray: {ray} (needs `pip install 'drivesim\\[ray]'`).{more}",
            show_default=False,
        ),
    ]


AddressOption = Annotated[
    str | None,
    typer.Option(
        "--address",
        help="With --backend ray: 'auto' (a cluster started by `ray start` here) or the head's host:port; default: "
        "start Ray here. Every node needs drivesim and the files at the same paths.",
        show_default=False,
    ),
]


def choose_backend(backend: str | None, address: str | None, config: Any) -> None:
    """Set `config.backend` / `config.address` from --backend / --address, refusing a bad pair with one line."""
    from drivesim.pipeline.errors import ConfigError

    if backend is not None:
        if backend not in ("local", "ray"):
            raise ConfigError(f"--backend {backend!r}: choose local or ray")
        config.backend = backend
    if address is not None:
        config.address = address
    if config.address is not None and config.backend != "ray":
        raise ConfigError("--address is the Ray cluster's address: give it with --backend ray")
