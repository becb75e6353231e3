"""One training run in its run folder: build the envs and the model, warm start, learn, resume, write the files."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import VecNormalize

from drivesim.pipeline.config import validation_line
from drivesim.pipeline.errors import ConfigError, DrivesimError, Interrupted
from drivesim.pipeline.workspace import MANIFEST_NAME
from drivesim.policy.run_folder import CONFIG_JSON, RUNS_DIR
from drivesim.stages.train.anneal import anneal_learning_rates
from drivesim.stages.train.best import BEST_CHECKPOINT, BestPolicy
from drivesim.stages.train.callbacks import RunState, TrainingCallback
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.envs import MEMORY_OUTPUTS, EnvSource
from drivesim.stages.train.imitation import ExpertLabels, ImitationRegularizer
from drivesim.stages.train.lane_aux import LanePositionAux, LanePositionLabels
from drivesim.stages.train.periodic_eval import PeriodicEvaluator
from drivesim.stages.train.recurrent import ChunkedRecurrentPPO, TimedVecEnv
from drivesim.stages.train.run_files import (
    CHECKPOINTS,
    CURVES_PNG,
    LAST_CHECKPOINT,
    PROGRESS_CSV,
    WARM_START_CHECKPOINT,
    plot_curves,
    read_progress,
    torch_save_atomic,
    write_json,
    write_policy_files,
    write_progress,
)
from drivesim.stages.train.sb3_policy import DrivingLstmPolicy
from drivesim.stages.train.warm_start import warm_start


class TrainingInterruptedError(Interrupted):
    """Ctrl-C or SIGTERM during training: not an error; the run folder keeps everything up to the last update and
    `--resume` continues it."""


@dataclass
class TrainOutcome:
    """What a finished run reports (the stage turns it into its summary)."""

    steps: int
    updates: int
    episodes: int
    wall_s: float
    steps_per_s: float
    time_s: dict[str, float]
    last_row: dict[str, Any]
    warm_start: dict[str, float]
    policy_steps: int = 0
    policy_eval: dict[str, float] = field(default_factory=dict)
    time_limit_s: float | None = None


def new_run_dir(workspace_root: Path, task: str) -> Path:
    """A new, empty run folder `runs/<task>-<YYYYmmdd-HHMMSS>` (`-2`, `-3`, ... when that name is taken), created
    here: os.mkdir fails for a name that exists, so two runs started in the same second never share a folder."""
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    base = workspace_root / RUNS_DIR / f"{task}-{stamp}"
    base.parent.mkdir(parents=True, exist_ok=True)
    run_dir, i = base, 1
    while True:
        try:
            os.mkdir(run_dir)
        except FileExistsError:
            i += 1
            run_dir = base.with_name(f"{base.name}-{i}")
            continue
        return run_dir


def write_run_config(
    run_dir: Path, cfg: TrainConfig, source: EnvSource, env_config: dict[str, Any], observation_shape: tuple
) -> None:
    """config.json: the resolved train config, the env config (its ROI resolved), the observation shape, the worlds
    and the meshes of the run."""
    write_json(
        run_dir / CONFIG_JSON,
        {
            "train": cfg.model_dump(mode="json"),
            "env_config": env_config,
            "observation_shape": [int(v) for v in observation_shape],
            "worlds": [str(w) for w in source.worlds],
            "world_hashes": world_hashes(source.worlds),
            "meshes": None if source.meshes is None else str(source.meshes),
        },
    )


def world_hashes(worlds: list[Path]) -> list[str | None]:
    """Each world's artifact_hash from its manifest (None for a folder without one): which build of each world a
    run trains on, so that a run is continued only on the worlds it started on."""
    hashes: list[str | None] = []
    for world in worlds:
        try:
            value = json.loads((Path(world) / MANIFEST_NAME).read_text()).get("artifact_hash")
        except (OSError, UnicodeDecodeError, ValueError, AttributeError, RecursionError):
            value = None
        hashes.append(value if isinstance(value, str) else None)
    return hashes


def continues_run(run_dir: Path, cfg: TrainConfig, worlds: list[Path]) -> bool:
    """True when `run_dir` is an unfinished run (no manifest) started with this very config on these worlds (the
    same folders holding the same builds): the run that a re-run of the chain continues instead of starting anew."""
    if (run_dir / MANIFEST_NAME).exists():
        return False
    try:
        saved = json.loads((run_dir / CONFIG_JSON).read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return False
    return (
        isinstance(saved, dict)
        and saved.get("train") == cfg.model_dump(mode="json")
        and saved.get("worlds") == [str(w) for w in worlds]
        and saved.get("world_hashes") == world_hashes(worlds)
    )


def read_run_config(run_dir: Path) -> tuple[TrainConfig, list[Path], Path | None]:
    """The train config, worlds and meshes an unfinished run was started with (for --resume)."""
    try:
        data = json.loads((run_dir / CONFIG_JSON).read_text())
        cfg = TrainConfig.model_validate(data["train"])
    except FileNotFoundError as e:
        raise DrivesimError(f"no {CONFIG_JSON}: not a drivesim run folder, nothing to resume", run_dir) from e
    except ValidationError as e:
        raise DrivesimError(f"{CONFIG_JSON} is refused: {validation_line(e)}; cannot resume this run", run_dir) from e
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise DrivesimError(f"{CONFIG_JSON} is damaged ({type(e).__name__}); cannot resume this run", run_dir) from e
    meshes = data.get("meshes")
    return cfg, [Path(w) for w in data.get("worlds", [])], None if meshes is None else Path(meshes)


def build_model(cfg: TrainConfig, venv: Any) -> ChunkedRecurrentPPO:
    """The RecurrentPPO with the driving policy, as configured."""
    try:
        return _make_model(cfg, venv)
    except ValueError as e:
        raise ConfigError(f"policy: {e}") from e


def _make_model(cfg: TrainConfig, venv: Any) -> ChunkedRecurrentPPO:
    ppo, pol = cfg.ppo, cfg.policy
    return ChunkedRecurrentPPO(
        DrivingLstmPolicy,
        venv,
        learning_rate=ppo.learning_rate,
        n_steps=cfg.steps_per_env(),
        batch_size=ppo.minibatch_steps,
        n_epochs=ppo.epochs,
        gamma=ppo.gamma,
        gae_lambda=ppo.gae_lambda,
        clip_range=ppo.clip_range,
        ent_coef=ppo.ent_coef,
        vf_coef=ppo.vf_coef,
        max_grad_norm=ppo.max_grad_norm,
        target_kl=ppo.target_kl,
        policy_kwargs={
            "conv_layers": [list(layer) for layer in pol.conv_layers],
            "features_dim": pol.features_dim,
            "input_pool": pol.input_pool,
            "lstm_hidden_size": pol.lstm_hidden_size,
            "n_lstm_layers": pol.lstm_layers,
            "log_std_init": pol.log_std_init,
            "memory_outputs": MEMORY_OUTPUTS if pol.memory_weight > 0 else 0,
        },
        sequence_length=pol.sequence_length_steps,
        rollout_threads=cfg.rollout_threads,
        seed=cfg.seed,
        device=cfg.device,
        verbose=0,
    )


def return_stats(venv: VecNormalize) -> dict[str, Any]:
    """The reward normalization's running statistics of the discounted return (checkpoints, normalization.json)."""
    rms = venv.ret_rms
    return {
        "return_mean": float(np.asarray(rms.mean)),
        "return_var": float(np.asarray(rms.var)),
        "return_count": float(rms.count),
    }


