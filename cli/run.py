"""`drivesim run`: the whole chain in one command, each stage skipped when its artifact is fresh."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from drivesim.cli.common import console, workspace
from drivesim.cli.ingest import TopicOption, topic_overrides
from drivesim.cli.video_options import NO_VIDEO, VideoOptions, with_video_options

if TYPE_CHECKING:
    from drivesim.chain.run import ChainRun

TrustEntryPointOption = Annotated[
    bool,
    typer.Option(
        "--trust-entry-point",
        help="Let eval.env_entry_point name your own gymnasium.Env class; its module is imported, so its code "
        "runs: only for code you trust. Without it only drivesim's own env classes are accepted.",
    ),
]


@with_video_options
def run_command(
    recording: Annotated[
        Path | None,
        typer.Argument(
            help="Your recording (.bag, rosbag2 folder, .mcap, KITTI folder, video, image folder with --fps); the "
            "flags of `drivesim ingest` apply. Default: the embedded demo drive.",
            show_default=False,
        ),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(
            "--preset",
            help="Run preset in configs/run/: recording (the default, at most 40 min of training), demo (6.0 min on "
            "a quiet 2-core VM), lane (a lane-keeping policy) or full.",
            show_default=False,
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", help="YAML file of per-stage overrides (stage: {key: value}), after the preset."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Override one stage's config value, e.g. --set train.total_steps=4096 (repeatable).",
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Redo every stage even when its artifact is fresh.")] = False,
    topic: TopicOption = None,
    video: VideoOptions = NO_VIDEO,
    trust_entry_point: TrustEntryPointOption = False,
) -> None:
    """Run every stage in order: (synth,) ingest, preprocess, build-world, meshes, train, eval, export.

    A stage whose artifact is fresh (same config, same inputs) is skipped, so running it again after a crash or
    Ctrl-C continues where it stopped. Without --preset the recording preset is used (the demo preset only when
    asked for: --preset demo). Ends with the result (the policy's Table I rows beside the expert's, the warm
    start's and the paper's), the worlds it trained on, and the paths of the HTML report and of the ONNX policy.
    """
    # Imported here so `drivesim --help` stays fast.
    from drivesim.chain.run import StageRun, choose_run_preset, load_run_preset, run_chain

    topics = [f"ingest.{o}" for o in topic_overrides(topic)]
    overrides = [*(set_ or []), *topics, *video.overrides(prefix="ingest.")]
    overrides = load_run_preset(choose_run_preset(preset), config, overrides)

    def on_stage(done: StageRun) -> None:
        state = "[dim]fresh, skipped[/]" if done.skipped else f"[green]done[/] in {done.wall_s:.1f} s"
        console.print(f"[bold]{done.stage}[/]: {state} -> {done.path}", highlight=False, soft_wrap=True)
        for note in done.notes:
            console.print(f"  [dim]{note}[/]", highlight=False, soft_wrap=True)

    result = run_chain(
        workspace(), recording, overrides, force=force, on_stage=on_stage, trust_entry_point=trust_entry_point
    )
    _print_chain_result(result)


def _print_chain_result(result: ChainRun) -> None:
    """The chain's wall time, the evaluation's Table I rows and training worlds, the report's and policy's paths."""
    from drivesim.cli.result import print_result

    total_s = sum(s.wall_s for s in result.stages)
    console.print(f"[bold green]chain finished[/] in {total_s / 60:.1f} min", highlight=False)
    if result.report_html is not None:
        print_result(result.report_html.parent, report_line=False)  # the Table I rows and the worlds trained on
        console.print(f"report: {result.report_html}", highlight=False, soft_wrap=True)
    if result.onnx is not None:
        console.print(f"policy: {result.onnx}", highlight=False, soft_wrap=True)
