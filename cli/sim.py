"""`drivesim sim render`: one episode of a task with the expert, as a video, a strip of frames and a bird's-eye plot."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import console, workspace
from drivesim.sim.envs.registry import TASK_NAMES

sim_app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


@sim_app.command("render")
def render_command(
    out: Annotated[Path, typer.Option("--out", help="Folder for episode.mp4, strip.png and birdseye.png.")],
    task: Annotated[str, typer.Option("--task", help=f"One of {', '.join(TASK_NAMES)}.")] = "overtake",
    policy: Annotated[str, typer.Option("--policy", help="Who drives: expert (the privileged expert).")] = "expert",
    world: Annotated[
        Path | None, typer.Option("--world", help="World folder (default: <workspace>/world).", show_default=False)
    ] = None,
    meshes: Annotated[
        Path | None,
        typer.Option("--meshes", help="Vehicle library (default: <workspace>/meshes if built, else procedural)."),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Episode seed.")] = 0,
    mcap: Annotated[
        bool,
        typer.Option(
            "--mcap",
            help="Also write episode.mcap for Foxglove (layout docs/foxglove_layout.json), as `eval --record`.",
        ),
    ] = False,
) -> None:
    """Drive one episode: the ego camera's view as an MP4, a PNG strip and a bird's-eye plot.

    The MP4 is the full sim image with the car inserted, at 10 Hz; the strip, the frames while the ego passes the other
    car; the plot, both trajectories with the vehicle footprints.
    """
    from drivesim.pipeline.errors import DrivesimError
    from drivesim.sim.envs.render_episode import render_episode

    if policy != "expert":
        raise DrivesimError(f"--policy {policy!r}: only 'expert' can drive here; use `drivesim eval --video` for runs")
    ws = workspace()
    # the workspace's world as its readers take it (not stale, its files as built); a folder given by path, checked
    world = ws.require("world", "drivesim build-world") if world is None else world
    if meshes is None and (ws.root / "meshes").is_dir():
        meshes = ws.root / "meshes"
    for folder in (world, meshes):
        if folder is not None:
            ws.check_input(folder)
    try:
        summary = render_episode(task, world, meshes, out, seed, mcap=mcap)
    except (ValueError, FileNotFoundError) as exc:
        raise DrivesimError(str(exc)) from None
    console.print(
        f"[green]rendered[/] {summary['steps']} steps of {task} ({summary['outcome']}), min clearance "
        f"{summary['min_clearance_m']:.2f} m -> {out}/episode.mp4, strip.png, birdseye.png"
        + (", episode.mcap" if mcap else ""),
        highlight=False,
        soft_wrap=True,
    )