def read_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint as saved by training (tensors and plain values only: `weights_only`, so a pickle that would run
    code is refused); DrivesimError (one line) for a damaged or refused file."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (any damage or a refused pickle: one line)
        raise DrivesimError(
            f"cannot read the checkpoint ({type(e).__name__}: {(str(e).splitlines() or [''])[0][:120]}); "
            "delete it to resume from an older one",
            path,
        ) from e
    if not isinstance(checkpoint, dict):
        raise DrivesimError("the checkpoint does not hold a dict; delete it to resume from an older one", path)
    return checkpoint


def _restore(model: ChunkedRecurrentPPO, path: Path, venv: VecNormalize) -> dict[str, Any]:
    checkpoint = read_checkpoint(path)
    try:
        model.policy.load_driving_net_state(checkpoint["policy"])
        if "optimizer" in checkpoint:
            model.policy.optimizer.load_state_dict(checkpoint["optimizer"])
    except Exception as e:  # noqa: BLE001  (any damage: one line, the user can restart from an older checkpoint)
        raise DrivesimError(
            f"cannot read the checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:120]}); "
            "delete it to resume from an older one",
            path,
        ) from e
    if "return_var" in checkpoint:
        venv.ret_rms.mean = np.float64(checkpoint["return_mean"])
        venv.ret_rms.var = np.float64(checkpoint["return_var"])
        venv.ret_rms.count = float(checkpoint["return_count"])
    model.num_timesteps = int(checkpoint.get("num_timesteps", 0))
    model.updates_done = int(checkpoint.get("n_updates", 0))
    if "torch_rng" in checkpoint:
        torch.set_rng_state(checkpoint["torch_rng"])
    return checkpoint


