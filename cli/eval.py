"""`drivesim eval`: closed-loop episodes with fixed seeds, the paper's metrics, figures and an HTML report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from drivesim.cli.common import (
    AddressOption,
    ConfigOption,
    ForceOption,
    backend_option,
    choose_backend,
    console,
    set_option,
    workspace,
)
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError
from drivesim.sim.envs.registry import TASK_NAMES

TaskOption = Annotated[
    str | None,
    typer.Option("--task", help=f"One of {', '.join(TASK_NAMES)} (default: overtake).", show_default=False),
]
PolicyOption = Annotated[
    str | None,
    typer.Option(
        "--policy",
        help="A `drivesim train` run folder or checkpoint (RUN/checkpoints/NAME.pt), an .onnx file, 'expert', "
        "'random' or 'straight' (never steers). Default: the workspace's newest finished run of the task.",
        show_default=False,
    ),
]
EpisodesOption = Annotated[
    int | None,
    typer.Option(
        "--episodes",
        help="Episodes to run in each world (default 1000); every world gets the same seeds.",
        show_default=False,
    ),
]
WorkersOption = Annotated[
    int | None,
    typer.Option(
        "--workers",
        help="Worker processes, or Ray actors with --backend ray (default: one per core, of the cluster).",
        show_default=False,
    ),
]
BackendOption = backend_option(
    "worker processes on this machine",
    "Ray actors over a cluster's workers, one world loaded per actor",
    " Same seeds, same numbers.",
)
SeedOption = Annotated[
    int | None, typer.Option("--seed", help="Seed of episode 0; episode i uses seed + i.", show_default=False)
]
WorldOption = Annotated[
    list[Path] | None,
    typer.Option(
        "--world",
        help="World folder (default: the workspace's world/, or each recording's after `drivesim run` on several). "
        "Repeatable: the same seeds in each, a row per world (train or unseen) and the pooled figures.",
        show_default=False,
    ),
]
MeshesOption = Annotated[
    Path | None,
    typer.Option("--meshes", help="Vehicle mesh library (default: the workspace's meshes/).", show_default=False),
]
VideoOption = Annotated[int | None, typer.Option("--video", help="Render MP4s of N episodes (the worst and the best).")]
RecordOption = Annotated[
    str | None,
    typer.Option(
        "--record",
        help="Episodes to write as Foxglove MCAP files in recordings/: failures (the default; those with an "
        "intervention, the first 50), all, N (the first N episodes) or none. Layout: docs/foxglove_layout.json.",
        show_default=False,
    ),
]
NameOption = Annotated[
    str | None,
    typer.Option("--name", help="Folder name under eval/ (default: <task>-<policy>).", show_default=False),
]

ScenarioOption = Annotated[
    list[str] | None,
    typer.Option(
        "--scenario",
        help="The paper's Table II scenarios (repeatable): static or dynamic front car, pass-left or pass-right "
        "(default: the task's own mix, split by scenario in the report).",
        show_default=False,
    ),
]
TrustEntryPointOption = Annotated[
    bool,
    typer.Option(
        "--trust-entry-point",
        help="Let env_entry_point (--set or --config) name your own gymnasium.Env class; its module is imported and "
        "runs, so only for code you trust.",
    ),
]


def eval_command(
    task: TaskOption = None,
    policy: PolicyOption = None,
    episodes: EpisodesOption = None,
    workers: WorkersOption = None,
    backend: BackendOption = None,
    address: AddressOption = None,
    seed: SeedOption = None,
    world: WorldOption = None,
    meshes: MeshesOption = None,
    video: VideoOption = None,
    record: RecordOption = None,
    scenario: ScenarioOption = None,
    name: NameOption = None,
    config: ConfigOption = None,
    set_: set_option("env.max_lateral_m=2.0") = None,
    force: ForceOption = False,
    trust_entry_point: TrustEntryPointOption = False,
) -> None:
    """Evaluate a policy in closed loop: intervention, clearance, deviation and yaw with 95 % intervals.

    Writes eval/<name>/ in the workspace: report.html (self-contained), metrics.json, episodes.csv,
    episodes/<seed>.json and the figures. Ctrl-C keeps the finished episodes; the same command resumes.
    """
    # Imported here so `drivesim --help` stays fast.
    from drivesim.stages.evaluate.config import EvalConfig
    from drivesim.stages.evaluate.stage import choose_policy, run_eval

    ws = workspace()
    if episodes is not None and episodes < 1:
        raise ConfigError(f"--episodes {episodes}: episodes must be >= 1")
    overrides = list(set_ or [])
    for key, value in (("task", task), ("episodes", episodes), ("seed", seed), ("video", video), ("record", record)):
        if value is not None:
            overrides.append(f"{key}={value}")
    if scenario:
        overrides.append(f"scenario=[{','.join(scenario)}]")
    if world:
        overrides.append(f"world={json.dumps([str(w.absolute()) for w in world])}")  # JSON is YAML: any path reads
    if meshes is not None:
        overrides.append(f"meshes={meshes.absolute()}")
    cfg = load_config(EvalConfig, preset="eval", config_file=config, overrides=overrides)
    if cfg.world is None:  # the workspace's recordings, when its last run was on several
        from drivesim.chain.recordings import set_worlds

        worlds = set_worlds(ws)
        if worlds:
            cfg = cfg.model_copy(update={"world": [str(w) for w in worlds]})
    if workers is not None:
        cfg.workers = workers
    choose_backend(backend, address, cfg)
    if name is not None:
        cfg.name = name
    user_chose = config is not None or any(o.startswith("policy=") for o in overrides)
    cfg = choose_policy(ws, cfg, policy, user_chose)
    where = f" in each of {len(cfg.world)} worlds" if cfg.world is not None and len(cfg.world) > 1 else ""
    console.print(
        f"evaluating {cfg.policy} on {cfg.task}: {cfg.episodes} episodes{where} from seed {cfg.seed}", highlight=False
    )
    result = run_eval(ws, cfg, force=force, trust_entry_point=trust_entry_point)
    _print_result(result, cfg)


def _print_result(result: Any, cfg: Any) -> None:
    """The evaluation's one-paragraph summary, its report and its recordings."""
    from drivesim.cli.result import print_result, print_worlds

    s = result.summary
    report = result.path / "report.html"
    if result.skipped:
        console.print(f"{result.path} is fresh, nothing to do; --force redoes it", soft_wrap=True)
        if not print_result(result.path):
            console.print(f"report: {report}", soft_wrap=True)
        return
    for note in result.notes:
        console.print(note, highlight=False, soft_wrap=True)

    def show(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.3f}"

    unit = "Ray actors" if cfg.backend == "ray" else "workers"
    speed = f", {s.episodes_per_min:.1f} episodes/min with {s.workers} {unit}" if s.episodes_per_min else ""
    console.print(
        f"[green]eval[/] {s.episodes} episodes of {s.policy}: success {s.success:.3f}, "
        f"intervention {s.intervention:.3f} "
        f"(collision {s.collision:.3f}, off lane {s.off_lane:.3f}, over-rotation {s.over_rotation:.3f}), "
        f"min clearance {show(s.min_clearance_m)} m (all episodes), max deviation {show(s.max_deviation_m)} m, "
        f"max yaw {show(s.max_yaw_rad)} rad{speed}",
        highlight=False,
        soft_wrap=True,
    )
    print_worlds(result.path / "metrics.json")
    _print_starts(result.path / "metrics.json")
    if not print_result(result.path):  # the Table I rows, the worlds trained on, the report
        console.print(f"report: {report}", highlight=False, soft_wrap=True)
    recordings = sorted([*result.path.glob("recordings/*.mcap"), *result.path.glob("worlds/*/recordings/*.mcap")])
    if recordings:
        console.print(
            f"recordings: {len(recordings)} episodes in {recordings[0].parent} (Foxglove, layout "
            "docs/foxglove_layout.json)",
            highlight=False,
            soft_wrap=True,
        )


def _print_starts(metrics_path: Path) -> None:
    """Overtake: how many starts labelled unwinnable were among the episodes, and success on the others."""
    try:
        rows = json.loads(metrics_path.read_text()).get("starts") or []
    except (OSError, ValueError):
        return
    by_name = {row["starts"]: row for row in rows}
    unwinnable, winnable = by_name.get("unwinnable starts"), by_name.get("winnable starts")
    if not unwinnable or not winnable or not unwinnable["episodes"]:
        return
    success = winnable["success"]["value"]
    console.print(
        f"starts labelled unwinnable (the hardest swerve cannot escape): {unwinnable['episodes']} of "
        f"{unwinnable['episodes'] + winnable['episodes']} "
        f"(in every figure above); success on the others {'n/a' if success is None else f'{success:.3f}'}",
        highlight=False,
        soft_wrap=True,
    )
