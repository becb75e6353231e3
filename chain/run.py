"""`drivesim run`: every stage of the chain registry (`chain.registry.CHAIN`) in order, each skipped when fresh.

A run preset (`configs/run/<name>.yaml`) maps a stage name (and `synth`, for the embedded demo drive) to overrides
of that stage's config, on top of the stage's own preset:

    synth: {drive: {duration_s: 60}}
    preprocess: {depth: {method: mvs}}
    train: {total_steps: 20000}

The walker (`chain/walk.py`) runs most stages as `run_stage(ws, SPEC, cfg)`; the few whose artifact is one of many or
that read files outside the workspace get a runner here (meshes: imported mesh files; train: the towns its config
names, built first, and a new run folder unless a finished run of the same config and worlds exists, or an
unfinished one that it continues from its last checkpoint; eval and export: the run that train made).

A run preset's `chain` section is the budget of the whole command (`chain/budget.py`): training stops at what the
stages before it left of it.

On several recordings (`run_chain(..., more_recordings=[...])`) each recording first goes through the world-making
stages in its own workspace (`chain/recordings.py`), then the rest of the chain runs once: train on every world, eval
in every world.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivesim.chain.budget import ChainBudget, chain_budget
from drivesim.chain.walk import StageRun, Walk, deep_merge, run_ingest, walk_chain
from drivesim.pipeline.config import StageConfig, load_yaml_text, parse_override, preset_path, read_config_text
from drivesim.pipeline.errors import ConfigError, DrivesimError
from drivesim.pipeline.stage import StageResult, StageSpec
from drivesim.pipeline.workspace import Workspace

RUN_PRESETS_DIR = "run"
DEMO_PRESET = "demo"
"""The short run on the embedded demo drive: only when asked for (`--preset demo`, `make demo`)."""
RECORDING_PRESET = "recording"
"""The run without --preset, on a user's recording or on the demo drive alike."""
GPU_PRESETS = (RECORDING_PRESET,)
"""Presets whose training and rendering run on a GPU when torch sees one."""
GPU_OVERRIDES: dict[str, Any] = {"train": {"device": "cuda", "envs": {"config": {"render_device": "cuda"}}}}


def choose_run_preset(preset: str | None) -> str:
    """The run preset `drivesim run` uses: the one asked for, else the recording preset (the demo preset only when
    asked for by name)."""
    return preset if preset is not None else RECORDING_PRESET


def gpu_available() -> bool:
    """Whether torch sees a CUDA device."""
    import torch

    return bool(torch.cuda.is_available())


@dataclass
class ChainRun:
    """What `drivesim run` did: each stage in order, and the two files a user wants at the end."""

    stages: list[StageRun]
    report_html: Path | None = None
    onnx: Path | None = None


def load_run_preset(name: str | None, config_file: Path | None = None, overrides: Iterable[str] = ()) -> dict:
    """Per-stage overrides: the preset `configs/run/<name>.yaml` (with `GPU_OVERRIDES` for a preset of
    `GPU_PRESETS` where torch sees a GPU), a user file, then `stage.key=value` overrides."""
    import yaml

    data: dict[str, Any] = {}
    paths = []
    if name is not None:
        path = preset_path(f"{RUN_PRESETS_DIR}/{name}")
        if not path.is_file():
            known = sorted(p.stem for p in path.parent.glob("*.yaml"))
            raise ConfigError(f"no run preset {name!r}; presets: {', '.join(known)}")
        paths.append(path)
    if config_file is not None:
        paths.append(Path(config_file))
    for path in paths:
        text = read_config_text(Path(path))  # a folder, a binary file: one line
        try:
            loaded = load_yaml_text(text) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"not a valid run preset: {str(e).splitlines()[0]}", path) from e
        if not isinstance(loaded, dict) or not all(isinstance(v, dict) for v in loaded.values()):
            raise ConfigError("a run preset maps stage names to their config overrides (a mapping each)", path)
        data = deep_merge(data, loaded)
        if path == paths[0] and name in GPU_PRESETS and gpu_available():
            data = deep_merge(data, GPU_OVERRIDES)  # part of the preset: a user's file or --set still overrides it
    for text in overrides:
        keys, value = parse_override(text)
        if len(keys) < 2:
            raise ConfigError(f"--set {text!r}: expected STAGE.KEY=VALUE, e.g. --set train.total_steps=4096")
        nested: Any = value
        for key in reversed(keys[1:]):
            nested = {key: nested}
        data = deep_merge(data, {keys[0]: nested})
    return data


