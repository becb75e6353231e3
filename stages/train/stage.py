"""The train stage under the stage contract: `SPEC`, its summary, and `run_training` (what the CLI calls).

A training run is resumable, so unlike other stages it does not build in a temporary folder that a crash removes:
it trains in its run folder `runs/<task>-<timestamp>/` (checkpoint + progress.csv after every update, no manifest:
an unfinished run), handed to the build as the contract's `work_dir`, and only at the end does `run_stage` take the
finished files, write manifest.json and move the folder into place. `run_training` passes both the run folder and
`artifact=f"runs/{run_dir.name}"` (the build refuses to run without a run folder).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import replace
from pathlib import Path

from drivesim.pipeline.errors import DrivesimError, Interrupted
from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace
from drivesim.policy.run_folder import CONFIG_JSON
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.summary import TrainSummary


def _worlds_of(ctx: BuildContext) -> list[Path]:
    external = [ctx.external[k] for k in sorted(ctx.external) if k.startswith("world")]
    if external:
        return external
    return [ctx.inputs["world"]] if "world" in ctx.inputs else []


def _meshes_of(ws: Workspace) -> Path | None:
    """The workspace's mesh library, its files checked against its manifest, or None when it has none."""
    folder = ws.artifact_dir("meshes")
    if not (folder / MANIFEST_NAME).is_file():
        return None
    ws.check_input(folder)
    return folder


def _build(ctx: BuildContext, stop_by: float | None = None) -> TrainSummary:
    from drivesim.pipeline.progress import console, progress_bar
    from drivesim.stages.train.envs import EnvSource
    from drivesim.stages.train.run import train_in_folder

    cfg = ctx.config
    assert isinstance(cfg, TrainConfig)
    run_dir = ctx.work_dir
    if run_dir is None:
        # run_stage(ws, SPEC, cfg) alone would move the finished run over the whole runs/ folder.
        raise DrivesimError("the train stage runs through stages.train.stage.run_training (one folder per run)")
    members = [ctx.external[k] for k in sorted(ctx.external) if k.startswith(_MEMBER_PREFIX)]
    if members:
        return _build_ensemble(ctx, cfg, run_dir, members)
    cost_free = cfg.envs.source == "cost_free"
    source = EnvSource(
        task=cfg.task,
        worlds=[] if cost_free else _worlds_of(ctx),
        meshes=None if cost_free else _meshes_of(ctx.workspace),
        config=cfg.envs.config,
        cost_free=cost_free,
        worker_threads=cfg.envs.worker_threads,
        processes=cfg.envs.processes,
    )

    # The run's lines (each warm-start round, resumes, the chosen weights) as they happen, above the bar: the
    # warm start alone takes minutes, with the bar still at 0 steps.
    def report(line: str) -> None:
        console.print(line, highlight=False, soft_wrap=True)

    with progress_bar("train", total=cfg.total_steps) as bar:
        outcome = train_in_folder(run_dir, cfg, source, report=report, progress=bar, stop_by=stop_by)
    # The finished files move into the folder run_stage writes the manifest in and moves into place.
    for entry in run_dir.iterdir():
        os.replace(entry, ctx.dir / entry.name)
    row = outcome.last_row
    return TrainSummary(
        task=cfg.task,
        run=run_dir.name,
        steps=outcome.steps,
        updates=outcome.updates,
        episodes=outcome.episodes,
        wall_s=round(outcome.wall_s, 1),
        steps_per_s=round(outcome.steps_per_s, 1),
        time_rollout_s=round(outcome.time_s.get("rollout", 0.0), 1),
        time_simulator_s=round(outcome.time_s.get("simulator", 0.0), 1),
        time_optimization_s=round(outcome.time_s.get("optimization", 0.0), 1),
        eval_success_rate=row.get("eval_success_rate"),
        eval_return_mean=row.get("eval_return_mean"),
        policy_steps=outcome.policy_steps,
        policy_eval_success_rate=outcome.policy_eval.get("success_rate"),
        warm_start=cfg.warm_start.method != "none",
        worlds=[str(w) for w in source.worlds],
        time_limit_s=None if outcome.time_limit_s is None else round(outcome.time_limit_s, 1),
    )


