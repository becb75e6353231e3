"""`drivesim synth`: a procedural drive with ground truth, written as a ROS2 MCAP recording."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from drivesim.cli.common import ConfigOption, console, set_option, workspace
from drivesim.pipeline.config import load_config
from drivesim.pipeline.progress import progress_bar
from drivesim.stages.synth.config import SynthConfig


def synth_command(
    seed: Annotated[int | None, typer.Option("--seed", help="World and sensor-noise seed (config: seed).")] = None,
    duration_s: Annotated[
        float | None, typer.Option("--duration-s", help="Length of the drive in seconds (config: drive.duration_s).")
    ] = None,
    rate_hz: Annotated[
        float | None, typer.Option("--rate-hz", help="Camera frame rate in Hz (config: camera.rate_hz).")
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Recording to write (default <workspace>/recordings/synth-seed<N>.mcap)."),
    ] = None,
    preview: Annotated[
        bool,
        typer.Option(
            "--preview", help="Also write <name>.preview.png (frames) and <name>.map.png (map) beside <name>.mcap."
        ),
    ] = False,
    config: ConfigOption = None,
    set_: set_option("drive.duration_s=60") = None,
) -> None:
    """Render a procedural drive and write it as an MCAP recording."""
    overrides = list(set_ or [])
    for key, value in (("seed", seed), ("drive.duration_s", duration_s), ("camera.rate_hz", rate_hz)):
        if value is not None:
            overrides.append(f"{key}={value}")
    cfg = load_config(SynthConfig, preset="synth", config_file=config, overrides=overrides)
    if output is None:
        output = workspace().root / "recordings" / f"synth-seed{cfg.seed}.mcap"

    from drivesim.stages.synth.synthesize import synthesize  # imports torch: only when rendering

    frames = int(cfg.drive.duration_s * cfg.camera.rate_hz + 0.999999)
    with progress_bar(f"rendering {cfg.camera.width_px}x{cfg.camera.height_px}", total=frames) as (progress, task):
        result = synthesize(
            cfg,
            output,
            preview=preview,
            on_frame=lambda done, total: progress.update(task, completed=done, total=total),
        )

    table = Table(show_header=False, box=None, pad_edge=False)
    table.add_row("recording", str(result.output))
    table.add_row("size", f"{result.size_bytes / 1e6:.1f} MB")
    table.add_row(
        "drive",
        f"{cfg.drive.duration_s:g} s, {result.path_length_m:.0f} m, {result.frame_count} frames "
        f"at {cfg.camera.rate_hz:g} Hz ({cfg.camera.width_px}x{cfg.camera.height_px})",
    )
    table.add_row("messages", ", ".join(f"{t} {n}" for t, n in result.message_counts.items()))
    table.add_row("world", f"seed {cfg.seed}, {result.triangle_count} triangles; rebuild with {result.sidecar.name}")
    table.add_row("time", f"{result.total_s:.1f} s ({result.render_s / max(result.frame_count, 1):.2f} s per frame)")
    for path in result.previews:
        table.add_row("preview", str(path))
    console.print(table)
