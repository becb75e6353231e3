"""`drivesim sim render`: one episode of a task, driven by the expert or a trained policy, as a video, a strip of frames
and a bird's-eye plot."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

import typer

from drivesim.cli.common import console, workspace
from drivesim.sim.envs.registry import TASK_NAMES

sim_app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


@sim_app.command("render")
def render_command(
    out: Annotated[Path, typer.Option("--out", help="Folder for episode.mp4, strip.png and birdseye.png.")],
    task: Annotated[str, typer.Option("--task", help=f"One of {', '.join(TASK_NAMES)}.")] = "overtake",
    policy: Annotated[
        str,
        typer.Option(
            "--policy",
            help="Who drives: expert (privileged), a `drivesim train` run folder or checkpoint, or an .onnx file, "
            "as `drivesim eval --policy` takes; it sees its own observation.",
        ),
    ] = "expert",
    world: Annotated[
        Path | None, typer.Option("--world", help="World folder (default: <workspace>/world).", show_default=False)
    ] = None,
    meshes: Annotated[
        Path | None,
        typer.Option("--meshes", help="Vehicle library (default: <workspace>/meshes if built, else procedural)."),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Episode seed.")] = 0,
    size: Annotated[
        str | None,
        typer.Option(
            "--size",
            help="Frame size WxH in pixels, e.g. 320x96 (default: the recording's image size).",
            show_default=False,
        ),
    ] = None,
    mcap: Annotated[
        bool,
        typer.Option(
            "--mcap",
            help="Also write episode.mcap for Foxglove (layout docs/foxglove_layout.json), as `eval --record`.",
        ),
    ] = False,
) -> None:
    """Drive one episode: the ego camera's view as an MP4, a PNG strip and a bird's-eye plot.

    The MP4 is the whole sim image with the car inserted, at 10 Hz and the recording's resolution; the strip, the
    frames while the ego passes the other car; the plot, both trajectories with the vehicle footprints.
    """
    from drivesim.pipeline.errors import DrivesimError
    from drivesim.sim.envs.render_episode import render_episode

    size_px = parse_size(size)
    ws = workspace()
    # the workspace's world as its readers take it (not stale, its files as built); a folder given by path, checked
    world = ws.require("world", "drivesim build-world") if world is None else world
    if meshes is None and (ws.root / "meshes").is_dir():
        meshes = ws.root / "meshes"
    for folder in (world, meshes):
        if folder is not None:
            ws.check_input(folder)
    driver, env_config = load_driver(policy, task)
    try:
        summary = render_episode(
            task, world, meshes, out, seed, mcap=mcap, env_config=env_config, size_px=size_px, policy=driver
        )
    except (ValueError, FileNotFoundError) as exc:
        raise DrivesimError(str(exc)) from None
    width, height = summary["size_px"]
    console.print(
        f"[green]rendered[/] {summary['steps']} steps of {task} ({summary['outcome']}) at {width}x{height}, min "
        f"clearance {summary['min_clearance_m']:.2f} m -> {out}/episode.mp4, strip.png, birdseye.png"
        + (", episode.mcap" if mcap else ""),
        highlight=False,
        soft_wrap=True,
    )


def parse_size(text: str | None) -> tuple[int, int] | None:
    """`--size` WxH as (width, height) pixels; None for None; one line (ConfigError) when malformed or under 16."""
    from drivesim.pipeline.errors import ConfigError

    if text is None:
        return None
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if match is None or min(int(match[1]), int(match[2])) < 16 or max(int(match[1]), int(match[2])) > 8192:
        raise ConfigError(f"--size {text!r}: give WIDTHxHEIGHT in pixels, each 16 to 8192, e.g. --size 640x193")
    return int(match[1]), int(match[2])


def load_driver(policy: str, task: str) -> tuple[Any, dict[str, Any] | None]:
    """(the policy, its training env config) for `--policy`: (None, None) for the expert; a run folder or ONNX file
    loaded as `drivesim eval` loads it, one line (exit 2) when it cannot be read or was trained on another task."""
    from drivesim.pipeline.errors import DrivesimError, InputError
    from drivesim.stages.evaluate.rollout import PolicySpec

    if policy == "expert":
        return None, None
    spec = PolicySpec.parse(policy)
    if spec.kind not in ("run", "onnx"):
        raise InputError("only expert, a run folder or an .onnx file can drive `sim render`", policy)
    try:
        driver = spec.load(None)
    except DrivesimError:
        raise
    except Exception as exc:  # noqa: BLE001 - an unreadable ONNX graph or run: one line, not a traceback
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise InputError(f"cannot load the policy: {first[:200]}", spec.path) from None
    trained_on = getattr(driver, "task", None)
    if trained_on and trained_on != task:
        raise InputError(f"this policy was trained on {trained_on}, not {task}; use --task {trained_on}", spec.path)
    return driver, dict(getattr(driver, "env_config", {}) or {})