_MEMBER_PREFIX = "member_"
"""External inputs of an ensemble run: its member runs, `member_00`, `member_01`, ..."""


def _build_ensemble(ctx: BuildContext, cfg: TrainConfig, run_dir: Path, members: list[Path]) -> TrainSummary:
    """The ensemble run of the finished runs `members` (`policy/ensemble.py`) in the stage's folder; its
    summary adds up the members' training."""
    import json

    from drivesim.policy.ensemble import load_members, write_ensemble_files

    loaded = load_members(members)
    write_ensemble_files(ctx.dir, loaded, cfg.model_dump(mode="json"))
    summaries = [json.loads((m / MANIFEST_NAME).read_text()).get("summary", {}) for m in members]

    def total(key: str) -> float:
        return float(sum(s.get(key) or 0 for s in summaries))

    worlds: list[str] = []
    for summary in summaries:
        worlds += [w for w in summary.get("worlds", []) if w not in worlds]
    ctx.notes.append(f"ensemble of {len(members)} runs: {', '.join(str(m) for m in members)}")
    return TrainSummary(
        task=cfg.task,
        run=run_dir.name,
        steps=int(total("steps")),
        updates=int(total("updates")),
        episodes=int(total("episodes")),
        wall_s=round(total("wall_s"), 1),
        steps_per_s=round(total("steps") / max(total("wall_s"), 1e-9), 1),
        time_rollout_s=round(total("time_rollout_s"), 1),
        time_simulator_s=round(total("time_simulator_s"), 1),
        time_optimization_s=round(total("time_optimization_s"), 1),
        policy_steps=int(total("policy_steps")),
        warm_start=any(s.get("warm_start") for s in summaries),
        worlds=worlds,
    )


SPEC: StageSpec[TrainSummary] = StageSpec(
    name="train",
    artifact="runs",
    command="drivesim train overtake",
    config_model=TrainConfig,
    preset="train/overtake",
    summary_model=TrainSummary,
    requires=("world",),
    upstream_hints={"world": "drivesim build-world"},
    build=_build,
    collection=True,
)


def training_inputs(
    ws: Workspace, cfg: TrainConfig, worlds: list[Path] | None, towns: list[Path] | None = None
) -> tuple[StageSpec[TrainSummary], dict[str, Path]]:
    """The stage spec and external inputs of a run: the workspace's world as its one artifact input; with world
    folders or towns, every world as an external input `world_00`, `world_01`, ... in order (the given worlds or
    else the workspace's, then the towns not among them); none with the cost-free env. A world given twice stays
    twice: episodes draw their world uniformly from the list, so it gets twice the share."""
    if cfg.envs.source == "cost_free":
        return replace(SPEC, requires=()), {}
    if not worlds and not towns:
        return SPEC, {}
    base = list(worlds) if worlds else [ws.require("world", SPEC.upstream_hints["world"])]
    every = [Path(world).absolute() for world in base]
    for town in towns or []:  # a resumed run's worlds hold its towns already
        if Path(town).absolute() not in every:
            every.append(Path(town).absolute())
    for world in every:
        if not (world / MANIFEST_NAME).is_file():
            raise DrivesimError("not a world folder (no manifest.json); make one with `drivesim build-world`", world)
    return replace(SPEC, requires=()), {f"world_{i:02d}": w for i, w in enumerate(every)}


