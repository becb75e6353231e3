"""`drivesim run`: the whole chain in one command, each stage skipped when its artifact is fresh."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from drivesim.cli.common import AddressOption, backend_option, console, workspace
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


BackendOption = backend_option(
    "preprocess's depth in this process",
    "preprocess's camera-only (mvs) depth split over a Ray cluster's workers",
)


@with_video_options
def run_command(
    recordings: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Your recording(s): .bag, rosbag2 folder, .mcap, KITTI folder, video, image folder (--fps); "
            "ingest's flags apply. Several: a world each, one policy trained on all (docs/data.md). Default: "
            "demo drive.",
            show_default=False,
        ),
    ] = None,
    recordings_file: Annotated[
        Path | None,
        typer.Option(
            "--recordings-file",
            help="Text file naming recordings, one path per line (# comments; relative to the file's folder), "
            "after those given as arguments.",
            show_default=False,
        ),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(
            "--preset",
            help="Run preset in configs/run/: recording (the default, the whole chain in an hour), demo (5.5 min on "
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
    backend: BackendOption = None,
    address: AddressOption = None,
) -> None:
    """Run every stage in order: (synth,) ingest, preprocess, build-world, meshes, train, eval, export.

    A stage whose artifact is fresh (same config, same inputs) is skipped, so running it again after a crash or
    Ctrl-C continues where it stopped. Without --preset the recording preset is used (the demo preset only when
    asked for: --preset demo). Ends with the result (the policy's Table I rows beside the expert's, the warm
    start's and the paper's; with several recordings a row per recording and the pooled one), the worlds it trained
    on, and the paths of the HTML report and of the ONNX policy.
    """
    # Imported here so `drivesim --help` stays fast.
    from drivesim.chain.recordings import expand_recordings
    from drivesim.chain.run import StageRun, choose_run_preset, load_run_preset, run_chain

    given = expand_recordings(recordings or [], recordings_file)
    if len(given) > 1:
        _refuse_one_video_options(video)
    topics = [f"ingest.{o}" for o in topic_overrides(topic)]
    overrides = [*(set_ or []), *topics, *video.overrides(prefix="ingest."), *_backend_overrides(backend, address)]
    overrides = load_run_preset(choose_run_preset(preset), config, overrides)

    def on_stage(done: StageRun) -> None:
        state = "[dim]fresh, skipped[/]" if done.skipped else f"[green]done[/] in {done.wall_s:.1f} s"
        name = f"{done.recording}: " if done.recording else ""
        console.print(f"[bold]{name}{done.stage}[/]: {state} -> {done.path}", highlight=False, soft_wrap=True)
        for note in done.notes:
            console.print(f"  [dim]{note}[/]", highlight=False, soft_wrap=True)

    more = {"more_recordings": given[1:]} if len(given) > 1 else {}
    first = given[0] if given else None
    result = run_chain(
        workspace(), first, overrides, force=force, on_stage=on_stage, trust_entry_point=trust_entry_point, **more
    )
    _print_chain_result(result)


def _backend_overrides(backend: str | None, address: str | None) -> list[str]:
    """preprocess.backend / preprocess.address overrides from --backend / --address (a bad pair is one line; Ray's
    import is checked before any work)."""
    from drivesim.pipeline.errors import ConfigError

    if backend is not None and backend not in ("local", "ray"):
        raise ConfigError(f"--backend {backend!r}: choose local or ray")
    if address is not None and backend != "ray":
        raise ConfigError("--address is the Ray cluster's address: give it with --backend ray")
    if backend == "ray":
        from drivesim.pipeline.ray_cluster import import_ray

        import_ray()
    out = [] if backend is None else [f"preprocess.backend={backend}"]
    return out if address is None else [*out, f"preprocess.address={address}"]


def _refuse_one_video_options(video: VideoOptions) -> None:
    """--gps FILE and --video-start-utc describe one video: with several recordings, one line saying what to do."""
    from drivesim.pipeline.errors import ConfigError

    if video.gps is not None and video.gps.lower() != "none":
        raise ConfigError("--gps FILE is one video's track: with several recordings put each track beside its video")
    if video.video_start_utc is not None:
        raise ConfigError("--video-start-utc is one video's start: with several recordings run them one by one")


def _print_chain_result(result: ChainRun) -> None:
    """The chain's wall time, the evaluation's Table I rows and training worlds, the report's and policy's paths."""
    from drivesim.cli.result import print_result, print_worlds

    total_s = sum(s.wall_s for s in result.stages)
    trained = next((s.summary for s in result.stages if s.stage == "train" and not s.skipped), {})
    training = ""
    if trained.get("wall_s") is not None and trained.get("steps") is not None:
        training = f" (training {trained['wall_s'] / 60:.1f} min, {trained['steps']} env steps)"
    console.print(f"[bold green]chain finished[/] in {total_s / 60:.1f} min{training}", highlight=False)
    if result.report_html is not None:
        print_worlds(result.report_html.parent / "metrics.json")  # several recordings: a row each and pooled
        print_result(result.report_html.parent, report_line=False)  # the Table I rows and the worlds trained on
        console.print(f"report: {result.report_html}", highlight=False, soft_wrap=True)
    if result.onnx is not None:
        console.print(f"policy: {result.onnx}", highlight=False, soft_wrap=True)