def _fresh_run(ws: Workspace, spec: StageSpec, cfg: StageConfig, recordings: Sequence[Path] = ()) -> Path | None:
    """The newest finished run under runs/ made with this train config and the same worlds (the workspace's, the
    further `recordings`' worlds, the towns), or None."""
    from drivesim.chain.towns import is_built, town_world
    from drivesim.policy.run_folder import RUNS_DIR, is_complete_run
    from drivesim.stages.train.stage import training_inputs

    towns = [] if cfg.envs.source == "cost_free" else cfg.towns  # type: ignore[attr-defined]
    if not all(is_built(ws, seed) for seed in towns):
        return None
    extra = [*recordings, *(town_world(ws, seed) for seed in towns)]
    inputs, external = training_inputs(ws, cfg, None, extra)  # type: ignore[arg-type]
    refs = {up: ws.artifact_input(up) for up in inputs.requires}
    refs.update({key: ws.external_input(path) for key, path in external.items()})
    config_json = cfg.model_dump(mode="json")
    fresh = []
    for run_dir in sorted((ws.root / RUNS_DIR).glob("*")):
        if run_dir.is_dir() and is_complete_run(run_dir):
            manifest = ws.fresh_manifest(f"{RUNS_DIR}/{run_dir.name}", spec.name, config_json, refs)
            if manifest is not None:
                fresh.append((manifest.get("created_utc", ""), run_dir))
    return max(fresh)[1] if fresh else None


def _unfinished_run(ws: Workspace, cfg: StageConfig, towns: list[Path]) -> Path | None:
    """The newest unfinished run under runs/ started with this very train config on the same worlds (their same
    builds), or None: what a re-run of the chain continues after a crash or Ctrl-C in training, from its last
    checkpoint. When another command is training it now, the run's lock stops this one with one line instead of a
    second training of the same config beside it."""
    from drivesim.policy.run_folder import CONFIG_JSON, RUNS_DIR
    from drivesim.stages.train.run import continues_run
    from drivesim.stages.train.stage import training_inputs

    if cfg.ensemble > 1:  # type: ignore[attr-defined]  (an ensemble's members are runs of their own)
        return None
    spec, external = training_inputs(ws, cfg, None, towns)  # type: ignore[arg-type]
    worlds = [ws.artifact_dir(up) for up in spec.requires] + [p for k, p in sorted(external.items())]
    found = [
        (run_dir.stat().st_mtime_ns, run_dir)
        for run_dir in (ws.root / RUNS_DIR).glob(f"{cfg.task}-*")  # type: ignore[attr-defined]
        if (run_dir / CONFIG_JSON).is_file() and continues_run(run_dir, cfg, worlds)  # type: ignore[arg-type]
    ]
    return max(found)[1] if found else None


def _run_train(
    walk: Walk,
    spec: StageSpec,
    cfg: StageConfig,
    recordings: Sequence[Path] = (),
    budget: ChainBudget | None = None,
    began: float = 0.0,
) -> StageResult:
    """Train on the workspace's world, then the further recordings' worlds (`recordings`), then the towns; with a
    `budget`, until what the chain that began at the monotonic time `began` has left for training."""
    from drivesim.chain.towns import training_towns
    from drivesim.stages.train.stage import run_training

    fresh = None if walk.force else _fresh_run(walk.ws, spec, cfg, recordings)
    if fresh is not None:
        summary = spec.summary_model.model_validate(walk.ws.read_manifest(f"runs/{fresh.name}").get("summary", {}))
        result = StageResult(stage=spec.name, path=fresh, skipped=True, summary=summary)
    else:
        # The further recordings' worlds go to the train stage the way the towns' do: extra worlds after its own.
        extra = [*recordings, *training_towns(walk.ws, cfg)]  # type: ignore[arg-type]
        unfinished = None if walk.force else _unfinished_run(walk.ws, cfg, extra)
        stop_by = None if budget is None else budget.training_stop_by(began, time.monotonic())
        result = run_training(walk.ws, cfg, towns=extra, resume=unfinished, stop_by=stop_by)  # type: ignore[arg-type]
    walk.run_dir = result.path
    return result


def _needs_run(walk: Walk, stage: str) -> Path:
    if walk.run_dir is None:
        raise DrivesimError(f"{stage} needs the policy that train makes, but the chain has no train stage")
    return walk.run_dir


def _run_eval(
    walk: Walk, spec: StageSpec, cfg: StageConfig, trust_entry_point: bool = False, worlds: Sequence[Path] = ()
) -> StageResult:
    """Evaluate the run train made: in the workspace's world, or in every world of `worlds` (a row per world and
    the pooled figures)."""
    from drivesim.stages.evaluate.stage import run_eval

    update: dict[str, Any] = {"policy": str(_needs_run(walk, "eval"))}
    if worlds:
        update["world"] = [str(w) for w in worlds]
    cfg = cfg.model_copy(update=update)
    # An evaluation the user made in this workspace with other settings (`drivesim eval --episodes 1000`) is kept:
    # the chain's own evaluation goes beside it.
    return run_eval(
        walk.ws,
        cfg,  # type: ignore[arg-type]
        force=walk.force,
        keep_other="beside",
        trust_entry_point=trust_entry_point,
    )


