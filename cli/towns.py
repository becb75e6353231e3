"""`drivesim towns`: procedural towns the tool builds itself (chain/towns.py), to train on more than one place."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import ConfigOption, ForceOption, console, set_option, workspace
from drivesim.pipeline.config import load_config

towns_app = typer.Typer(no_args_is_help=True)

SeedsArgument = Annotated[
    list[int],
    typer.Argument(help="Town seeds to build, e.g. 1 2 3 (each a different procedural town).", show_default=False),
]
DurationOption = Annotated[
    float | None,
    typer.Option("--duration-s", help="Seconds of drive per town (default 30, the preset's).", show_default=False),
]


@towns_app.command("build")
def build_command(
    seeds: SeedsArgument,
    duration_s: DurationOption = None,
    config: ConfigOption = None,
    set_: set_option("stages.preprocess.depth.method=plane") = None,
    force: ForceOption = False,
) -> None:
    """Build each town's world at <workspace>/towns/seed<N>/world.

    synth -> ingest -> preprocess -> build-world. A town that is fresh (same settings) is skipped, stage by stage;
    Ctrl-C keeps the stages done and writes nothing half: the same command continues. `drivesim train` uses these
    towns when its config's `towns` key names them. Towns 8 and 9 are tree-lined (rows of trees beside the road;
    `per_town` in configs/towns.yaml), the others mostly built up.
    """
    from drivesim.chain.towns import PRESET, TownsConfig, TownStage, build_towns, check_seeds

    overrides = list(set_ or [])
    if duration_s is not None:
        overrides.append(f"duration_s={duration_s}")
    cfg = load_config(TownsConfig, preset=PRESET, config_file=config, overrides=overrides)
    seeds = check_seeds(seeds)
    ws = workspace()
    console.print(f"towns {' '.join(map(str, seeds))}: {cfg.duration_s:g} s of drive each in {ws.root / 'towns'}")

    def on_stage(done: TownStage) -> None:
        state = "[dim]fresh, skipped[/]" if done.skipped else f"[green]done[/] in {done.wall_s:.1f} s"
        console.print(f"town seed{done.seed}: [bold]{done.stage}[/]: {state} -> {done.path}", soft_wrap=True)

    worlds = build_towns(ws, seeds, cfg, force=force, on_stage=on_stage)
    for world in worlds:
        console.print(f"world: {world}", highlight=False, soft_wrap=True)


@towns_app.command("list")
def list_command() -> None:
    """The towns of the workspace: each seed, built or not, and its world folder."""
    from drivesim.chain.towns import TOWNS_DIR, is_built, town_world

    ws = workspace()
    found = sorted(int(p.name[4:]) for p in (ws.root / TOWNS_DIR).glob("seed*") if p.is_dir() and p.name[4:].isdigit())
    if not found:
        console.print(f"no towns in {ws.root / TOWNS_DIR}; build some with `drivesim towns build 1 2 3`")
        return
    for seed in found:
        state = "built" if is_built(ws, seed) else "unfinished (`drivesim towns build` continues it)"
        console.print(f"seed{seed}: {state}: {Path(town_world(ws, seed))}", highlight=False, soft_wrap=True)