def train_in_folder(
    run_dir: Path,
    cfg: TrainConfig,
    source: EnvSource,
    report: Callable[[str], None] = print,
    progress: Any = None,
    stop_by: float | None = None,
) -> TrainOutcome:
    """Train (or continue training) the run in `run_dir` until cfg.total_steps; write every file but the manifest.

    The folder holds after every PPO update a checkpoint and progress.csv, so a crash or Ctrl-C loses at most the
    rollout under way; calling this again on the same folder continues from the last checkpoint.

    :param stop_by: a `time.monotonic()` time by which learning stops, besides cfg.time_limit_s (a chain's budget:
        `chain/budget.py`); the learning rates anneal over whichever comes first.
    """
    torch.set_num_threads(cfg.learner_threads)
    last = run_dir / CHECKPOINTS / LAST_CHECKPOINT
    done_steps = int(read_checkpoint(last).get("num_timesteps", 0)) if last.is_file() else 0
    timed, labelled, placed, venv = _training_envs(cfg, source, done_steps)
    run_dir.mkdir(parents=True, exist_ok=True)
    evaluator = None
    try:
        probe = source.make_env("eval")
        env_config = source.resolved_env_config(probe)
        max_curvature = source.max_curvature_1pm(probe)
        evaluator = _periodic_evaluator(cfg, source)
        probe.close()
        write_run_config(run_dir, cfg, source, env_config, probe.observation_space.shape)
        model = build_model(cfg, venv)
        model.set_logger(configure(str(run_dir / "tb"), ["tensorboard"]))
        _add_update_phases(model, cfg, labelled, placed, env_config)
        state, figures = _starting_state(model, run_dir, cfg, venv, report)
        time_limit_s = effective_time_limit_s(cfg.time_limit_s, state.wall_s, stop_by)
        if time_limit_s is not None and time_limit_s != cfg.time_limit_s:
            report(f"training until {time_limit_s / 60:.1f} min of training time: the chain's budget leaves that")
        best = BestPolicy.load(run_dir / CHECKPOINTS / BEST_CHECKPOINT) if evaluator is not None else None
        callback = TrainingCallback(
            run_dir,
            cfg.envs.count,
            cfg.total_steps,
            state,
            evaluator,
            cfg.eval.every_steps,
            cfg.checkpoint_every_steps,
            progress=progress,
            timing=lambda: {**model.time_s, "simulator": timed.step_time_s},
            time_limit_s=time_limit_s,
            extra_checkpoint=lambda: return_stats(venv),
            best=best,
        )
        anneal_learning_rates(model, cfg, callback.wall_s, time_limit_s)
        start_steps, elapsed = _learn(model, callback, cfg.total_steps, run_dir)
        if evaluator is not None and state.rows and "eval_success_rate" not in state.rows[-1]:
            _evaluate_final_policy(model, callback, evaluator, best, run_dir)  # stopped by the time limit
        kept_best = best if cfg.eval.keep_best and best is not None and best.success_rate is not None else None
        policy_steps = _write_chosen_policy(run_dir, cfg, model, venv, kept_best, max_curvature, report)
        if state.rows:
            plot_curves(state.rows, run_dir / CURVES_PNG, f"{cfg.task}: {run_dir.name}")
        return TrainOutcome(
            steps=int(model.num_timesteps),
            updates=model.updates_done,
            episodes=state.episodes,
            wall_s=callback.wall_s(),
            steps_per_s=(model.num_timesteps - start_steps) / max(elapsed, 1e-9),
            time_s={**model.time_s, "simulator": timed.step_time_s},
            last_row=state.rows[-1] if state.rows else {},
            warm_start=figures,
            policy_steps=policy_steps,
            policy_eval={"success_rate": kept_best.success_rate, "return_mean": kept_best.return_mean}
            if kept_best is not None
            else {},
            time_limit_s=time_limit_s,
        )
    finally:
        venv.close()
        if evaluator is not None:
            evaluator.close()


