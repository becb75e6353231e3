"""`drivesim train TASK`: PPO with a CNN and an LSTM in the simulator (the tasks: sim/envs/registry.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from drivesim.cli.common import (
    AddressOption,
    ConfigOption,
    backend_option,
    choose_backend,
    console,
    set_option,
    workspace,
)
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError
from drivesim.sim.envs.registry import TASK_NAMES, task_help

TaskArgument = Annotated[
    str | None,
    typer.Argument(help=f"The task ({task_help()}); taken from the run with --resume.", show_default=False),
]


WorldOption = Annotated[
    list[Path] | None,
    typer.Option(
        "--world",
        help="A world folder to train in (repeatable: episodes from all, each equally often; one given twice gets "
        "twice the share); default: the workspace's world, or each recording's after a run on several.",
    ),
]
TotalStepsOption = Annotated[
    int | None, typer.Option("--total-steps", help="Env steps to train for (overrides the preset).")
]
EnvsOption = Annotated[int | None, typer.Option("--envs", help="Episodes simulated at once.")]
BackendOption = backend_option(
    "the envs run on this machine",
    "each env in a Ray actor spread over a cluster, so --envs may exceed this machine's cores",
)
ResumeOption = Annotated[
    Path | None,
    typer.Option("--resume", help="Continue an unfinished run folder (runs/<task>-<time>, or just its name)."),
]
EnsembleOption = Annotated[
    int | None,
    typer.Option(
        "--ensemble",
        help="Train this many policies (seeds seed, seed+1, ...; each a run of its own) and make them one ensemble "
        "run whose steering is the mean of theirs.",
        show_default=False,
    ),
]
EnsembleOfOption = Annotated[
    list[Path] | None,
    typer.Option(
        "--ensemble-of",
        help="Train nothing: make an ensemble run of these finished runs (repeatable; one task, view and network), "
        "e.g. the members of an interrupted --ensemble once each is finished with --resume.",
        show_default=False,
    ),
]
WarmStartOption = Annotated[
    str | None,
    typer.Option("--warm-start", help="'expert': behaviour cloning from the privileged expert (DAgger) first."),
]


def train_command(
    task: TaskArgument = None,
    world: WorldOption = None,
    total_steps: TotalStepsOption = None,
    envs: EnvsOption = None,
    backend: BackendOption = None,
    address: AddressOption = None,
    resume: ResumeOption = None,
    warm_start: WarmStartOption = None,
    ensemble: EnsembleOption = None,
    ensemble_of: EnsembleOfOption = None,
    config: ConfigOption = None,
    set_: set_option("ppo.learning_rate=1e-4") = None,
) -> None:
    """Train a driving policy with PPO (CNN + LSTM); the run goes to runs/<task>-<time>/ in the workspace.

    Ctrl-C keeps everything up to the last update; `--resume RUN` continues it. Presets: configs/train/<task>.yaml.
    With --ensemble N, N runs are trained one after another and an ensemble run of them is made last.
    """
    # Imported here so `drivesim --help` stays fast (training pulls in torch and stable-baselines3).
    from drivesim.chain.towns import training_towns
    from drivesim.stages.train.config import TrainConfig
    from drivesim.stages.train.resume import plan_resume, reopen
    from drivesim.stages.train.stage import run_training

    ws = workspace()
    if ensemble_of:
        _print_result(_assemble(ws, ensemble_of, config, list(set_ or [])))
        return
    overrides = list(set_ or [])
    if ensemble is not None:
        overrides.append(f"ensemble={ensemble}")
    if total_steps is not None:
        overrides.append(f"total_steps={total_steps}")
    if envs is not None:
        overrides.append(f"envs.count={envs}")
    if warm_start is not None:
        if warm_start not in ("expert", "none"):
            raise ConfigError(f"--warm-start {warm_start!r}: the only warm start is 'expert' (or 'none')")
        overrides.append(f"warm_start.method={warm_start}")
    plan = None
    worlds = list(world or [])
    if resume is not None:  # the run's own workspace, its saved config with the keys given again on top
        plan = plan_resume(ws, resume, task, config, overrides, worlds)
        ws, cfg, worlds = plan.workspace, plan.cfg, plan.worlds
    else:
        if task is None:
            raise ConfigError(f"give a task to train: {', '.join(TASK_NAMES)} (or --resume RUN)")
        if task not in TASK_NAMES:
            raise ConfigError(f"task {task!r}: choose one of {', '.join(TASK_NAMES)}")
        cfg = load_config(
            TrainConfig, preset=f"train/{task}", config_file=config, overrides=[f"task={task}", *overrides]
        )
        if not worlds and cfg.envs.source != "cost_free":  # the workspace's recordings, when its last run had several
            from drivesim.chain.recordings import set_worlds

            worlds = set_worlds(ws)
    choose_backend(backend, address, cfg.envs)
    if cfg.envs.backend == "ray":
        from drivesim.pipeline.ray_cluster import import_ray

        import_ray()  # a missing Ray is one line before anything runs

    def on_start(run_dir: Path) -> None:
        if plan is not None:
            reopen(plan)  # a finished run trained further is unfinished until its new manifest
        what = "continuing" if plan is not None else "training"
        console.print(
            f"{what} {cfg.task} to {cfg.total_steps} env steps in {run_dir} "
            f"(Ctrl-C keeps it; `drivesim train --resume {run_dir}` continues it)",
            highlight=False,
            soft_wrap=True,
        )

    towns = training_towns(ws, cfg, worlds)  # upstream of the train stage: the towns its config names
    result = run_training(
        ws, cfg, worlds=worlds or None, resume=None if plan is None else plan.run_dir, on_start=on_start, towns=towns
    )
    _print_result(result)


def _assemble(ws: Any, runs: list[Path], config: Path | None, overrides: list[str]) -> Any:
    """The ensemble run of finished runs (their task from the first one's policy.json)."""
    from drivesim.policy.run_folder import load_policy
    from drivesim.stages.train.config import TrainConfig
    from drivesim.stages.train.stage import assemble_ensemble

    task = load_policy(runs[0]).task
    cfg = load_config(TrainConfig, preset=f"train/{task}", config_file=config, overrides=[f"task={task}", *overrides])
    return assemble_ensemble(ws, cfg, runs)


def _print_result(result: Any) -> None:
    """The run's notes and its one-line summary."""
    for note in result.notes:
        console.print(note, highlight=False, soft_wrap=True)
    s = result.summary
    eval_text = (
        ""
        if s.eval_success_rate is None
        else (f"; evaluation on held-back seeds: success {s.eval_success_rate:.0%}, return {s.eval_return_mean:.1f}")
    )
    curves = " (curves.png)" if (Path(result.path) / "curves.png").is_file() else " (an ensemble: no curves of its own)"
    console.print(
        f"[green]train[/] {s.task}: {s.steps} env steps in {s.wall_s / 60:.1f} min ({s.steps_per_s:.0f} env steps/s; "
        f"simulator {s.time_simulator_s:.0f} s, rollout {s.time_rollout_s:.0f} s, optimization "
        f"{s.time_optimization_s:.0f} s){eval_text} -> {result.path}{curves}",
        highlight=False,
        soft_wrap=True,
    )
