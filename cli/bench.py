"""`drivesim bench ...`: measure the simulator against ground truth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.table import Table

from drivesim.bench.machine import machine_line, now_utc, report_header
from drivesim.cli.common import ConfigOption, console, set_option, workspace
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError
from drivesim.pipeline.progress import progress_bar
from drivesim.stages.preprocess.config import DepthConfig

bench_app = typer.Typer(no_args_is_help=True)


def figure_option(what: str, file_name: str) -> Any:
    """The `--figure PATH` option of a bench command: its `what` PNG, by default <workspace>/bench/<file_name>."""
    return Annotated[Path | None, typer.Option("--figure", help=f"{what} PNG (default <workspace>/bench/{file_name}).")]


MarkdownOption = Annotated[
    Path | None, typer.Option("--markdown", help="Also write the results as a markdown report to this file.")
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print the results as JSON instead of tables.")]

if TYPE_CHECKING:  # the fidelity module imports torch: only when the command runs
    from drivesim.bench.fidelity import FidelityResult


def fidelity_table(result: FidelityResult) -> tuple[Table, Table]:
    """Rich tables of the depth metrics and of the novel-view metrics."""
    from drivesim.bench.fidelity import DEPTH_SOURCES

    depth = Table(title=f"depth vs ground truth ({len(result.evaluated_frames)} frames)")
    for column in ("method", "AbsRel", "δ<1.25", "seconds"):
        depth.add_column(column, justify="right" if column != "method" else "left")
    for method, m in result.depth.items():
        depth.add_row(method, f"{m['abs_rel']:.3f}", f"{m['delta1']:.3f}", f"{result.depth_seconds[method]:.1f}")
    views = Table(title="novel views vs ground-truth render (over the pixels the warp fills)")
    for column in ("offset", "depth", "PSNR dB", "SSIM", "filled"):
        views.add_column(column, justify="left" if column in ("offset", "depth") else "right")
    for offset in dict.fromkeys(row["offset"] for row in result.views):
        for k, source in enumerate(DEPTH_SOURCES):
            r = result.view(offset, source)
            label = "GT (bound)" if source == "ground_truth" else source
            views.add_row(
                offset if k == 0 else "",
                label,
                f"{r['psnr_db']:.2f}",
                f"{r['ssim']:.3f}",
                f"{r['filled_fraction']:.3f}",
            )
        views.add_section()
    return depth, views


def fidelity_markdown(result: FidelityResult, command: str) -> str:
    """The results as a markdown report (machine, date, command, tables)."""
    from drivesim.bench.fidelity import DEPTH_SOURCES

    lines = [
        *report_header("Depth and view-synthesis fidelity against ground truth", machine_line(), command),
        f"- synthetic drive: seed {result.seed}, {result.frames} frames at {result.width_px}x{result.height_px}; depth "
        f"over frames {result.evaluated_frames[0]}-{result.evaluated_frames[-1]} (all neighbours present); views "
        "synthesized from the recorded frame with its depth by forward warp (paper eq. 2), compared with the "
        "ground-truth render over the pixels the warp fills",
        "",
        "| depth method | AbsRel | δ<1.25 | seconds |",
        "|---|---:|---:|---:|",
    ]
    for method, m in result.depth.items():
        lines.append(f"| {method} | {m['abs_rel']:.3f} | {m['delta1']:.3f} | {result.depth_seconds[method]:.1f} |")
    lines += ["", "| novel view | depth | PSNR (dB) | SSIM | filled |", "|---|---|---:|---:|---:|"]
    for offset in dict.fromkeys(row["offset"] for row in result.views):
        for source in DEPTH_SOURCES:
            r = result.view(offset, source)
            label = "ground truth (upper bound)" if source == "ground_truth" else source
            lines.append(f"| {offset} | {label} | {r['psnr_db']:.2f} | {r['ssim']:.3f} | {r['filled_fraction']:.3f} |")
    return "\n".join(lines) + "\n"


@bench_app.command("fidelity")
def fidelity_command(
    as_json: JsonOption = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic world.")] = 0,
    frames: Annotated[int, typer.Option("--frames", help="Frames in the synthetic drive (10 Hz).", min=2)] = 24,
    width_px: Annotated[int, typer.Option("--width", help="Image width (pixels).", min=32)] = 320,
    height_px: Annotated[int, typer.Option("--height", help="Image height (pixels).", min=20)] = 200,
    view_frames: Annotated[
        int, typer.Option("--view-frames", help="Frames whose novel views are rendered.", min=1)
    ] = 4,
    figure: figure_option("Side-by-side", "fidelity.png") = None,
    markdown: MarkdownOption = None,
    config: ConfigOption = None,
    set_: set_option("method=mvs") = None,
) -> None:
    """Depth and view-synthesis fidelity against ground truth on a synthetic drive.

    Depth AbsRel and δ<1.25 of `plane` and `mvs`; PSNR, SSIM and filled fraction of views synthesized with each
    depth at lateral offsets 0.5, 1.0, 1.5 m and yaw ±5°, with the ground-truth depth as the upper bound.
    `--set` and `--config` take depth config keys (e.g. --set mvs.num_hypotheses=32).
    """
    cfg = load_config(DepthConfig, preset=None, config_file=config, overrides=set_)
    if cfg.method != "mvs" and set_ and any(s.startswith("method=") for s in set_):
        raise ConfigError("bench fidelity always compares plane and mvs; leave depth.method alone")
    from drivesim.bench.fidelity import run_fidelity

    figure_path = figure if figure is not None else workspace().root / "bench" / "fidelity.png"
    with progress_bar("fidelity bench", total=None) as (progress, task):

        def on_progress(phase: str, done: int, total: int) -> None:
            progress.update(task, description=phase, completed=done, total=total)

        result = run_fidelity(
            seed=seed,
            n_frames=frames,
            width_px=width_px,
            height_px=height_px,
            mvs_config=cfg,
            n_view_frames=view_frames,
            figure_path=figure_path,
            progress=on_progress,
        )
    if markdown is not None:
        command = f"drivesim bench fidelity --seed {seed} --frames {frames} --width {width_px} --height {height_px}"
        command += f" --view-frames {view_frames}" + "".join(f" --set {o}" for o in set_ or [])
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(fidelity_markdown(result, command))
    if as_json:
        print(json.dumps({**result.to_json(), "figure": str(figure_path)}, indent=2))
        return
    depth, views = fidelity_table(result)
    console.print(depth)
    console.print(views)
    console.print(f"figure: {figure_path}")


@bench_app.command("sim")
def sim_command(
    as_json: JsonOption = False,
    world: Annotated[
        Path | None, typer.Option("--world", help="World folder (default: the workspace's world/).")
    ] = None,
    steps: Annotated[int, typer.Option("--steps", help="Env steps per measurement.", min=10)] = 300,
    tasks: Annotated[
        str, typer.Option("--tasks", help="Comma-separated tasks (overtake:eval: episodes that end at the pass).")
    ] = "lane,follow,overtake,overtake:eval",
    markdown: MarkdownOption = None,
) -> None:
    """Simulator speed: env steps/s per task and ms per step by part.

    One process, one env per core and batched envs at the default observation; ms per step split into dynamics,
    association, warp, car raster, harmonization and rewards; and the view synthesizer alone.
    """
    from drivesim.bench.sim_speed import TASKS, run_sim_speed, sim_speed_markdown

    world_path = world if world is not None else workspace().root / "world"
    if not (world_path / "world.json").is_file():
        raise ConfigError(f"{world_path}: no world here; build one with `drivesim build-world` or pass --world")
    chosen = tuple(t.strip() for t in tasks.split(",") if t.strip())
    if not chosen or any(t not in TASKS for t in chosen):
        raise ConfigError(f"--tasks {tasks!r}: choose from {', '.join(TASKS)}")
    with progress_bar("simulator speed", total=None):
        result = run_sim_speed(world_path, tasks=chosen, steps=steps)
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        command = f"drivesim bench sim --world {world_path} --steps {steps} --tasks {','.join(chosen)}"
        markdown.write_text(sim_speed_markdown(result, command))
    if as_json:
        print(json.dumps(result.to_json(), indent=2))
        return
    table = Table(title=f"simulator speed ({result.machine})")
    for column in ("task", "steps/s", "all cores", "batched", "warp ms", "raster ms", "harmonize ms", "total ms"):
        table.add_column(column, justify="left" if column == "task" else "right")
    for t in result.tasks:
        ms = t.ms_per_step
        table.add_row(
            t.task, f"{t.steps_per_s:.0f}", f"{t.steps_per_s_all_cores:.0f}", f"{t.batched_steps_per_s:.0f}",
            f"{ms['warp']:.2f}", f"{ms['raster']:.2f}", f"{ms['harmonize']:.2f}", f"{ms['total']:.2f}",
        )  # fmt: skip
    console.print(table)
    for key, value in result.view_ms.items():
        console.print(f"view alone, {key}: {value:.2f}")


@bench_app.command("car-fidelity")
def car_fidelity_command(
    as_json: Annotated[bool, typer.Option("--json", help="Print the results as JSON instead of a report.")] = False,
    real_world: Annotated[
        list[str] | None,
        typer.Option(
            "--real-world",
            help="METHOD=WORLD_DIR of a real drive's world, e.g. plane=/tmp/ws/world "
            "(repeatable; one per depth method).",
        ),
    ] = None,
    frames: Annotated[int, typer.Option("--frames", help="Synthetic frames evaluated.", min=1)] = 3,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic world and the car.")] = 0,
    figure: figure_option("Side-by-side", "car_fidelity.png") = None,
    markdown: MarkdownOption = None,
) -> None:
    """Inserted-car fidelity and view synthesis against ground truth.

    The synthetic world with lighting and harmonization off and on, at lateral offsets 0, 0.5, 1 m; and real frames:
    a recorded frame warped to a later frame's pose, per depth method.
    """
    worlds: dict[str, Path] = {}
    for item in real_world or []:
        method, sep, folder = item.partition("=")
        if not sep or not (Path(folder) / "world.json").is_file():
            raise ConfigError(f"--real-world {item!r}: expected METHOD=WORLD_DIR with a built world there")
        worlds[method] = Path(folder)
    from drivesim.bench.car_fidelity import car_fidelity_markdown, run_car_fidelity

    figure_path = figure if figure is not None else workspace().root / "bench" / "car_fidelity.png"
    with progress_bar("car fidelity", total=None):
        result = run_car_fidelity(worlds, figure_path, frames=frames, seed=seed)
    command = f"drivesim bench car-fidelity --frames {frames} --seed {seed}"
    command += "".join(f" --real-world {m}={p}" for m, p in worlds.items())
    report = car_fidelity_markdown(result, machine_line(), command)
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(report)
    if as_json:
        print(json.dumps(dataclasses.asdict(result), indent=2))
        return
    console.print(report)


@bench_app.command("stereo")
def stereo_command(
    folder: Annotated[
        Path, typer.Argument(help="KITTI odometry stereo folder: image_l/, image_r/, calib.txt, poses.txt.")
    ],
    world: Annotated[
        list[Path] | None, typer.Option("--world", help="A world built from this folder: its depth is a row too.")
    ] = None,
    methods: Annotated[
        str, typer.Option("--methods", help="Comma-separated depth methods run on the left frames alone.")
    ] = "plane,mvs",
    as_json: Annotated[bool, typer.Option("--json", help="Print the results as JSON instead of a report.")] = False,
    figure: figure_option("Worst-frame", "stereo_worst.png") = None,
    markdown: MarkdownOption = None,
    config: ConfigOption = None,
    set_: set_option("method=mvs") = None,
) -> None:
    """Real lateral views: left frames warped into the right camera, against the real right image.

    Rows: identity (left as right), each depth method on the left frames alone, each --world's stored depth, and
    SGBM depth from the true pair (a reference that sees the answer). PSNR and SSIM over filled pixels, the filled
    fraction, and whole-image PSNR with holes counted. `--set` and `--config` take depth config keys.
    """
    from drivesim.bench.stereo import run_stereo_bench, stereo_markdown
    from drivesim.stages.preprocess.depth import DEPTH_METHODS

    cfg = load_config(DepthConfig, preset=None, config_file=config, overrides=set_)
    chosen = tuple(m.strip() for m in methods.split(",") if m.strip())
    usable = [m for m in DEPTH_METHODS if m not in ("lidar", "stereo", "auto")]
    if any(m not in usable for m in chosen):
        raise ConfigError(f"--methods {methods!r}: choose from {', '.join(usable)} (the pair's SGBM is always a row)")
    for w in world or []:
        if not (w / "world.json").is_file():
            raise ConfigError(f"--world {w}: no world here; build one with `drivesim build-world`")
    figure_path = figure if figure is not None else workspace().root / "bench" / "stereo_worst.png"
    with progress_bar("stereo bench", total=None) as (progress, task):
        result = run_stereo_bench(
            folder, chosen, tuple(world or ()), depth_config=cfg, figure_path=figure_path,
            progress=lambda phase: progress.update(task, description=phase),
        )  # fmt: skip
    command = f"drivesim bench stereo {folder} --methods {','.join(chosen)}"
    command += "".join(f" --world {w}" for w in world or []) + "".join(f" --set {o}" for o in set_ or [])
    report = stereo_markdown(result, machine_line(), command, now_utc())
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(report)
    if as_json:
        print(json.dumps(result.to_json(), indent=2))
        return
    console.print(report)
