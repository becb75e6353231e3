"""The one stage contract: every stage of the chain is a `StageSpec` run by `run_stage`.

A stage is a build function `build(ctx) -> summary` plus its identity (name, artifact folder, config model, preset,
upstream artifacts, the command that makes it). `run_stage` does what every stage needs, in one place:

    require the upstream artifacts (present, unchanged, not stale) -> lock the artifact -> freshness (config +
    input hashes + code version + its files unchanged) -> build in a temporary sibling folder -> write manifest.json
    -> move into place (os.replace)

so a crash or Ctrl-C never leaves a half-written artifact that looks fresh, and a second run with the same config
and inputs prints "fresh, nothing to do". The summary is a typed pydantic model (`StageSummary`), recorded in the
manifest as JSON and handed back to the caller as the model, never as a dict read by key.

Stages whose artifact is one of many (a training run `runs/<task>-<timestamp>/`, an evaluation `eval/<name>/`) pass
`artifact=` to `run_stage`; stages reading recordings outside the workspace pass them as `external=`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict

from drivesim.pipeline.config import StageConfig
from drivesim.pipeline.errors import ArtifactConflictError
from drivesim.pipeline.workspace import InputRef, Workspace

SummaryT = TypeVar("SummaryT", bound="StageSummary")


class StageSummary(BaseModel):
    """Base of every stage summary: the figures a stage records in its manifest and `drivesim status` shows."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


@dataclass
class BuildContext:
    """What a stage's build function gets.

    :param workspace: the workspace.
    :param dir: the temporary folder to write the artifact's files into (moved into place on success).
    :param config: the resolved stage config.
    :param inputs: upstream artifact name -> its folder in the workspace.
    :param external: external input name -> path (a recording outside the workspace).
    :param notes: lines for the user that the CLI prints after the stage (e.g. which camera topic was chosen).
    :param work_dir: where a resumable stage keeps its work while it builds, outside the temporary folder so that a
        crash keeps it (a training run's folder, checkpoints and all); None for a stage that builds in `dir` alone.
    """

    workspace: Workspace
    dir: Path
    config: StageConfig
    inputs: dict[str, Path]
    external: dict[str, Path]
    notes: list[str] = field(default_factory=list)
    work_dir: Path | None = None


@dataclass(frozen=True)
class StageResult(Generic[SummaryT]):
    """What running a stage did.

    :param stage: the stage name.
    :param path: the artifact folder.
    :param skipped: True when the artifact was fresh and nothing was redone.
    :param summary: the stage's typed summary (read back from the manifest when skipped).
    :param notes: lines for the user from the build (empty when skipped).
    """

    stage: str
    path: Path
    skipped: bool
    summary: SummaryT
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True)
class StageSpec(Generic[SummaryT]):
    """A stage's identity and its build function, written once (the chain registry lists these).

    :param name: the stage (and CLI command) name, e.g. "build-world".
    :param artifact: the artifact folder it writes, relative to the workspace, e.g. "world".
    :param config_model: the stage's pydantic config model.
    :param summary_model: the typed summary the build returns.
    :param build: `build(ctx) -> summary`; writes into `ctx.dir` only. Import heavy modules (torch) inside it, or
        name it with `deferred_build`, so that importing the spec (the chain registry, `--help`) stays fast.
    :param command: the command a user types to make the artifact; default `drivesim <name>`.
    :param preset: the name of its YAML preset in `configs/` (may hold only what differs from the defaults);
        default the stage's name.
    :param requires: upstream artifacts the stage reads, in order; default none.
    :param collection: the artifact folder holds many artifacts (`runs/<task>-<timestamp>/`, `eval/<name>/`);
        `drivesim status` shows the newest complete one.
    :param upstream_hints: each required artifact -> the command that makes it, for the one-line "run X first"
        error (the stage says it itself; the chain registry checks these against its upstream stages' commands).
    """

    name: str
    artifact: str
    config_model: type[StageConfig]
    summary_model: type[SummaryT]
    build: Callable[[BuildContext], SummaryT]
    command: str = ""
    preset: str = ""
    requires: tuple[str, ...] = ()
    collection: bool = False
    upstream_hints: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.command:
            object.__setattr__(self, "command", f"drivesim {self.name}")
        if not self.preset:
            object.__setattr__(self, "preset", self.name)


