"""The eval stage under the stage contract: `SPEC`, its summary, and `run_eval` (what the CLI calls).

An evaluation is resumable: its episodes are written one by one into a work folder `eval/.partial-<name>/episodes/`
that survives an interruption (`partial.json` records what they were made with: a different world, policy or env
config starts the work folder afresh; more or fewer episodes do not). When every episode is on disk the build copies
them into the temporary folder `run_stage` gives it, writes the metrics, figures and report there, and `run_stage`
writes the manifest and moves `eval/<name>/` into place atomically; only then is the work folder removed. A bad run
folder, ONNX file or world is refused with one line before any episode runs, and leaves no report.
"""

from __future__ import annotations

import functools
import json
import shutil
import time
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivesim.pipeline.errors import ConfigError, DrivesimError, InputError, Interrupted
from drivesim.pipeline.hashing import sha256_json
from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, run_stage
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.summary import EvalSummary

EVAL_DIR = "eval"
PARTIAL_PREFIX = ".partial-"
WORLD_HINT = "drivesim build-world"
WORLDS_DIR = "worlds"


@dataclass
class _Plan:
    """What an evaluation runs, resolved from the config and the workspace."""

    name: str
    worlds: list[Path]
    world_in_workspace: bool
    meshes: Path | None
    policy_text: str
    policy_path: Path | None


BUILT_IN_POLICIES = ("expert", "random", "straight")
"""Policies named by a word: the env's privileged expert, uniform random steering and no steering at all (baselines:
on a gentle drive a policy that never steers stays in its lane in many episodes)."""


def _policy_label(policy: str) -> str:
    if policy in BUILT_IN_POLICIES:
        return policy
    path = Path(policy)
    return path.stem if path.suffix.lower() == ".onnx" else path.name


def default_name(task: str, policy: str) -> str:
    """`<task>-<policy>` (a run folder's name already starts with its task)."""
    label = _policy_label(policy)
    return label if label.startswith(f"{task}-") else f"{task}-{label}"


def _plan(ws: Workspace, cfg: EvalConfig) -> _Plan:
    if cfg.world is not None:
        worlds = [Path(w).absolute() for w in cfg.world]
        for world in worlds:
            if not world.is_dir():
                raise InputError("no such world folder; build one with `drivesim build-world`", world)
        if len(set(worlds)) < len(worlds):
            raise ConfigError("--world: the same world folder is given twice; give each world once")
        world_in_ws = False
    else:
        worlds = [ws.require("world", WORLD_HINT)]
        world_in_ws = True
    if cfg.meshes is not None:
        meshes: Path | None = Path(cfg.meshes).absolute()
        if not meshes.is_dir():
            raise InputError("no such mesh library folder; build one with `drivesim meshes`", meshes)
    else:
        ws_meshes = ws.artifact_dir("meshes")
        meshes = ws_meshes if (ws_meshes / MANIFEST_NAME).is_file() else None
    policy_path = None
    if cfg.policy not in BUILT_IN_POLICIES:
        policy_path = Path(cfg.policy).absolute()
        if not policy_path.exists():
            what = "ONNX file" if policy_path.suffix.lower() == ".onnx" else "run folder"
            raise InputError(
                f"no such {what}; give a run folder of `drivesim train`, an .onnx file or expert", policy_path
            )
    name = cfg.name or default_name(cfg.task, cfg.policy)
    if "/" in name or name.startswith(".") or not name.strip():
        raise ConfigError(f"--name {name!r}: a plain folder name is needed (no '/', not starting with '.')")
    return _Plan(name, worlds, world_in_ws, meshes, cfg.policy, policy_path)


def resolve(ws: Workspace, cfg: EvalConfig) -> tuple[EvalConfig, _Plan]:
    """The config with absolute paths (so the artifact's identity does not depend on the working folder)."""
    plan = _plan(ws, cfg)
    update: dict[str, Any] = {
        "name": plan.name,
        "world": None if plan.world_in_workspace else [str(w) for w in plan.worlds],
        "meshes": None if plan.meshes is None or cfg.meshes is None else str(plan.meshes),
        "policy": cfg.policy if plan.policy_path is None else str(plan.policy_path),
    }
    return cfg.model_copy(update=update), plan


