"""`drivesim run`: every stage of the chain registry (`stages.chain.CHAIN`) in order, each skipped when fresh.

A run preset (`configs/run/<name>.yaml`) maps a stage name (and `synth`, for the embedded demo drive) to overrides
of that stage's config, on top of the stage's own preset:

    synth: {drive: {duration_s: 60}}
    preprocess: {depth: {method: mvs}}
    train: {total_steps: 20000}

Most stages run as `run_stage(ws, SPEC, cfg)`; the few whose artifact is one of many or that read files outside the
workspace get a small runner here (ingest: the recording; meshes: imported mesh files; train: a new run folder
unless a finished run of the same config and world exists; eval and export: the run that train made).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivesim.pipeline.config import (
    StageConfig,
    load_config,
    load_yaml_text,
    parse_override,
    preset_path,
    read_config_text,
)
from drivesim.pipeline.errors import ConfigError, DrivesimError, InputError
from drivesim.pipeline.stage import StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import Workspace

RUN_PRESETS_DIR = "run"
DEMO_RECORDING = "recordings/demo.mcap"
SYNTH = "synth"


@dataclass
class StageRun:
    """One stage of a `drivesim run`.

    :param stage: the stage name.
    :param path: its artifact (a recording for synth).
    :param skipped: True when it was fresh and nothing was redone.
    :param wall_s: wall time of the stage (s), including the freshness check.
    :param notes: lines for the user from the stage.
    :param summary: the stage's summary as JSON.
    """

    stage: str
    path: Path
    skipped: bool
    wall_s: float
    notes: tuple[str, ...] = ()
    summary: dict[str, Any] = field(default_factory=dict)


@dataclass
class ChainRun:
    """What `drivesim run` did: each stage in order, and the two files a user wants at the end."""

    stages: list[StageRun]
    report_html: Path | None = None
    onnx: Path | None = None


@dataclass
class _Walk:
    """State passed along the chain: the workspace, the recording, and the run folder train made."""

    ws: Workspace
    recording: Path
    hints: dict[str, str]
    force: bool = False
    run_dir: Path | None = None


def _deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        out[key] = _deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_run_preset(name: str | None, config_file: Path | None = None, overrides: Iterable[str] = ()) -> dict:
    """Per-stage overrides: the preset `configs/run/<name>.yaml`, a user file, then `stage.key=value` overrides."""
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
        data = _deep_merge(data, loaded)
    for text in overrides:
        keys, value = parse_override(text)
        if len(keys) < 2:
            raise ConfigError(f"--set {text!r}: expected STAGE.KEY=VALUE, e.g. --set train.total_steps=4096")
        nested: Any = value
        for key in reversed(keys[1:]):
            nested = {key: nested}
        data = _deep_merge(data, {keys[0]: nested})
    return data


def stage_config(model: type[StageConfig], preset: str | None, overrides: dict[str, Any], stage: str) -> StageConfig:
    """The stage's config: its defaults, its own preset, then the run preset's overrides for it."""
    from pydantic import ValidationError

    cfg = load_config(model, preset=preset)
    if not overrides:
        return cfg
    try:
        return model.model_validate(_deep_merge(cfg.model_dump(), overrides))
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"run preset, {stage}.{where}: {first['msg']}") from e


def _fresh_run(ws: Workspace, spec: StageSpec, cfg: StageConfig) -> Path | None:
    """The newest finished run under runs/ made with this train config and the same world, or None."""
    from drivesim.stages.policy.run_folder import RUNS_DIR, is_complete_run
    from drivesim.stages.towns import is_built, town_world
    from drivesim.stages.train.stage import training_inputs

    towns = [] if cfg.envs.source == "cost_free" else cfg.towns  # type: ignore[attr-defined]
    if not all(is_built(ws, seed) for seed in towns):
        return None
    inputs, external = training_inputs(ws, cfg, None, [town_world(ws, seed) for seed in towns])  # type: ignore[arg-type]
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


def _run_ingest(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    return run_stage(
        walk.ws, spec, cfg, force=walk.force, external={"recording": walk.recording}, make_hints=walk.hints
    )


def _run_train(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.train.stage import run_training

    fresh = None if walk.force else _fresh_run(walk.ws, spec, cfg)
    if fresh is not None:
        summary = spec.summary_model.model_validate(walk.ws.read_manifest(f"runs/{fresh.name}").get("summary", {}))
        result = StageResult(stage=spec.name, path=fresh, skipped=True, summary=summary)
    else:
        result = run_training(walk.ws, cfg)  # type: ignore[arg-type]
    walk.run_dir = result.path
    return result


def _needs_run(walk: _Walk, stage: str) -> Path:
    if walk.run_dir is None:
        raise DrivesimError(f"{stage} needs the policy that train makes, but the chain has no train stage")
    return walk.run_dir


def _run_eval(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.evaluate.stage import run_eval

    cfg = cfg.model_copy(update={"policy": str(_needs_run(walk, "eval"))})
    # An evaluation the user made in this workspace with other settings (`drivesim eval --episodes 1000`) is kept:
    # the chain's own evaluation goes beside it.
    return run_eval(walk.ws, cfg, force=walk.force, keep_other="beside")  # type: ignore[arg-type]


def _run_export(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.export.stage import run_export

    cfg = cfg.model_copy(update={"run": str(_needs_run(walk, "export"))})
    return run_export(walk.ws, cfg, force=walk.force)  # type: ignore[arg-type]


def _run_meshes(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    from drivesim.stages.meshes.stage import run_meshes  # imported mesh files are its external inputs

    return run_meshes(walk.ws, cfg, force=walk.force)  # type: ignore[arg-type]


def _run_default(walk: _Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    return run_stage(walk.ws, spec, cfg, force=walk.force, make_hints=walk.hints)


RUNNERS: dict[str, Callable[[_Walk, StageSpec, StageConfig], StageResult]] = {
    "ingest": _run_ingest,
    "meshes": _run_meshes,
    "train": _run_train,
    "eval": _run_eval,
    "export": _run_export,
}


def synth_demo(ws: Workspace, overrides: dict[str, Any], force: bool = False) -> StageRun:
    """The embedded demo drive at `<workspace>/recordings/demo.mcap`; skipped when it exists with the same config."""
    import json

    from drivesim.stages.synth.config import SynthConfig
    from drivesim.stages.synth.synthesize import resolve_config, sidecar_path, synthesize

    began = time.perf_counter()
    cfg = resolve_config(stage_config(SynthConfig, "synth", overrides, SYNTH))  # type: ignore[arg-type]
    output = ws.root / DEMO_RECORDING
    try:
        recorded = json.loads(sidecar_path(output).read_text()).get("config")
    except (OSError, json.JSONDecodeError):
        recorded = None
    if not force and output.is_file() and recorded == cfg.model_dump(mode="json"):
        return StageRun(SYNTH, output, True, time.perf_counter() - began)
    if output.exists():
        output.unlink()  # synth refuses to overwrite; the sidecar said it was made with another config
    from drivesim.pipeline.progress import progress_bar

    with progress_bar("synth", total=None) as (progress, task):
        result = synthesize(
            cfg, output, preview=True, on_frame=lambda d, t: progress.update(task, completed=d, total=t)
        )
    summary = {
        "frame_count": result.frame_count,
        "path_length_m": result.path_length_m,
        "size_bytes": result.size_bytes,
    }
    return StageRun(SYNTH, output, False, time.perf_counter() - began, summary=summary)


def run_chain(
    ws: Workspace,
    recording: Path | None,
    overrides: dict[str, Any],
    force: bool = False,
    on_stage: Callable[[StageRun], None] | None = None,
    chain: tuple[StageSpec, ...] | None = None,
) -> ChainRun:
    """Walk the chain registry: synth the demo drive when `recording` is None, then every stage in order.

    :param ws: the workspace.
    :param recording: the user's recording, or None for the embedded demo drive.
    :param overrides: stage name -> config overrides (a run preset).
    :param force: redo every stage even when fresh.
    :param on_stage: called after each stage (progress for the CLI).
    :param chain: the stages (default: `stages.chain.CHAIN`).
    """
    if chain is None:
        from drivesim.stages.chain import CHAIN

        chain = CHAIN
    unknown = sorted(set(overrides) - {SYNTH, *(spec.name for spec in chain)})
    if unknown:
        names = ", ".join([SYNTH, *(spec.name for spec in chain)])
        raise ConfigError(f"run preset: unknown stage(s) {', '.join(unknown)}; stages: {names}")
    done: list[StageRun] = []

    def record(stage_run: StageRun) -> None:
        done.append(stage_run)
        if on_stage is not None:
            on_stage(stage_run)

    # Every config first: a typo in the preset is one line before anything runs.
    configs = [stage_config(spec.config_model, spec.preset, overrides.get(spec.name, {}), spec.name) for spec in chain]
    if recording is None:
        record(synth_demo(ws, overrides.get(SYNTH, {}), force=force))
        recording = done[-1].path
    elif not Path(recording).exists():
        raise InputError("no such recording", recording)
    walk = _Walk(ws=ws, recording=Path(recording).absolute(), hints={s.artifact: s.command for s in chain}, force=force)
    report, onnx = None, None
    for spec, cfg in zip(chain, configs, strict=True):
        began = time.perf_counter()
        result = RUNNERS.get(spec.name, _run_default)(walk, spec, cfg)
        summary = result.summary.model_dump(mode="json") if hasattr(result.summary, "model_dump") else {}
        record(StageRun(spec.name, result.path, result.skipped, time.perf_counter() - began, result.notes, summary))
        if spec.name == "eval" and (result.path / "report.html").is_file():
            report = result.path / "report.html"
        if spec.name == "export" and (result.path / "policy.onnx").is_file():
            onnx = result.path / "policy.onnx"
    return ChainRun(stages=done, report_html=report, onnx=onnx)
