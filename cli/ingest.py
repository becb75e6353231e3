"""`drivesim ingest`: a recording in, the trace artifact out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import ConfigOption, ForceOption, console, set_option, workspace
from drivesim.cli.video_options import NO_VIDEO, VideoOptions, with_video_options
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.stages.ingest.config import TOPIC_ROLES, IngestConfig
from drivesim.stages.ingest.stage import run_ingest


def topic_overrides(topic: list[str] | None) -> list[str]:
    """`--topic camera=/x` options as `--set topics.camera=/x` overrides (so they are part of the config hash)."""
    overrides = []
    for item in topic or []:
        role, sep, name = item.partition("=")
        role = role.strip()
        if not sep or not name.strip():
            raise ConfigError(f"--topic {item!r}: expected ROLE=TOPIC, e.g. --topic camera=/cam/image_raw")
        if role not in TOPIC_ROLES:
            raise ConfigError(f"--topic {item!r}: unknown role {role!r}; roles: {', '.join(TOPIC_ROLES)}")
        overrides.append(f"topics.{role}={name.strip()}")
    return overrides


TopicOption = Annotated[
    list[str] | None,
    typer.Option(
        "--topic",
        help=f"Pick a topic by role ({', '.join(TOPIC_ROLES)}), e.g. --topic camera=/cam/image_raw; "
        "for KITTI folders camera=image_02.",
    ),
]


@with_video_options
def ingest_command(
    path: Annotated[
        Path,
        typer.Argument(
            help="ROS1 .bag, rosbag2 folder, .mcap file, KITTI raw (..._sync) or odometry folder, a video "
            "(.mp4/.mov/.mkv/.avi) or a folder of images (--fps); a video's scale from --camera-height-m or --gps."
        ),
    ],
    topic: TopicOption = None,
    video: VideoOptions = NO_VIDEO,
    config: ConfigOption = None,
    set_: set_option("image.width_px=640") = None,
    force: ForceOption = False,
) -> None:
    """Read a recording into the trace artifact."""
    overrides = [*(set_ or []), *topic_overrides(topic), *video.overrides()]
    cfg = load_config(IngestConfig, preset="ingest", config_file=config, overrides=overrides)
    if not path.exists():
        raise InputError("no such file or folder", path)
    result = run_ingest(workspace(), path, cfg, force=force)
    if result.skipped:
        console.print(f"trace is fresh ({result.path}), nothing to do; --force to redo", soft_wrap=True)
        return
    for note in result.notes:
        console.print(f"[dim]{note}[/]", highlight=False, soft_wrap=True)
    s = result.summary
    sensors = ", ".join(f"{name} {v.message_count}" for name, v in s.sensors.items())
    console.print(
        f"[green]trace[/] {result.path}: {s.frame_count} frames "
        f"{s.width_px}x{s.height_px}, {s.duration_s:.1f} s; {sensors}",
        highlight=False,
        soft_wrap=True,
    )