def run_training(
    ws: Workspace,
    cfg: TrainConfig,
    worlds: list[Path] | None = None,
    resume: Path | None = None,
    on_start: Callable[[Path], None] | None = None,
    towns: list[Path] | None = None,
    stop_by: float | None = None,
) -> StageResult[TrainSummary]:
    """Train a policy in a new run folder (or continue the unfinished run `resume`) and finish it with a manifest.

    :param ws: the workspace (runs/ goes in it; its world/ is the default world).
    :param cfg: the resolved train config.
    :param worlds: world folders to train on (default: the workspace's world); ignored with the cost-free env.
    :param resume: an unfinished run folder to continue (`stages.train.resume` finds it and reopens a finished one).
    :param on_start: called with the run folder once the inputs are checked, right before training (the CLI
        reopens a finished run to train it further, and prints its header).
    :param towns: the world folders of the towns `cfg.towns` names, built upstream (`chain.towns.training_towns`);
        added after `worlds`. Refused when the config names towns and none are given.
    :param stop_by: a `time.monotonic()` time by which learning stops besides cfg.time_limit_s (`drivesim run`'s
        budget for the whole chain); not part of the run's config, so a re-run of the chain still finds the run.
    """
    from drivesim.stages.train.run import new_run_dir

    if cfg.towns and cfg.envs.source != "cost_free" and not towns:
        raise DrivesimError(
            f"the config trains on towns {', '.join(map(str, cfg.towns))}, but their worlds were not given "
            "(`drivesim train` builds them first)"
        )
    if cfg.ensemble > 1 and resume is None:
        return _train_ensemble(ws, cfg, worlds, on_start, towns)
    spec, external = training_inputs(ws, cfg, worlds, towns)
    if stop_by is not None:
        spec = replace(spec, build=functools.partial(_build, stop_by=stop_by))
    for upstream in spec.requires:  # a missing world is one line before the header names a run folder
        ws.require(upstream, spec.upstream_hints.get(upstream, f"drivesim {upstream}"))
    run_dir = resume if resume is not None else new_run_dir(ws.root, cfg.task)  # created: no other run takes it
    # One process trains a run folder at a time (`--resume` twice is refused by the lock).
    with (
        _says_how_to_resume(run_dir),
        _empty_run_removed_on_failure(run_dir, new=resume is None),
        ws.lock(f"runs/{run_dir.name}"),
    ):
        if on_start is not None:
            on_start(run_dir)
        return run_stage(
            ws, spec, cfg, force=True, external=external, artifact=f"runs/{run_dir.name}", work_dir=run_dir
        )


@contextmanager
def _says_how_to_resume(run_dir: Path) -> Iterator[None]:
    """Ctrl-C or a stop signal anywhere in a run that has its config.json (setup, warm start, the PPO updates, the
    final files, the folder's lock) ends with the line saying how to continue it; before that, as any command."""
    from drivesim.stages.train.run import TrainingInterruptedError

    try:
        yield
    except Interrupted:
        raise
    except KeyboardInterrupt as e:
        if not (run_dir / CONFIG_JSON).is_file():
            raise
        raise TrainingInterruptedError(
            f"interrupted; the run keeps everything up to its last update in {run_dir}; continue with "
            f"`drivesim train --resume {run_dir}`"
        ) from e


@contextmanager
def _empty_run_removed_on_failure(run_dir: Path, new: bool) -> Iterator[None]:
    """Remove the new run folder `run_dir` again when the run stops before writing anything into it."""
    try:
        yield
    except BaseException:
        if new:
            with suppress(OSError):
                run_dir.rmdir()  # only an empty folder: what a run wrote is kept
        raise


def _train_ensemble(
    ws: Workspace,
    cfg: TrainConfig,
    worlds: list[Path] | None,
    on_start: Callable[[Path], None] | None,
    towns: list[Path] | None,
) -> StageResult[TrainSummary]:
    """`cfg.ensemble` runs with seeds cfg.seed, cfg.seed + 1, ..., one after another, then their ensemble run."""
    members = []
    for k in range(cfg.ensemble):
        member_cfg = cfg.model_copy(update={"ensemble": 1, "seed": cfg.seed + k})
        members.append(run_training(ws, member_cfg, worlds, on_start=on_start, towns=towns).path)
    return assemble_ensemble(ws, cfg, members)


def assemble_ensemble(ws: Workspace, cfg: TrainConfig, members: list[Path]) -> StageResult[TrainSummary]:
    """An ensemble run of the finished runs `members` (checked to act alike) in a new run folder of `ws`, under the
    stage contract (the members are its inputs; its manifest is written last)."""
    from drivesim.stages.train.run import new_run_dir

    cfg = cfg.model_copy(update={"ensemble": len(members)})
    run_dir = new_run_dir(ws.root, cfg.task)
    external = {f"{_MEMBER_PREFIX}{k:02d}": Path(m).absolute() for k, m in enumerate(members)}
    spec = replace(SPEC, requires=())
    with _empty_run_removed_on_failure(run_dir, new=True):
        return run_stage(
            ws, spec, cfg, force=True, external=external, artifact=f"runs/{run_dir.name}", work_dir=run_dir
        )