def _worlds_of(ctx: BuildContext) -> list[Path]:
    """The worlds in the order given: `world` (one world), or `world_00`, `world_01`, ... (several)."""
    if "world" in ctx.external:
        return [ctx.external["world"]]
    several = [ctx.external[k] for k in sorted(ctx.external) if k.startswith("world_")]
    return several or [ctx.inputs["world"]]


def _open_and_check(cfg: EvalConfig, factory: Any, policy_spec: Any, world: Path) -> dict[str, Any]:
    """Build the env and the policy once here, so bad input is one line before any episode runs.

    Returns the env kwargs to use: a run's (or ONNX file's) training env config, then the user's overrides. The
    policy is read before the env is built, so that a world only the policy's own config admits (a short drive
    trained with a lower min_path_length_m) is evaluated with it.
    """
    from drivesim.stages.evaluate.report import Track

    try:
        Track.load(world)
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"not a world folder (path.npz unreadable: {e}); run `{WORLD_HINT}`", world) from e
    policy = None
    if policy_spec.kind in ("run", "onnx"):  # they need no env to load
        policy = _load_policy(policy_spec, None)
        run_task = getattr(policy, "task", None)
        if run_task and run_task != cfg.task:
            raise InputError(
                f"this policy was trained on {run_task}, not {cfg.task}; use --task {run_task}", policy_spec.path
            )
        env_config = dict(getattr(policy, "env_config", {}) or {})
        if env_config:  # the policy's own env settings (its view), then the user's overrides
            config = _env_config(cfg, {**env_config, **cfg.env_overrides()})
            factory = replace(factory, kwargs={**factory.kwargs, "config": config})
    env = _make_env(factory, world)
    try:
        _check_first_action(env, policy or _load_policy(policy_spec, env), policy_spec, cfg.seed)
    finally:
        env.close()
    return dict(factory.kwargs)


def _check_first_action(env: Any, policy: Any, policy_spec: Any, seed: int) -> None:
    """One step of the policy on the env's first observation: a wrong input or output is one line."""
    import numpy as np

    obs, _ = env.reset(seed=seed)
    try:
        action, _ = policy.predict(obs[None], policy.initial_state(1), np.ones(1, dtype=bool))
        action = np.asarray(action, dtype=np.float32)
    except DrivesimError:
        raise
    except Exception as e:  # a wrong input name, shape or dtype from torch or onnxruntime
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(
            f"the policy does not take this env's observations {tuple(obs.shape)} uint8: {first[:200]}",
            policy_spec.path,
        ) from e
    if action.size != 1 or not np.all(np.isfinite(action)):
        raise InputError(f"the policy gave {action.shape} actions; one finite steering value is needed")


def _load_policy(policy_spec: Any, env: Any) -> Any:
    """The policy; anything but a DrivesimError (an unreadable ONNX graph, say) becomes one line."""
    try:
        return policy_spec.load(env)
    except DrivesimError:
        raise
    except Exception as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"cannot load the policy: {first[:200]}", policy_spec.path) from e


