"""`drivesim export onnx`: the trained policy as one ONNX graph, checked against torch with onnxruntime."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import ConfigOption, ForceOption, console, said_fresh, set_option, workspace
from drivesim.pipeline.config import load_config

export_app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


@export_app.command("onnx")
def export_onnx_command(
    run: Annotated[
        Path | None,
        typer.Option(
            "--run", help="Run folder to export (default: the workspace's newest finished run).", show_default=False
        ),
    ] = None,
    config: ConfigOption = None,
    set_: set_option("check_steps=100") = None,
    force: ForceOption = False,
) -> None:
    """Write export/policy.onnx and check it against torch with onnxruntime.

    Inputs: uint8 image, LSTM state (h, c) and episode start; outputs: steering and the new state. Preprocessing is
    inside the graph; metadata holds the input shape, region of interest, action scale, LSTM sizes and the training
    config's hash. The export is checked with onnx.checker and against torch over a 200-step rollout with a reset
    (export/check.json; it fails above 1e-4), and timed on one thread.
    """
    # Imported here so `drivesim --help` stays fast.
    from drivesim.stages.export.config import ExportConfig
    from drivesim.stages.export.stage import run_export

    overrides = list(set_ or [])
    if run is not None:
        overrides.append(f"run={run.absolute()}")
    cfg = load_config(ExportConfig, preset="export", config_file=config, overrides=overrides)
    result = run_export(workspace(), cfg, force=force)
    s = result.summary
    onnx_path = result.path / "policy.onnx"
    if said_fresh(result, "export", onnx_path):
        return
    for note in result.notes:
        console.print(note, highlight=False, soft_wrap=True)
    console.print(
        f"[green]export[/] {s.task} policy of {s.run}: {s.size_bytes / 1e3:.0f} kB, max abs diff {s.max_abs_diff:.2g}, "
        f"{s.latency_median_ms:.2f} ms/step (p99 {s.latency_p99_ms:.2f}) on one thread -> {onnx_path}",
        highlight=False,
        soft_wrap=True,
    )
