"""Commands the design has but that are not built yet: they say so plainly and exit 2."""

from __future__ import annotations

import typer

from drivesim.pipeline.errors import NotBuiltError


def not_built_command(app: typer.Typer, name: str, help_text: str) -> None:
    """Register `drivesim NAME ...` (any arguments) reporting that it is not built yet."""

    def _not_built(ctx: typer.Context) -> None:
        raise NotBuiltError(f"`drivesim {name}` is not built yet in this version of drivesim")

    app.command(
        name,
        help=f"{help_text} [not built yet]",
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )(_not_built)