def _learn(
    model: ChunkedRecurrentPPO, callback: TrainingCallback, total_steps: int, run_dir: Path
) -> tuple[int, float]:
    """PPO until `total_steps` env steps or the callback's time limit; (env steps at the start, seconds learning).
    Ctrl-C ends it with one line saying how to continue the run."""
    remaining = total_steps - model.num_timesteps
    start_steps, start = model.num_timesteps, time.perf_counter()
    if remaining > 0:
        try:
            model.learn(remaining, callback=callback, reset_num_timesteps=False)
        except KeyboardInterrupt:
            kept = int(callback.state.rows[-1]["steps"]) if callback.state.rows else 0
            raise TrainingInterruptedError(
                f"interrupted at {kept} env steps; the run keeps everything up to the last update in {run_dir}; "
                f"continue with `drivesim train --resume {run_dir}`"
            ) from None
    return start_steps, time.perf_counter() - start


def _evaluate_final_policy(
    model: ChunkedRecurrentPPO,
    callback: TrainingCallback,
    evaluator: PeriodicEvaluator,
    best: BestPolicy | None,
    run_dir: Path,
) -> None:
    """The held-back evaluation of the last update's weights, added to the last progress row (and offered as the best
    policy), for a run that stopped between two evaluations."""
    rows = callback.state.rows
    rows[-1].update(evaluator(model.policy))
    write_progress(run_dir / PROGRESS_CSV, rows)
    if best is not None:
        best.offer(rows[-1], int(model.num_timesteps), callback.policy_checkpoint)


def effective_time_limit_s(time_limit_s: float | None, trained_s: float, stop_by: float | None) -> float | None:
    """The run's training time limit [s]: `time_limit_s`, or less where the monotonic time `stop_by` comes first
    (`trained_s` of the run's training time already spent); None for neither."""
    if stop_by is None:
        return time_limit_s
    by_deadline = trained_s + max(stop_by - time.monotonic(), 0.0)
    return by_deadline if time_limit_s is None else min(time_limit_s, by_deadline)


def _periodic_evaluator(cfg: TrainConfig, source: EnvSource) -> PeriodicEvaluator | None:
    """The held-back evaluation the config asks for during training (its own envs, in this process), or None."""
    if cfg.eval.every_steps <= 0 or cfg.eval.episodes <= 0:
        return None
    kind = "dummy" if cfg.envs.vec_env == "subproc" else cfg.envs.vec_env
    return PeriodicEvaluator(
        lambda: source.make_vec(cfg.eval.episodes, kind, cfg.eval.seed, mode="eval"), cfg.eval.seed
    )


def _training_envs(
    cfg: TrainConfig, source: EnvSource, done_steps: int
) -> tuple[TimedVecEnv, ExpertLabels | None, LanePositionLabels | None, VecNormalize]:
    """The training envs, timed, with the labels the update phases read, under reward normalization: (timed,
    expert labels or None, lane-position labels or None, the outermost wrapper). A resumed run draws new episodes
    (the envs' seed moves with the steps done)."""
    try:
        kind = "ray" if cfg.envs.backend == "ray" else cfg.envs.vec_env
        timed = TimedVecEnv(source.make_vec(cfg.envs.count, kind, cfg.seed + done_steps, address=cfg.envs.address))
    except (ValueError, FileNotFoundError) as e:  # the envs' one-line errors (short world, missing meshes, ...)
        raise DrivesimError(f"cannot make the {cfg.task} env: {str(e).splitlines()[0]}") from e
    memory = cfg.policy.memory_weight > 0
    labelled = ExpertLabels(timed, cfg.steps_per_env(), memory) if cfg.imitation.epochs > 0 else None
    placed = LanePositionLabels(labelled or timed, cfg.steps_per_env()) if cfg.lane_aux.epochs > 0 else None
    venv = VecNormalize(
        placed or labelled or timed, norm_obs=False, norm_reward=cfg.ppo.normalize_reward, gamma=cfg.ppo.gamma
    )
    return timed, labelled, placed, venv


