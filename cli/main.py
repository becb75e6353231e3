"""The `drivesim` command: one thin sub-command per stage of the chain."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from drivesim.cli import bench, config_show, export, ingest, meshes, preprocess, run, status, synth, train, world
from drivesim.cli import eval as eval_cmd
from drivesim.cli import sim as sim_cmd
from drivesim.cli.common import err_console, state
from drivesim.pipeline.errors import DrivesimError

app = typer.Typer(
    name="drivesim",
    help="Turn a real vehicle recording into a data-driven driving simulator; train, evaluate and export a policy.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)


@app.callback()
def _global_options(
    workspace: Annotated[
        Path, typer.Option("--workspace", "-w", help="Folder holding every artifact of the chain.")
    ] = Path("drivesim-work"),
) -> None:
    state.workspace = workspace


app.command("ingest", help="Read a recording (ROS1 .bag, rosbag2, .mcap, KITTI raw) into the trace artifact.")(
    ingest.ingest_command
)
app.command("preprocess", help="Poses (GPS/IMU/odometry fusion) and per-frame depth from the trace.")(
    preprocess.preprocess_command
)
app.command("build-world", help="The simulatable world: frames, depth, reference path, index, point cloud.")(
    world.build_world_command
)
app.add_typer(meshes.meshes_app, name="meshes", help="The vehicle mesh library: build, import, preview.")
app.command("synth", help="Render a procedural drive with ground truth and write it as a ROS2 MCAP recording.")(
    synth.synth_command
)
app.command(
    "train",
    help="Train a driving policy with PPO, a CNN and an LSTM (tasks: lane, follow, overtake) into runs/<task>-<time>/; "
    "Ctrl-C keeps everything up to the last update and --resume RUN continues it.",
)(train.train_command)
app.command("eval", help="Offline closed-loop evaluation: metrics, plots, report.")(eval_cmd.eval_command)
app.add_typer(export.export_app, name="export", help="Export the policy as ONNX, checked with onnxruntime.")
app.command("run", help="Every stage of the chain, on the embedded demo drive by default.")(run.run_command)
app.command("status", help="Every stage as fresh / stale / missing, with a summary of each artifact.")(
    status.status_command
)
app.command("config", help="Show a stage's config keys with their values, units and meaning.")(
    config_show.config_command
)
app.add_typer(sim_cmd.sim_app, name="sim", help="Look at the simulator: render an episode driven by the expert.")
app.add_typer(bench.bench_app, name="bench", help="Measure the simulator: fidelity against ground truth, and speed.")


_INTERRUPTED = "interrupted: no artifact was written; run the command again to redo it"


def main() -> None:
    """Entry point: run the app; user errors become one line on stderr and exit code 2."""
    try:
        code = app(standalone_mode=False)
        # Outside standalone mode click returns (not raises) the exit code of an aborted command (Ctrl-C).
        if isinstance(code, int) and code != 0:
            if code == 130:
                err_console.print(_INTERRUPTED, highlight=False)
            sys.exit(code)
    except DrivesimError as e:
        # escape: a message's own brackets (`pip install 'drivesim[ray]'`, paths) are text, not rich markup
        err_console.print(f"[bold red]error:[/] {escape(e.one_line())}", highlight=False, soft_wrap=True)
        sys.exit(e.exit_code)
    except KeyboardInterrupt:
        err_console.print(_INTERRUPTED, highlight=False)
        sys.exit(130)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except typer.Abort:
        sys.exit(130)
    except typer.TyperException as e:  # usage errors (unknown option, missing argument)
        show = getattr(e, "show", None)
        if show is not None:
            show()
        sys.exit(getattr(e, "exit_code", 2))


if __name__ == "__main__":
    main()
