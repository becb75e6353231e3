"""The `drivesim` command: one thin sub-command per stage of the chain.

`main` is the CLI's one error boundary: every command raises and none catches. A `DrivesimError` (bad input, a
missing artifact), a pydantic `ValidationError`, an `OSError` (disk full, permission denied) becomes one line on
stderr and an exit code (2 for input errors); Ctrl-C, SIGTERM and SIGHUP print what was kept and how to continue
(130, 143, 129).
A real bug still shows its traceback.
"""

from __future__ import annotations

import errno
import shutil
import signal
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from drivesim.cli import bench, config_show, export, ingest, meshes, preprocess, run, status, synth, towns, train, world
from drivesim.cli import eval as eval_cmd
from drivesim.cli import sim as sim_cmd
from drivesim.cli.common import err_console, state
from drivesim.pipeline.errors import DrivesimError, Interrupted, Terminated, printable
from drivesim.sim.envs.registry import TASK_NAMES


class _StoppedError(Exception):
    """Carries a KeyboardInterrupt out of click, which would turn it into a bare exit code 130 and lose its text."""

    def __init__(self, interrupt: KeyboardInterrupt) -> None:
        super().__init__(str(interrupt))
        self.interrupt = interrupt


class _Group(typer.core.TyperGroup):
    """The top-level command group: hands an interrupt to `main` with its message."""

    def invoke(self, ctx: typer.Context) -> object:  # noqa: D102
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as e:
            raise _StoppedError(e) from e


app = typer.Typer(
    cls=_Group,
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


app.command("ingest", help="Read a recording (ROS1 .bag, rosbag2, .mcap, KITTI, video) into the trace artifact.")(
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
app.add_typer(towns.towns_app, name="towns", help="Procedural towns to train on, in <workspace>/towns/seed<N>/world.")
app.command(
    "train",
    help="Train a driving policy (PPO, CNN + LSTM) into runs/<task>-<time>/.\n\n"
    f"Tasks: {', '.join(TASK_NAMES)}. Ctrl-C keeps everything up to the last update and --resume RUN continues it.",
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
_TERMINATED = "terminated ({name}): no artifact was written; run the command again to redo it"
SIGTERM_EXIT_CODE = 128 + signal.SIGTERM
SIGINT_EXIT_CODE = 128 + signal.SIGINT
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Signals handled as Ctrl-C with the same cleanup: SIGTERM (`timeout`, Slurm, `docker stop`) and SIGHUP (the
terminal or ssh session closed); each exits 128 + its number with one line naming it."""


class _Signals:
    """Which signal stopped the command (the exit code depends on it): a signal number, or None for Ctrl-C."""

    stopped_by: int | None = None


def _on_stop_signal(signum: int, frame: object) -> None:
    """SIGTERM or SIGHUP as Ctrl-C: the same cleanup (temporary folders, worker processes), then exit 128 + signum."""
    _Signals.stopped_by = signum
    signal.signal(signum, signal.SIG_DFL)  # the same signal again ends the process at once
    raise Terminated(signum)


def _print_error(text: str) -> None:
    # escape: a message's own brackets (`pip install 'drivesim[ray]'`, paths) are text, not rich markup
    err_console.print(f"[bold red]error:[/] {escape(printable(text))}", highlight=False, soft_wrap=True)


def _os_error_line(e: OSError) -> str:
    """One line for an OS error: which path, and for a full disk how much space is left there."""
    path = e.filename if e.filename is not None else None
    if e.errno == errno.ENOSPC:
        folder = Path(path).parent if path is not None else Path(state.workspace).absolute()
        return f"disk full: no space left on the device of {folder}{_free_space(folder)}; free some space and run again"
    if e.errno in (errno.EACCES, errno.EPERM):
        return f"permission denied: {path if path is not None else 'a file this command needed'}"
    if e.errno == errno.EROFS:
        return f"read-only file system: cannot write {path if path is not None else state.workspace}"
    reason = e.strerror or str(e).strip() or type(e).__name__  # an OSError raised with a text has no strerror
    return f"{reason}: {path}" if path is not None else f"{reason} ({type(e).__name__})"


def _free_space(folder: Path) -> str:
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        return f" ({shutil.disk_usage(probe).free / 1e6:.1f} MB free there)"
    except OSError:
        return ""


def _stop(interrupt: KeyboardInterrupt) -> None:
    """Exit after Ctrl-C (130), SIGTERM (143) or SIGHUP (129) with one line saying what was kept and how to go on."""
    signum = _Signals.stopped_by or (interrupt.signum if isinstance(interrupt, Terminated) else None)
    code = SIGINT_EXIT_CODE if signum is None else 128 + signum
    if isinstance(interrupt, Interrupted):
        text = interrupt.message
        if signum is not None:
            text = text.replace("interrupted", f"terminated ({signal.Signals(signum).name})", 1)
    else:
        text = _INTERRUPTED if signum is None else _TERMINATED.format(name=signal.Signals(signum).name)
    err_console.print(escape(printable(text)), highlight=False, soft_wrap=True)
    sys.exit(code)


def main() -> None:
    """Entry point: run the app; every user or OS error becomes one line on stderr (the CLI's one error boundary)."""
    from pydantic import ValidationError

    from drivesim.pipeline.config import validation_line
    from drivesim.sim.world_checks import WorldError

    for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is signal.SIG_DFL:  # not under nohup (SIGHUP ignored) or a caller's handler
            signal.signal(signum, _on_stop_signal)
    try:
        code = app(standalone_mode=False)
        # Outside standalone mode click returns (not raises) the exit code of an aborted command.
        if isinstance(code, int) and code != 0:
            if code == SIGINT_EXIT_CODE:
                _stop(KeyboardInterrupt())
            sys.exit(code)
    except DrivesimError as e:
        _print_error(e.one_line())
        sys.exit(e.exit_code)
    except _StoppedError as e:
        _stop(e.interrupt)
    except KeyboardInterrupt as e:
        _stop(e)
    except ValidationError as e:
        _print_error(validation_line(e))
        sys.exit(2)
    except WorldError as e:  # a damaged world met outside the stages that say so themselves (`drivesim sim ...`)
        _print_error(str(e))
        sys.exit(2)
    except OSError as e:
        _print_error(_os_error_line(e))
        sys.exit(1)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except typer.Abort:
        _stop(KeyboardInterrupt())
    except typer.TyperException as e:  # usage errors (unknown option, missing argument)
        show = getattr(e, "show", None)
        if show is not None:
            show()
        sys.exit(getattr(e, "exit_code", 2))


if __name__ == "__main__":
    main()