def _check_eval_entry_point(overrides: dict[str, Any], trust_entry_point: bool) -> None:
    """An `eval.env_entry_point` the evaluation may not register is refused before the first stage, not after
    training (`stages/evaluate/entry_point.py`)."""
    from drivesim.sim.envs.registry import task_spec
    from drivesim.stages.evaluate.config import EvalConfig
    from drivesim.stages.evaluate.entry_point import check_env_entry

    section = overrides.get("eval") or {}
    entry_point = section.get("env_entry_point")
    if entry_point is not None:
        task = str(section.get("task", EvalConfig.model_fields["task"].default))
        env_id = str(section.get("env_id") or task_spec(task).env_id)
        check_env_entry(env_id, str(entry_point), trust_entry_point)


def _run_export(walk: Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.export.stage import run_export

    cfg = cfg.model_copy(update={"run": str(_needs_run(walk, "export"))})
    return run_export(walk.ws, cfg, force=walk.force)  # type: ignore[arg-type]


def _run_meshes(walk: Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.meshes.stage import run_meshes  # imported mesh files are its external inputs

    return run_meshes(walk.ws, cfg, force=walk.force)  # type: ignore[arg-type]


RUNNERS: dict[str, Callable[[Walk, StageSpec, StageConfig], StageResult]] = {
    "ingest": run_ingest,
    "meshes": _run_meshes,
    "train": _run_train,
    "eval": _run_eval,
    "export": _run_export,
}


def run_chain(
    ws: Workspace,
    recording: Path | None,
    overrides: dict[str, Any],
    force: bool = False,
    on_stage: Callable[[StageRun], None] | None = None,
    trust_entry_point: bool = False,
    more_recordings: Sequence[Path] = (),
) -> ChainRun:
    """Walk the chain registry: synth the demo drive when `recording` is None, then every stage in order.

    :param ws: the workspace.
    :param recording: the user's recording, or None for the embedded demo drive.
    :param overrides: stage name -> config overrides (a run preset).
    :param force: redo every stage even when fresh.
    :param on_stage: called after each stage (progress for the CLI).
    :param trust_entry_point: let `eval.env_entry_point` name a gymnasium.Env class outside drivesim's envs.
    :param more_recordings: further recordings to train on beside `recording`, each made into a world of its own
        (`chain/recordings.py`); the evaluation then reports each recording's world and the pooled figures.
    """
    from drivesim.chain.recordings import forget_set
    from drivesim.chain.registry import CHAIN

    began = time.monotonic()
    budget = chain_budget(overrides)
    _check_eval_entry_point(overrides, trust_entry_point)
    if more_recordings:
        if recording is None:
            raise ConfigError("several recordings: give the first one too (the demo drive is for a run on none)")
        return _run_several(
            ws, [recording, *more_recordings], overrides, force, on_stage, trust_entry_point, budget, began
        )
    runners = {
        **RUNNERS,
        "train": functools.partial(_run_train, budget=budget, began=began),
        "eval": functools.partial(_run_eval, trust_entry_point=trust_entry_point),
    }
    done = walk_chain(ws, recording, overrides, CHAIN, runners, force=force, on_stage=on_stage)
    forget_set(ws)  # a later `drivesim eval` evaluates in this recording's world alone
    return _chain_run(done)


def _run_several(
    ws: Workspace,
    recordings: Sequence[Path],
    overrides: dict[str, Any],
    force: bool,
    on_stage: Callable[[StageRun], None] | None,
    trust_entry_point: bool,
    budget: ChainBudget,
    began: float,
) -> ChainRun:
    """The chain on several recordings: each one's world-making stages (the first in the workspace, the others in
    `drives/<name>/`), then meshes, train on every world, eval in every world, export, once."""
    from drivesim.chain.recordings import WORLD_STAGES, build_drive_worlds, plan_drives, write_set
    from drivesim.chain.registry import CHAIN
    from drivesim.chain.walk import SYNTH, chain_configs

    chain_configs(CHAIN, overrides)  # a typo in any stage's settings is one line before anything runs
    drives = plan_drives(ws, recordings)
    done = build_drive_worlds(drives, overrides, force=force, on_stage=on_stage)
    write_set(ws, drives)
    further = [drive.world for drive in drives[1:]]
    runners = {
        **RUNNERS,
        "train": functools.partial(_run_train, recordings=further, budget=budget, began=began),
        "eval": functools.partial(
            _run_eval, trust_entry_point=trust_entry_point, worlds=[drive.world for drive in drives]
        ),
    }
    rest = tuple(spec for spec in CHAIN if spec.name not in WORLD_STAGES)
    rest_overrides = {k: v for k, v in overrides.items() if k not in (SYNTH, *WORLD_STAGES)}
    done += walk_chain(ws, drives[0].recording, rest_overrides, rest, runners, force=force, on_stage=on_stage)
    return _chain_run(done)


def _chain_run(done: list[StageRun]) -> ChainRun:
    return ChainRun(
        stages=done, report_html=_file_of(done, "eval", "report.html"), onnx=_file_of(done, "export", "policy.onnx")
    )


def _file_of(done: list[StageRun], stage: str, name: str) -> Path | None:
    """The file `name` in the artifact of the walk's stage `stage`, when both exist."""
    path = next((run.path / name for run in done if run.stage == stage), None)
    return path if path is not None and path.is_file() else None