def _add_update_phases(
    model: ChunkedRecurrentPPO,
    cfg: TrainConfig,
    labelled: ExpertLabels | None,
    placed: LanePositionLabels | None,
    env_config: dict[str, Any],
) -> None:
    """The phases after each PPO update the config asks for: the imitation regularizer, the encoder's lane target."""
    if labelled is not None:
        imitation = cfg.imitation
        model.update_hooks.append(
            ImitationRegularizer(
                model,
                labelled,
                imitation.epochs,
                imitation.learning_rate,
                cfg.seed,
                imitation.history_steps,
                cfg.policy.memory_weight,
            )
        )
    if placed is not None:
        scales = (float(env_config["max_lateral_m"]), float(env_config["max_rotation_rad"]))
        model.update_hooks.append(
            LanePositionAux(model, placed, cfg.lane_aux.epochs, cfg.lane_aux.learning_rate, scales, cfg.seed)
        )


def _starting_state(
    model: ChunkedRecurrentPPO, run_dir: Path, cfg: TrainConfig, venv: VecNormalize, report: Callable[[str], None]
) -> tuple[RunState, dict[str, float]]:
    """Where training starts: the last checkpoint of a resumed run, else the expert warm start (made, or restored
    from the run's warm-start checkpoint) when asked for, else fresh weights; (the run's state, warm-start figures)."""
    last = run_dir / CHECKPOINTS / LAST_CHECKPOINT
    state = RunState()
    figures: dict[str, float] = {}
    if last.is_file():
        checkpoint = _restore(model, last, venv)
        state = RunState(
            wall_s=float(checkpoint.get("wall_s", 0.0)),
            episodes=int(checkpoint.get("episodes", 0)),
            rows=read_progress(run_dir / PROGRESS_CSV, up_to_steps=model.num_timesteps),
        )
        report(f"resuming {run_dir.name} at {model.num_timesteps} env steps")
    elif cfg.warm_start.method == "expert":
        warm_path = run_dir / CHECKPOINTS / WARM_START_CHECKPOINT
        if warm_path.is_file():
            _restore(model, warm_path, venv)
            report("warm start: restored from the run's warm-start checkpoint")
        else:
            start = time.perf_counter()
            regularizers = [h for h in model.update_hooks if isinstance(h, ImitationRegularizer)]
            keep = regularizers[0].remember if regularizers else None
            figures = warm_start(model, venv, cfg.warm_start, cfg.seed, report, keep, cfg.policy.memory_weight)
            state.wall_s = time.perf_counter() - start
            torch_save_atomic(
                warm_path, {"policy": model.policy.driving_net_state(), "wall_s": state.wall_s, **return_stats(venv)}
            )
        model.num_timesteps = 0
    return state, figures


def _write_chosen_policy(
    run_dir: Path,
    cfg: TrainConfig,
    model: ChunkedRecurrentPPO,
    venv: VecNormalize,
    best: BestPolicy | None,
    max_curvature: float,
    report: Callable[[str], None],
) -> int:
    """The run's policy files with the last update's weights, or `best`'s (the best held-back evaluation) when
    given; returns the env steps of the weights written."""
    chosen = {"policy": model.policy.driving_net_state(), **return_stats(venv)}
    policy_steps = int(model.num_timesteps)
    if best is not None:
        chosen, policy_steps = best.weights(), best.steps
        report(
            f"policy: the weights of step {best.steps} (best evaluation: success {best.success_rate:.0%}, "
            f"return {best.return_mean:.1f}); the last update's are in checkpoints/{LAST_CHECKPOINT}"
        )
    statistics = {k: chosen[k] for k in ("return_mean", "return_var", "return_count") if k in chosen}
    write_policy_files(
        run_dir,
        cfg.task,
        tuple(venv.observation_space.shape),
        model.policy.arch,
        chosen["policy"],
        max_curvature,
        reward_normalization={"enabled": cfg.ppo.normalize_reward, "gamma": cfg.ppo.gamma, **statistics},
    )
    return policy_steps