def _make_env(factory: Any, world: Path) -> Any:
    import gymnasium

    try:
        return factory()
    except (ValueError, FileNotFoundError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        for named in (f"{world / 'world.json'}: ", f"{world}: "):  # the error names the world once, in front
            first = first.removeprefix(named)
        raise InputError(f"cannot evaluate in this world: {first}", world) from e
    except gymnasium.error.Error as e:
        raise DrivesimError(f"the env {factory.env_id} is not available: {e}") from e


# Keys that do not change what an episode is: an interrupted evaluation of 100 episodes resumes into one of 1000.
# record: missing ones are replayed; baseline_episodes: the baselines' episodes have a work folder of their own.
_REPORT_ONLY_KEYS = ("episodes", "baseline_episodes", "video", "clearance_histogram_max_m", "record")


def _partial_key(ctx: BuildContext, config_json: dict[str, Any]) -> str:
    """What the work folder's episodes depend on: the config (but the report-only keys) and the inputs."""
    config_json = {k: v for k, v in config_json.items() if k not in _REPORT_ONLY_KEYS}
    ws = ctx.workspace
    inputs = {k: ws.external_input(p).hash for k, p in sorted(ctx.external.items())}
    inputs.update({k: ws.artifact_input(k).hash for k in sorted(ctx.inputs)})
    return sha256_json({"config": config_json, "inputs": inputs})


def _prepare_partial(folder: Path, key: str, notes: list[str]) -> Path:
    """The work folder's episodes/ folder, emptied first when it was made for something else."""
    from drivesim.stages.evaluate.rollout import remove_stale_temporaries

    marker = folder / "partial.json"
    if folder.is_dir():
        try:
            same = json.loads(marker.read_text()).get("key") == key
        except (OSError, ValueError):
            same = False
        if not same:
            shutil.rmtree(folder)
            notes.append(f"discarded the episodes of an earlier evaluation with other settings in {folder}")
    (folder / "episodes").mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(folder / "episodes")  # half-written by a worker killed with its evaluation
    marker.write_text(json.dumps({"key": key}) + "\n")
    return folder / "episodes"


@dataclass
class WorldJob:
    """One world of an evaluation: its env factory (checked), where its episodes and recordings go, and its label.

    :param world: the world folder. :param label: its name in tables and folders (`worlds/<label>/`).
    :param factory: builds its env. :param episodes_dir: the work folder's `<seed>.json` files.
    :param recording: what its workers record (None: nothing).
    """

    world: Path
    label: str
    factory: Any
    episodes_dir: Path
    recording: Any


def _env_id(cfg: EvalConfig) -> str:
    from drivesim.sim.envs.registry import task_spec

    return cfg.env_id or task_spec(cfg.task).env_id


def _env_config(cfg: EvalConfig, values: dict[str, Any]) -> Any:
    """The env config handed to the env: for a drivesim task's env an `EnvConfig` (the task's settings with `values`
    on top, validated here and kept typed to the env); for a user's own env (`env_entry_point`) the plain keys."""
    from pydantic import ValidationError

    from drivesim.sim.envs.registry import task_spec

    spec = task_spec(cfg.task)
    if cfg.env_entry_point is not None or _env_id(cfg) != spec.env_id:
        return values
    try:
        return spec.config_with(values)
    except ValidationError as e:  # a run's saved env config that this version refuses
        first = e.errors()[0]
        raise ConfigError(f"env.{'.'.join(map(str, first['loc']))}: {first['msg']}") from e


def _factory(cfg: EvalConfig, world: Path, meshes: Path | None, trusted: bool) -> Any:
    from drivesim.stages.evaluate.rollout import EnvFactory

    return EnvFactory(
        env_id=_env_id(cfg),
        kwargs={"world": str(world), "meshes": None if meshes is None else str(meshes), "mode": "eval"}
        | ({"config": _env_config(cfg, cfg.start_env_config())} if cfg.start_env_config() else {}),
        entry_point=cfg.env_entry_point,
        trusted=trusted,
    )


def _jobs(ctx: BuildContext, policy_spec: Any, seeds: list[int], partial: Path, trusted: bool) -> list[WorldJob]:
    """Every world checked (env, policy) before any episode runs, with its work folders; one world keeps today's
    layout (`episodes/`, `recordings/`), several go to `worlds/<label>/`."""
    from drivesim.stages.evaluate.record import RECORDINGS_DIR, record_plan
    from drivesim.stages.evaluate.rollout import remove_stale_temporaries
    from drivesim.stages.evaluate.worlds import world_labels

    cfg = ctx.config
    assert isinstance(cfg, EvalConfig)
    worlds = _worlds_of(ctx)
    meshes = ctx.external.get("meshes")
    factories = []
    for world in worlds:
        factory = _factory(cfg, world, meshes, trusted)
        factories.append(replace(factory, kwargs=_open_and_check(cfg, factory, policy_spec, world)))
    episodes_dir = _prepare_partial(partial, _partial_key(ctx, cfg.model_dump(mode="json")), ctx.notes)
    if len(worlds) == 1:
        recording = record_plan(cfg.record, seeds, partial / RECORDINGS_DIR, worlds[0])
        return [WorldJob(worlds[0], "", factories[0], episodes_dir, recording)]
    jobs = []
    for world, label, factory in zip(worlds, world_labels(worlds), factories, strict=True):
        folder = partial / WORLDS_DIR / label
        (folder / "episodes").mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(folder / "episodes")
        recording = record_plan(cfg.record, seeds, folder / RECORDINGS_DIR, world)
        jobs.append(WorldJob(world, label, factory, folder / "episodes", recording))
    return jobs


def _run_jobs(
    cfg: EvalConfig, jobs: list[WorldJob], policy_spec: Any, seeds: list[int], partial: Path, notes: list[str]
) -> tuple[int, int, int, float]:
    """Run every world's missing episodes (one progress bar over all); returns (episodes run now, episodes found on
    disk, workers, seconds)."""
    from drivesim.pipeline.progress import progress_bar
    from drivesim.stages.evaluate.rollout import RunningRate, capped_workers, completed_seeds, run_episodes

    def kept() -> int:
        return sum(len(completed_seeds(job.episodes_dir, seeds)) for job in jobs)

    resumed = kept()
    total = len(seeds) * len(jobs)
    if resumed:
        notes.append(f"resumed: {resumed} of {total} episodes were already on disk")
    workers, capped = capped_workers(cfg.workers, total - resumed)
    if capped and cfg.backend == "local":
        notes.append(capped)
    rate = RunningRate()
    ran = 0
    started = time.perf_counter()
    try:
        with progress_bar("eval", total=total) as (progress, task):
            progress.update(task, completed=resumed)

            def on_episode(done: Any) -> None:
                progress.update(task, advance=1, description=rate.add(done))

            for job in jobs:
                if cfg.backend == "ray":
                    from drivesim.stages.evaluate.ray_backend import run_episodes_ray

                    outcome = run_episodes_ray(
                        job.factory,
                        policy_spec,
                        cfg.task,
                        seeds,
                        job.episodes_dir,
                        cfg.address,
                        cfg.workers,
                        on_episode,
                    )
                    ran, workers = ran + outcome.episodes_run, outcome.actors or workers
                    where = f" ({job.label})" if job.label else ""
                    notes.append(f"ray{where}: {outcome.actors} actors on {outcome.nodes} node(s)")
                    if outcome.resubmitted:
                        notes.append(f"ray{where}: {outcome.resubmitted} episodes resubmitted after their worker died")
                else:
                    ran += run_episodes(
                        job.factory,
                        policy_spec,
                        cfg.task,
                        seeds,
                        job.episodes_dir,
                        workers,
                        on_episode,
                        record=job.recording,
                    )
    except KeyboardInterrupt as e:
        raise Interrupted(
            f"interrupted: {kept()} of {total} episodes are kept in {partial}; the same command resumes"
        ) from e
    return ran, resumed, workers, time.perf_counter() - started


def _results(job: WorldJob, seeds: list[int]) -> list[Any]:
    """The world's episodes, evaluated, in seed order."""
    from drivesim.stages.evaluate.metrics import evaluate_episode
    from drivesim.stages.evaluate.rollout import read_episode

    results = []
    for seed in seeds:
        record = read_episode(job.episodes_dir / f"{seed}.json")
        if record is None:
            raise DrivesimError(f"episode {seed} is missing from {job.episodes_dir}; run the evaluation again")
        results.append(evaluate_episode(record))
    return results


def _run_baselines(
    cfg: EvalConfig, job: WorldJob, policy_spec: Any, seeds: list[int], partial: Path, notes: list[str]
) -> list[tuple[Any, list[Any]]]:
    """The expert and the run's warm start (`stages/evaluate/baselines.py`) on the first `baseline_episodes` seeds,
    in the policy's env; each with its evaluated episodes."""
    from drivesim.stages.evaluate.baselines import BASELINES_DIR, baselines_for
    from drivesim.stages.evaluate.rollout import PolicySpec

    count = min(cfg.baseline_episodes, len(seeds))
    ran = []
    for baseline in baselines_for(policy_spec.kind, policy_spec.path) if count else []:
        folder = partial / BASELINES_DIR / baseline.key / "episodes"
        folder.mkdir(parents=True, exist_ok=True)
        base_job = WorldJob(job.world, baseline.key, job.factory, folder, None)
        _run_jobs(cfg, [base_job], PolicySpec.parse(baseline.policy), seeds[:count], partial, notes)
        ran.append((baseline, _results(base_job, seeds[:count])))
    return ran


def _table_extras(
    cfg: EvalConfig,
    job: WorldJob,
    policy_spec: Any,
    label: str,
    results: list[Any],
    seeds: list[int],
    partial: Path,
    notes: list[str],
) -> dict[str, Any]:
    """metrics.json's keys beside Table I: `baselines` (their rows), `trained_on` (the worlds a run's policy trained
    on), `geometry_note` (where the task's geometry differs from the paper's Table I setup) and `env` (the settings
    the episodes ran with: a run's own training env config, then the user's overrides; the manifest holds only the
    latter's defaults)."""
    from drivesim.stages.evaluate.baselines import baseline_rows
    from drivesim.stages.evaluate.report import geometry_note
    from drivesim.stages.evaluate.worlds import training_worlds, world_label

    ran = _run_baselines(cfg, job, policy_spec, seeds, partial, notes)
    trained = training_worlds(policy_spec.kind, policy_spec.path)
    return {
        "baselines": baseline_rows(label, results, ran),
        "trained_on": None
        if trained is None
        else [
            {"world": world_label(w), "path": str(w)}
            for w in sorted(trained, key=lambda w: (w.parent.parent.name == "towns", str(w)))  # its own world first
        ],
        "geometry_note": geometry_note(cfg.task, _as_dict(job.factory.kwargs.get("config"))),
        "env": json.loads(json.dumps(_as_dict(job.factory.kwargs.get("config")), default=str)),
    }


def _build(ctx: BuildContext, trusted: bool = False) -> EvalSummary:
    from drivesim.stages.evaluate.replay import finish_recordings
    from drivesim.stages.evaluate.report import Track, write_outputs
    from drivesim.stages.evaluate.rollout import PolicySpec
    from drivesim.stages.evaluate.video import render_videos

    cfg = ctx.config
    assert isinstance(cfg, EvalConfig)
    meshes = ctx.external.get("meshes")
    policy_spec = PolicySpec.parse(cfg.policy)
    name = cfg.name or default_name(cfg.task, cfg.policy)
    partial = ctx.workspace.root / EVAL_DIR / f"{PARTIAL_PREFIX}{name}"
    seeds = [cfg.seed + i for i in range(cfg.episodes)]
    jobs = _jobs(ctx, policy_spec, seeds, partial, trusted)
    ran, resumed, workers, elapsed = _run_jobs(cfg, jobs, policy_spec, seeds, partial, ctx.notes)
    header = {
        "policy": _policy_label(cfg.policy),
        "policy_path": cfg.policy,
        "world": str(jobs[0].world),
        "meshes": str(meshes) if meshes else "procedural",
        "seed": cfg.seed,
        "workers": workers,
        "backend": cfg.backend,
        "episodes_per_min": round(60 * ran / elapsed, 2) if ran else None,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if len(jobs) > 1:
        from drivesim.stages.evaluate.worlds import write_world_outputs

        data, results, videos = write_world_outputs(ctx.dir, cfg, jobs, [_results(j, seeds) for j in jobs], header)
        videos = [str(v.relative_to(ctx.dir)) for v in videos]
    else:
        job = jobs[0]
        results = _results(job, seeds)
        (ctx.dir / "episodes").mkdir()
        for seed in seeds:
            shutil.copy2(job.episodes_dir / f"{seed}.json", ctx.dir / "episodes" / f"{seed}.json")
        finish_recordings(job.recording, results, job.factory, policy_spec, cfg.task, ctx.dir)  # before the report
        extra = _table_extras(cfg, job, policy_spec, header["policy"], results, seeds, partial, ctx.notes)
        data = write_outputs(
            ctx.dir, results, Track.load(job.world), cfg.task, header, cfg.clearance_histogram_max_m, extra=extra
        )
        videos = [p.name for p in render_videos(results, cfg.video, job.factory, policy_spec, ctx.dir)]
    agg = data["aggregate"]
    return EvalSummary(
        task=cfg.task,
        policy=header["policy"],
        episodes=len(results),
        intervention=agg["intervention"]["value"],
        collision=agg["collision"]["value"],
        off_lane=agg["off_lane"]["value"],
        over_rotation=agg["over_rotation"]["value"],
        success=agg["success"]["value"],
        min_clearance_m=agg["min_clearance_m"]["value"],
        max_deviation_m=agg["max_deviation_m"]["value"],
        max_yaw_rad=agg["max_yaw_rad"]["value"],
        episodes_resumed=resumed,
        episodes_per_min=header["episodes_per_min"],
        workers=workers,
        videos=videos,
    )


SPEC: StageSpec[EvalSummary] = StageSpec(
    name="eval",
    artifact=EVAL_DIR,
    config_model=EvalConfig,
    summary_model=EvalSummary,
    requires=("world",),
    upstream_hints={"world": WORLD_HINT},
    build=_build,
    collection=True,
)


def choose_policy(ws: Workspace, cfg: EvalConfig, policy: str | None, user_chose: bool) -> EvalConfig:
    """The config with the policy to evaluate: `policy` when given; else, when the user named none (no `--policy`,
    no `policy=` in --set or --config), the workspace's newest finished run of the task.

    :raises ConfigError: the user named no policy and the workspace has no finished run of the task (evaluating
        the expert instead would pass its figures off as the user's policy's).
    """
    from drivesim.policy.run_folder import latest_run

    if policy is not None:
        return cfg.model_copy(update={"policy": policy})
    if user_chose or cfg.policy != "expert":
        return cfg
    newest = latest_run(ws, cfg.task)
    if newest is None:
        raise ConfigError(
            f"no trained {cfg.task} policy in {ws.root / 'runs'}: train one first (`drivesim train {cfg.task}`), "
            "or name what to evaluate: --policy RUN|FILE.onnx|expert|random|straight"
        )
    return cfg.model_copy(update={"policy": str(newest)})


def beside_name(name: str, cfg: EvalConfig) -> str:
    """The folder name for an evaluation written beside one of the same name made with other settings:
    `<name>-<first 8 hex digits of its config hash>` (the same settings find it again)."""
    return f"{name}-{sha256_json(cfg.model_dump(mode='json'))[:8]}"


def run_eval(
    ws: Workspace, cfg: EvalConfig, force: bool = False, keep_other: str = "refuse", trust_entry_point: bool = False
) -> StageResult[EvalSummary]:
    """Evaluate `cfg.policy` into `eval/<name>/` (resuming an interrupted evaluation of the same settings).

    An evaluation of the same name made with other settings (say 1000 episodes where this asks for 100) is never
    replaced silently: `keep_other="refuse"` stops with one line naming --force and --name (what `drivesim eval`
    does), "beside" writes this one beside it as `<name>-<config hash>` (what `drivesim run` does).

    :param ws: the workspace (its world/ and meshes/ are the defaults).
    :param cfg: the eval config; `name`, `workers`, `backend` and `address` do not change the artifact's identity.
    :param force: evaluate again even when `eval/<name>/` is fresh; with "refuse", replace one made with other
        settings.
    :param keep_other: "refuse" or "beside".
    :param trust_entry_point: let `cfg.env_entry_point` name a gymnasium.Env class outside drivesim's envs (its
        module is imported); without it such an entry point is refused before anything of it is imported.
    """
    from drivesim.stages.evaluate.entry_point import check_env_entry

    trusted = check_env_entry(_env_id(cfg), cfg.env_entry_point, trust_entry_point)
    if cfg.backend == "ray":
        from drivesim.pipeline.ray_cluster import import_ray

        import_ray()  # a missing Ray is one line before anything runs
    cfg, plan = resolve(ws, cfg)
    other = ws.other_settings(f"{EVAL_DIR}/{plan.name}", cfg.model_dump(mode="json"))
    if keep_other == "beside" and other:  # even with --force: a chain's redo never replaces the user's result
        plan = replace(plan, name=beside_name(plan.name, cfg))
        cfg = cfg.model_copy(update={"name": plan.name})
    external: dict[str, Path] = {}
    if not plan.world_in_workspace and len(plan.worlds) == 1:
        external["world"] = plan.worlds[0]
    elif not plan.world_in_workspace:
        external.update({f"world_{i:02d}": w for i, w in enumerate(plan.worlds)})
    if plan.meshes is not None:
        external["meshes"] = plan.meshes
    if plan.policy_path is not None:
        external["policy"] = plan.policy_path
    spec = replace(SPEC, build=functools.partial(_build, trusted=trusted))
    spec = spec if plan.world_in_workspace else replace(spec, requires=())
    # The name's lock covers its work folder too: a second evaluation into this name stops with one line instead of
    # emptying the work folder of the one running.
    with ws.lock(f"{EVAL_DIR}/{plan.name}"):
        result = run_stage(
            ws,
            spec,
            cfg,
            force=force,
            external=external,
            artifact=f"{EVAL_DIR}/{plan.name}",
            protect=True,
            protect_hint="--force replaces it, --name NAME writes this evaluation beside it",
        )
        if not result.skipped:
            shutil.rmtree(ws.root / EVAL_DIR / f"{PARTIAL_PREFIX}{plan.name}", ignore_errors=True)
    return result


def _as_dict(config: Any) -> dict[str, Any]:
    """An env config as its keys (an `EnvConfig`'s dump, a user env's dict, {} for none)."""
    return config.model_dump() if hasattr(config, "model_dump") else dict(config or {})