def deferred_build(target: str) -> Callable[[BuildContext], Any]:
    """The build function `target` ("module:function"), imported only when the stage runs: importing the spec
    (the chain registry, `--help`) then leaves the stage's heavy modules (numpy, torch, open3d) unimported."""
    module_name, _, function_name = target.partition(":")

    def build(ctx: BuildContext) -> Any:
        return getattr(importlib.import_module(module_name), function_name)(ctx)

    build.__qualname__ = f"deferred_build({target!r})"
    return build


def run_stage(
    ws: Workspace,
    spec: StageSpec[SummaryT],
    cfg: StageConfig,
    *,
    force: bool = False,
    external: Mapping[str, Path] | None = None,
    artifact: str | None = None,
    make_hints: Mapping[str, str] | None = None,
    protect: bool = False,
    protect_hint: str = "--force replaces it",
    work_dir: Path | None = None,
) -> StageResult[SummaryT]:
    """Run one stage under the contract: require -> fresh? -> build in a temp folder -> manifest -> move into place.

    :param ws: the workspace.
    :param spec: the stage.
    :param cfg: its resolved config (an instance of `spec.config_model`).
    :param force: rebuild even when the artifact is fresh.
    :param external: external inputs (recordings outside the workspace), identified by a fast fingerprint.
    :param artifact: the artifact folder when it is not `spec.artifact` (one of many runs or evaluations).
    :param make_hints: upstream artifact name -> the command that makes it, for the "run X first" error, over
        `spec.upstream_hints` (the chain passes its registry's commands).
    :param protect: refuse (one line) to replace an existing artifact that was made with other settings (a result the
        user asked for, like a 1000-episode evaluation), unless `force`.
    :param protect_hint: what the refusal suggests.
    :param work_dir: the folder a resumable stage keeps its work in while it builds (`BuildContext.work_dir`).
    """
    name = artifact or spec.artifact
    hints = {**spec.upstream_hints, **(make_hints or {})}
    input_dirs = {up: ws.require(up, hints.get(up, f"drivesim {up}")) for up in spec.requires}
    refs: dict[str, InputRef] = {up: ws.artifact_input(up) for up in spec.requires}
    external_paths = {k: Path(v) for k, v in (external or {}).items()}
    for path in external_paths.values():  # a world, run or mesh library given by path: its files as written
        ws.check_input(path)
    refs.update({k: ws.external_input(p) for k, p in external_paths.items()})
    config_json: dict[str, Any] = cfg.model_dump(mode="json")
    with ws.lock(name):  # one writer per artifact: a second command writing it now stops with one line
        if protect and not force:
            differences = ws.other_settings(name, config_json)
            if differences:
                raise ArtifactConflictError(
                    f"holds a result made with other settings ({differences}); not replaced: {protect_hint}",
                    ws.artifact_dir(name),
                )
        manifest = None if force else ws.fresh_manifest(name, spec.name, config_json, refs)
        if manifest is not None:
            summary = spec.summary_model.model_validate(manifest.get("summary", {}))
            return StageResult(stage=spec.name, path=ws.artifact_dir(name), skipped=True, summary=summary)
        with ws.write_artifact(name, spec.name, config_json, refs, command=spec.command) as build:
            ctx = BuildContext(
                workspace=ws,
                dir=build.dir,
                config=cfg,
                inputs=input_dirs,
                external=external_paths,
                notes=[],
                work_dir=work_dir,
            )
            summary = spec.build(ctx)
            build.summary = summary.model_dump(mode="json")
    return StageResult(
        stage=spec.name, path=ws.artifact_dir(name), skipped=False, summary=summary, notes=tuple(ctx.notes)
    )
