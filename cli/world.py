"""`drivesim build-world`: the simulatable world from the trace and the preprocessed artifact."""

from __future__ import annotations

from drivesim.cli.common import ConfigOption, ForceOption, console, said_fresh, set_option, workspace
from drivesim.pipeline.config import load_config


def build_world_command(
    config: ConfigOption = None, set_: set_option("sim_width_px=320") = None, force: ForceOption = False
) -> None:
    """Build the simulatable world from the trace and the preprocessed poses and depth."""
    # Imported here so `drivesim --help` stays fast (the stage pulls in torch, open3d, matplotlib).
    from drivesim.stages.world.config import WorldConfig
    from drivesim.stages.world.stage import run_build_world

    cfg = load_config(WorldConfig, preset="world", config_file=config, overrides=set_)
    result = run_build_world(workspace(), cfg, force=force)
    if said_fresh(result, "world"):
        return
    s = result.summary
    console.print(
        f"[green]world[/] {s.frame_count} frames at {s.sim_width_px}x{s.sim_height_px}, "
        f"{s.path_length_m:.1f} m of path, curvature {s.curvature_min_1pm:+.4f}..{s.curvature_max_1pm:+.4f} "
        f"1/m, {s.pointcloud_points} cloud points -> {result.path} (see birdseye.png)",
        highlight=False,
        soft_wrap=True,
    )
