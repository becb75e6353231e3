"""`drivesim preprocess`: poses and per-frame depth from the trace."""

from __future__ import annotations

from drivesim.cli.common import (
    AddressOption,
    ConfigOption,
    ForceOption,
    backend_option,
    choose_backend,
    console,
    said_fresh,
    set_option,
    workspace,
)
from drivesim.pipeline.config import load_config

BackendOption = backend_option(
    "depth in this process",
    "camera-only (mvs) depth split over a Ray cluster's workers",
    " The same depth, frame for frame.",
)


def preprocess_command(
    config: ConfigOption = None,
    set_: set_option("depth.method=mvs") = None,
    force: ForceOption = False,
    backend: BackendOption = None,
    address: AddressOption = None,
) -> None:
    """Fuse poses (GPS + IMU + speed, odometry or visual SfM) and estimate per-frame depth (auto: lidar > stereo >
    mvs; or plane)."""
    # Imported here so `drivesim --help` stays fast (the stage pulls in torch, open3d, matplotlib).
    from drivesim.stages.preprocess.config import PreprocessConfig
    from drivesim.stages.preprocess.stage import run_preprocess

    cfg = load_config(PreprocessConfig, preset="preprocess", config_file=config, overrides=set_)
    choose_backend(backend, address, cfg)
    if cfg.backend == "ray":
        from drivesim.pipeline.ray_cluster import import_ray

        import_ray()  # a missing Ray is said before any work
    result = run_preprocess(workspace(), cfg, force=force)
    if said_fresh(result, "preprocessed"):
        return
    s = result.summary
    depth = f"median {s.depth_median_m} m" if s.depth_median_m is not None else "no near depth"
    residual = f", residual {s.residual_m} m" if s.residual_m is not None else ""
    console.print(
        f"[green]preprocessed[/] {s.frame_count} frames, {s.path_length_m:.1f} m of path "
        f"(poses: {s.pose_source}{residual}); depth {s.depth_method}: {depth}, "
        f"{100 * s.depth_far_fraction:.0f} % far -> {result.path}",
        highlight=False,
        soft_wrap=True,
    )
