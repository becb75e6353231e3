"""The chain walker: stage specs run in order on one recording, each skipped when fresh, each with its own preset
and the caller's overrides. `drivesim run` walks the whole chain (`chain/run.py`), a procedural town the
world-making stages (`chain/towns.py`).

Most stages run as `run_stage(ws, SPEC, cfg)`; a stage that needs more than its config and upstream artifacts gets
a runner (`Runner`): ingest here (the recording is the walk's input), the rest in the caller's table.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivesim.pipeline.config import StageConfig, load_config, preset_path
from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.pipeline.stage import StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import Workspace

DEMO_RECORDING = "recordings/demo.mcap"
SYNTH = "synth"


@dataclass
class StageRun:
    """One stage of a walk.

    :param stage: the stage name.
    :param path: its artifact (a recording for synth).
    :param skipped: True when it was fresh and nothing was redone.
    :param wall_s: wall time of the stage (s), including the freshness check.
    :param notes: lines for the user from the stage.
    :param summary: the stage's summary as JSON.
    :param recording: the recording's name in a run on several recordings ("" otherwise, and for the stages that
        run once for the whole set).
    """

    stage: str
    path: Path
    skipped: bool
    wall_s: float
    notes: tuple[str, ...] = ()
    summary: dict[str, Any] = field(default_factory=dict)
    recording: str = ""


@dataclass
class Walk:
    """State passed along the chain: the workspace, the recording, and the run folder train made."""

    ws: Workspace
    recording: Path
    hints: dict[str, str]
    force: bool = False
    run_dir: Path | None = None


Runner = Callable[[Walk, StageSpec, StageConfig], StageResult]
"""How one stage runs within a walk: `runner(walk, spec, cfg) -> result`."""


def deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """`base` with `update` merged in, nested mappings key by key (neither is changed)."""
    out = dict(base)
    for key, value in update.items():
        out[key] = deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def task_preset(preset: str | None, overrides: dict[str, Any]) -> str | None:
    """The stage's preset for the task the run preset names: `train/lane` for `train: {task: lane}`, where the stage's
    own preset is one of a folder of per-task presets (`train/overtake`) and that task has one; else `preset`."""
    task = overrides.get("task")
    if preset is None or "/" not in preset or not isinstance(task, str):
        return preset
    candidate = f"{preset.rsplit('/', 1)[0]}/{task}"
    return candidate if preset_path(candidate).is_file() else preset


def stage_config(model: type[StageConfig], preset: str | None, overrides: dict[str, Any], stage: str) -> StageConfig:
    """The stage's config: its defaults, its own preset (the named task's, see `task_preset`), then the run preset's
    overrides for it."""
    from pydantic import ValidationError

    cfg = load_config(model, preset=task_preset(preset, overrides))
    if not overrides:
        return cfg
    try:
        # Only the keys the preset set, then the overrides: a key left at its default stays unset, so that a config
        # that puts the keys a user set over another's (eval's env keys over a run's env config) sees only those.
        return model.model_validate(deep_merge(cfg.model_dump(exclude_unset=True), overrides))
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"run preset, {stage}.{where}: {first['msg']}") from e


def run_ingest(walk: Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    """The ingest stage on the walk's recording (an external input)."""
    return run_stage(
        walk.ws, spec, cfg, force=walk.force, external={"recording": walk.recording}, make_hints=walk.hints
    )


def run_default(walk: Walk, spec: StageSpec, cfg: StageConfig) -> StageResult:
    """A stage of config and upstream artifacts only, under the stage contract."""
    return run_stage(walk.ws, spec, cfg, force=walk.force, make_hints=walk.hints)


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


def chain_configs(chain: tuple[StageSpec, ...], overrides: dict[str, Any]) -> list[StageConfig]:
    """Every stage's config in order, checked before anything runs: a stage name outside the chain or a typo in the
    preset is one line.

    :param overrides: stage name -> config overrides (a run preset); `synth` and the chain's budget (`chain`,
        `chain/budget.py`) are accepted beside the chain's names.
    """
    from drivesim.chain.budget import CHAIN_SECTION

    unknown = sorted(set(overrides) - {SYNTH, CHAIN_SECTION, *(spec.name for spec in chain)})
    if unknown:
        names = ", ".join([SYNTH, CHAIN_SECTION, *(spec.name for spec in chain)])
        raise ConfigError(f"run preset: unknown stage(s) {', '.join(unknown)}; stages: {names}")
    return [stage_config(spec.config_model, spec.preset, overrides.get(spec.name, {}), spec.name) for spec in chain]


def walk_chain(
    ws: Workspace,
    recording: Path | None,
    overrides: dict[str, Any],
    chain: tuple[StageSpec, ...],
    runners: Mapping[str, Runner],
    force: bool = False,
    on_stage: Callable[[StageRun], None] | None = None,
) -> list[StageRun]:
    """Synth the demo drive when `recording` is None, then run every stage of `chain` in order; returns what each did.

    :param ws: the workspace.
    :param recording: the recording, or None for the embedded demo drive.
    :param overrides: stage name -> config overrides (a run preset); a name outside the chain is refused.
    :param chain: the stages, in order.
    :param runners: stage name -> its runner, for the stages `run_default` does not fit.
    :param force: redo every stage even when fresh.
    :param on_stage: called after each stage (progress for the CLI).
    """
    configs = chain_configs(chain, overrides)
    done: list[StageRun] = []

    def record(stage_run: StageRun) -> None:
        done.append(stage_run)
        if on_stage is not None:
            on_stage(stage_run)

    if recording is None:
        record(synth_demo(ws, overrides.get(SYNTH, {}), force=force))
        recording = done[-1].path
    elif not Path(recording).exists():
        raise InputError("no such recording", recording)
    walk = Walk(ws=ws, recording=Path(recording).absolute(), hints={s.artifact: s.command for s in chain}, force=force)
    for spec, cfg in zip(chain, configs, strict=True):
        began = time.perf_counter()
        result = runners.get(spec.name, run_default)(walk, spec, cfg)
        summary = result.summary.model_dump(mode="json") if hasattr(result.summary, "model_dump") else {}
        record(StageRun(spec.name, result.path, result.skipped, time.perf_counter() - began, result.notes, summary))
    return done
