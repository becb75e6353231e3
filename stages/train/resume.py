"""`drivesim train --resume RUN`: which run folder, in which workspace, with which config.

An unfinished run (no manifest.json) continues to its `total_steps`. A finished run continues only when the user asks
for more steps (`--total-steps N` above the steps it has): its manifest is kept beside it as
`manifest-<steps>-steps.json` (its figures stay in progress.csv), and a new manifest is written at the end. Only the
keys the user gives again (`--set`, `--config`, `--total-steps`) change the run's saved config.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from drivesim.pipeline.config import load_config_over
from drivesim.pipeline.errors import ConfigError, DrivesimError
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace
from drivesim.policy.run_folder import RUNS_DIR
from drivesim.stages.train.config import TrainConfig


@dataclass(frozen=True)
class ResumePlan:
    """What `--resume` continues.

    :param workspace: the run's workspace (the folder holding its `runs/`).
    :param run_dir: the run folder.
    :param cfg: the saved config with the user's new keys on top.
    :param worlds: the worlds the run trains on (the user's `--world`, else the run's own).
    :param finished_steps: env steps of the finished run being trained further (None: an unfinished run).
    """

    workspace: Workspace
    run_dir: Path
    cfg: TrainConfig
    worlds: list[Path]
    finished_steps: int | None = None


def find_run(ws: Workspace, resume: Path) -> tuple[Workspace, Path]:
    """The run folder `resume` names (a path, or a name under the workspace's runs/) and the workspace it lives in.

    A run folder given by path is resumed in its own workspace (`<workspace>/runs/<run>`), never moved into the
    current one; nothing is created on the way.
    """
    candidates = [Path(resume), ws.root / RUNS_DIR / Path(resume)]
    run_dir = next((c.absolute() for c in candidates if c.is_dir()), None)
    if run_dir is None:
        raise DrivesimError("no such run folder to resume", resume)
    if run_dir.parent.name != RUNS_DIR:
        raise DrivesimError(
            f"not a run folder of a workspace (<workspace>/{RUNS_DIR}/<run>); nothing to resume", run_dir
        )
    return Workspace(run_dir.parent.parent), run_dir


def finished_steps(run_dir: Path) -> int | None:
    """The env steps of a finished run (from its manifest), or None for an unfinished one."""
    import json

    manifest = run_dir / MANIFEST_NAME
    if not manifest.is_file():
        return None
    try:
        return int(json.loads(manifest.read_text())["summary"]["steps"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DrivesimError(f"the run's {MANIFEST_NAME} is damaged; cannot tell how far it trained", run_dir) from e


def plan_resume(
    ws: Workspace,
    resume: Path,
    task: str | None,
    config_file: Path | None,
    overrides: list[str],
    worlds: list[Path],
) -> ResumePlan:
    """Find the run, check it can continue, and merge the user's keys over its saved config."""
    from drivesim.stages.train.run import read_run_config

    run_ws, run_dir = find_run(ws, resume)
    saved, saved_worlds, _ = read_run_config(run_dir)
    if task is not None and task != saved.task:
        raise ConfigError(f"--resume {run_dir.name} is a {saved.task} run, not {task}")
    cfg = load_config_over(TrainConfig, saved.model_dump(mode="json"), config_file, overrides)
    done = finished_steps(run_dir)
    if done is not None and cfg.total_steps <= done:
        raise DrivesimError(
            f"this run is finished at {done} env steps; give --total-steps N above {done} to train it further, "
            "or start a new run",
            run_dir,
        )
    trained_s = trained_wall_s(run_dir)
    if cfg.time_limit_s is not None and trained_s >= cfg.time_limit_s:
        # the limit counts the run's time across resumes: a plain resume would stop again within an update
        raise DrivesimError(
            f"this run has used its time limit ({trained_s:.0f} s trained, time_limit_s={cfg.time_limit_s:g}); "
            "give it more to train further (--set time_limit_s=SECONDS)",
            run_dir,
        )
    return ResumePlan(run_ws, run_dir, cfg, list(worlds) or saved_worlds, done)


def trained_wall_s(run_dir: Path) -> float:
    """A finished run's training wall time, s, from its manifest (0 for an unfinished one: a run killed mid-way
    resumes from a checkpoint saved before its time limit ran out)."""
    try:
        return float(json.loads((run_dir / MANIFEST_NAME).read_text())["summary"]["wall_s"])
    except (OSError, KeyError, ValueError, TypeError):
        return 0.0


def reopen(plan: ResumePlan) -> None:
    """Make a finished run resumable: its manifest goes aside (`manifest-<steps>-steps.json`), so the run is
    unfinished until the new steps are trained and a new manifest is written."""
    if plan.finished_steps is None:
        return
    manifest = plan.run_dir / MANIFEST_NAME
    manifest.replace(plan.run_dir / f"manifest-{plan.finished_steps}-steps.json")
