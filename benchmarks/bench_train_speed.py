"""Env steps per second of `drivesim train`: the preset's whole training loop, with the bare PPO loop beside it.

With --world, two rows on that world. The preset: `drivesim train TASK --world W --total-steps N` run as a user types
it, in a fresh workspace (the preset's env wrappers, VecNormalize, the imitation passes after each update, the
periodic evaluations and every checkpoint), its rate read from the run's own progress.csv and from the command's wall
time; the towns are left out (`--set towns=[]`: building one takes many minutes) and the evaluation is scaled to the
budget (`--eval-every`, `--eval-episodes`). The bare PPO loop: the same preset's model (`build_model`) learning on the
same envs, nothing else.
With --learner, the learner alone on the cost-free env (3x64x160 uint8 images, 2 envs): sb3-contrib's default
CnnLstmPolicy, then one change at a time up to drivesim's policy, and plain PPO with the same CNN as the ceiling.

    .venv/bin/python benchmarks/bench_train_speed.py --world /tmp/ws-demo/world --steps 16384
    .venv/bin/python benchmarks/bench_train_speed.py --learner

Writes benchmarks/results/train_speed.md and train_speed.json (with the load average: the machine may be shared).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from _lib.report import write_markdown
from _lib.train_run import train_stage_row
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from drivesim.bench.machine import machine_line
from drivesim.policy.net import encoder_macs
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.recurrent import ChunkedRecurrentPPO, TimedVecEnv
from drivesim.stages.train.sb3_policy import DrivingLstmPolicy, EncoderExtractor

RESULTS = Path(__file__).parent / "results" / "train_speed.md"
SHAPE = (3, 64, 160)
SMALL_CNN = {"conv_layers": [[16, 5, 2], [32, 3, 2], [64, 3, 1]], "features_dim": 128, "input_pool": 2}
FULL_RES_CNN = {"conv_layers": [[16, 5, 3], [32, 3, 2], [64, 3, 2]], "features_dim": 128, "input_pool": 1}


@dataclass
class Row:
    name: str
    steps_per_s: float
    rollout_s: float
    optimization_s: float
    simulator_s: float
    note: str = ""


def cost_free_vec(n_envs: int = 2, episode_steps: int = 200, shape: tuple[int, int, int] = SHAPE) -> VecEnv:
    venv = DummyVecEnv([lambda: CostFreeDrivingEnv(shape, episode_steps=episode_steps) for _ in range(n_envs)])
    venv.seed(0)
    return venv


class _Timed:
    """Wrap collect_rollouts/train of any SB3 on-policy model to split the time."""

    def __init__(self, model: Any) -> None:
        self.time_s = {"rollout": 0.0, "optimization": 0.0}
        collect, train = model.collect_rollouts, model.train

        def timed_collect(*a: Any, **k: Any) -> bool:
            t = time.perf_counter()
            try:
                return collect(*a, **k)
            finally:
                self.time_s["rollout"] += time.perf_counter() - t

        def timed_train() -> None:
            t = time.perf_counter()
            train()
            self.time_s["optimization"] += time.perf_counter() - t

        model.collect_rollouts, model.train = timed_collect, timed_train


def measure(name: str, make_model: Any, steps: int, venv: VecEnv, threads: int = 2, note: str = "") -> Row:
    torch.set_num_threads(threads)
    timed_env = TimedVecEnv(venv)
    model = make_model(timed_env)
    model.set_logger(Logger(None, []))  # no SB3 log folder in /tmp
    timer = model if isinstance(model, ChunkedRecurrentPPO) else _Timed(model)
    start = time.perf_counter()
    model.learn(steps)
    elapsed = time.perf_counter() - start
    timed_env.close()
    row = Row(
        name,
        model.num_timesteps / elapsed,
        timer.time_s["rollout"],
        timer.time_s["optimization"],
        timed_env.step_time_s,
        note,
    )
    print(
        f"{name:60s} {row.steps_per_s:7.1f} steps/s  rollout {row.rollout_s:6.1f} s  optimization "
        f"{row.optimization_s:6.1f} s  simulator {row.simulator_s:6.1f} s",
        flush=True,
    )
    return row


def learner_variants(steps: int, epochs: int, include_slow: bool) -> list[Row]:
    """Every learner variant of the table, from sb3-contrib's defaults to drivesim's, on the cost-free env."""
    common = {"n_steps": 1024, "batch_size": 512, "n_epochs": epochs, "device": "cpu", "seed": 0, "verbose": 0}
    rows = _sb3_contrib_rows(steps, common, include_slow)
    rows += _drivesim_rows(steps, common)
    plain = {
        "features_extractor_class": EncoderExtractor,
        "features_extractor_kwargs": SMALL_CNN,
        "normalize_images": False,
        "net_arch": [],
    }
    rows.append(
        measure(
            "plain PPO, same small CNN (no recurrence: the ceiling)",
            lambda env: PPO("CnnPolicy", env, policy_kwargs=plain, **common),
            steps,
            cost_free_vec(),
        )
    )
    return rows


def _sb3_contrib_rows(steps: int, common: dict[str, Any], include_slow: bool) -> list[Row]:
    """sb3-contrib's RecurrentPPO: its defaults (with `include_slow`), then with our small CNN and fused pass."""
    rows = []
    if include_slow:
        rows.append(
            measure(
                "sb3-contrib CnnLstmPolicy (defaults)",
                lambda env: RecurrentPPO("CnnLstmPolicy", env, **common),
                steps,
                cost_free_vec(),
            )
        )
        rows.append(
            measure(
                "shared LSTM 128, no critic LSTM (NatureCNN)",
                lambda env: RecurrentPPO(
                    "CnnLstmPolicy",
                    env,
                    policy_kwargs={"lstm_hidden_size": 128, "shared_lstm": True, "enable_critic_lstm": False},
                    **common,
                ),
                steps,
                cost_free_vec(),
            )
        )
    small = {
        "features_extractor_class": EncoderExtractor,
        "features_extractor_kwargs": SMALL_CNN,
        "normalize_images": False,
        "net_arch": [],
        "lstm_hidden_size": 128,
        "shared_lstm": True,
        "enable_critic_lstm": False,
    }
    macs = encoder_macs(SHAPE, SMALL_CNN["conv_layers"], SMALL_CNN["features_dim"], SMALL_CNN["input_pool"])
    rows.append(
        measure(
            " + small CNN (sb3-contrib's per-step loop)",
            lambda env: RecurrentPPO(RecurrentActorCriticPolicy, env, policy_kwargs=small, **common),
            steps,
            cost_free_vec(),
            note=f"{macs / 1e6:.1f} M multiply-adds per frame",
        )
    )
    ours = {"conv_layers": SMALL_CNN["conv_layers"], "features_dim": 128, "input_pool": 2}
    rows.append(
        measure(
            " + fused recurrent pass (sb3-contrib's padded buffer)",
            lambda env: RecurrentPPO(DrivingLstmPolicy, env, policy_kwargs=ours, **common),
            steps,
            cost_free_vec(),
        )
    )
    return rows


def _drivesim_rows(steps: int, common: dict[str, Any]) -> list[Row]:
    """drivesim's chunked recurrent PPO and its variants (threads, CNN, epochs, observation size, envs per step)."""
    ours = {"conv_layers": SMALL_CNN["conv_layers"], "features_dim": 128, "input_pool": 2}
    rows = []
    for seq in (16, 32):
        rows.append(
            measure(
                f" + fixed-length chunks of {seq} (drivesim)",
                lambda env, seq=seq: ChunkedRecurrentPPO(
                    DrivingLstmPolicy, env, policy_kwargs=ours, sequence_length=seq, **common
                ),
                steps,
                cost_free_vec(),
            )
        )
    rows.append(
        measure(
            " drivesim, 1 torch thread",
            lambda env: ChunkedRecurrentPPO(DrivingLstmPolicy, env, policy_kwargs=ours, sequence_length=16, **common),
            steps,
            cost_free_vec(),
            threads=1,
        )
    )
    full = {"conv_layers": FULL_RES_CNN["conv_layers"], "features_dim": 128, "input_pool": 1}
    macs_full = encoder_macs(SHAPE, FULL_RES_CNN["conv_layers"], 128, 1)
    rows.append(
        measure(
            " drivesim, full-resolution CNN (no 2x pooling)",
            lambda env: ChunkedRecurrentPPO(DrivingLstmPolicy, env, policy_kwargs=full, sequence_length=16, **common),
            steps,
            cost_free_vec(),
            note=f"{macs_full / 1e6:.1f} M multiply-adds per frame",
        )
    )
    rows.append(
        measure(
            " drivesim, the paper's 10 epochs",
            lambda env: ChunkedRecurrentPPO(
                DrivingLstmPolicy, env, policy_kwargs=ours, sequence_length=16, **{**common, "n_epochs": 10}
            ),
            steps,
            cost_free_vec(),
        )
    )
    small_obs = {**ours, "input_pool": 1}
    rows.append(
        measure(
            " drivesim, 3x32x80 observations from the env (no pooling)",
            lambda env: ChunkedRecurrentPPO(
                DrivingLstmPolicy, env, policy_kwargs=small_obs, sequence_length=16, **common
            ),
            steps,
            cost_free_vec(shape=(3, 32, 80)),
            note="same CNN on a 4x smaller image",
        )
    )
    rows.append(
        measure(
            " drivesim, 8 envs per step",
            lambda env: ChunkedRecurrentPPO(
                DrivingLstmPolicy, env, policy_kwargs=ours, sequence_length=16, **{**common, "n_steps": 256}
            ),
            steps,
            cost_free_vec(n_envs=8),
            note="rollout 256 steps per env",
        )
    )
    return rows


def bare_loop_row(world: Path, task: str, steps: int) -> Row:
    """The preset's model learning `steps` env steps on the preset's envs: no VecNormalize, imitation, evaluation or
    checkpoint."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.train.envs import EnvSource
    from drivesim.stages.train.run import build_model

    cfg = load_config(TrainConfig, preset=f"train/{task}", overrides=["towns=[]"])
    source = EnvSource(task=task, worlds=[world], processes=cfg.envs.processes)
    venv = source.make_vec(cfg.envs.count, cfg.envs.vec_env, seed=0)
    name = (
        f"bare PPO loop ({cfg.envs.vec_env}, {cfg.envs.count} envs, {cfg.ppo.epochs} epochs, "
        f"buffer {cfg.ppo.buffer_steps})"
    )
    return measure(name, lambda env: build_model(cfg, env), steps, venv, threads=cfg.learner_threads)


def _table(rows: list[Row]) -> list[str]:
    lines = [
        "| variant | env steps/s | rollout [s] | of which simulator [s] | optimization [s] | note |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.name.strip()} | {r.steps_per_s:.0f} | {r.rollout_s:.1f} | {r.simulator_s:.1f} | "
            f"{r.optimization_s:.1f} | {r.note} |"
        )
    return lines


def _preset_lines(train: dict[str, Any], bare: Row, args: argparse.Namespace) -> list[str]:
    """The section of the preset's loop and the bare loop."""
    last = train["last_progress_row"]
    return [
        f"## `drivesim train {args.task}` against the bare PPO loop",
        "",
        f"World: `{args.world}`. Reproduce: `python benchmarks/bench_train_speed.py --world WORLD --task {args.task} "
        f"--steps {args.steps} --bare-steps {args.bare_steps} --eval-every {args.eval_every} "
        f"--eval-episodes {args.eval_episodes}`. The preset's towns left out, its evaluation cut to "
        f"{args.eval_episodes} episodes every {args.eval_every} env steps (the preset: 100 every 40960).",
        "",
        "| what | env steps | env steps/s | rollout [s] | of which simulator [s] | optimization [s] | imitation [s] |",
        "|---|---:|---:|---:|---:|---:|---:|",
        f"| the preset: `drivesim train`, its progress.csv ({train['updates']} updates; the last update's "
        f"evaluation and checkpoint not counted) | {last['steps']:.0f} | {last['steps_per_s_run']:.0f} | "
        f"{last.get('time_rollout_s', 0):.1f} | {last.get('time_simulator_s', 0):.1f} | "
        f"{last.get('time_optimization_s', 0):.1f} | {last.get('time_imitation_s', 0):.1f} |",
        f"| the preset: `drivesim train`, the whole command (start-up, every evaluation and checkpoint, the run's "
        f"files) | {last['steps']:.0f} | {last['steps'] / train['command_wall_s']:.0f} | | | | |",
        f"| {bare.name} | {args.bare_steps} | {bare.steps_per_s:.0f} | {bare.rollout_s:.1f} | {bare.simulator_s:.1f} "
        f"| {bare.optimization_s:.1f} | 0 |",
        "",
    ]


def write_results(learner: list[Row], train: dict[str, Any] | None, bare: Row | None, args: argparse.Namespace,
                  load_before: tuple[float, float, float]) -> None:  # fmt: skip
    """Write the sections measured now (the markdown and its raw figures)."""
    load_after = os.getloadavg()
    lines = [
        "# Training speed: env steps per second of `drivesim train`",
        "",
        f"Machine: {machine_line()}, torch {torch.__version__}. Date: "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Load average before: {load_before[0]:.2f} / "
        f"{load_before[1]:.2f} / {load_before[2]:.2f}, after: {load_after[0]:.2f} / {load_after[1]:.2f} / "
        f"{load_after[2]:.2f} (1/5/15 min): the machine was shared, so these are lower than on a quiet one.",
        "",
    ]
    if train is not None and bare is not None:
        lines += _preset_lines(train, bare, args)
    if learner:
        lines += [
            "## The learner alone (cost-free env)",
            "",
            f"Cost-free env, 2 envs, {args.learner_steps} steps, rollout 1024 steps per env, minibatch 512, "
            f"{args.epochs} epochs. `python benchmarks/bench_train_speed.py --learner` redoes it.",
            "",
            *_table(learner),
            "",
        ]
    raw = {
        "load_average_before_after_1_5_15_min": [load_before, load_after],
        "torch": torch.__version__,
        "world": str(args.world) if args.world else None,
        "task": args.task,
        "train_stage": train,
        "bare_loop": asdict(bare) | {"steps": args.bare_steps} if bare is not None else None,
        "learner_alone": [asdict(r) for r in learner],
    }
    write_markdown(RESULTS, lines, raw)


def main() -> None:
    """Measure what the flags ask for and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=None, help="a world folder: the preset's loop and the bare one")
    parser.add_argument("--task", default="overtake", help="the task whose preset is timed")
    parser.add_argument("--steps", type=int, default=16384, help="env steps of the `drivesim train` run")
    parser.add_argument("--bare-steps", type=int, default=8192, help="env steps of the bare PPO loop")
    parser.add_argument("--eval-every", type=int, default=8192, help="evaluation period of the train run [env steps]")
    parser.add_argument("--eval-episodes", type=int, default=8, help="episodes per evaluation of the train run")
    parser.add_argument("--learner", action="store_true", help="also the learner alone on the cost-free env")
    parser.add_argument("--learner-steps", type=int, default=4096, help="env steps per learner variant")
    parser.add_argument("--epochs", type=int, default=4, help="PPO epochs of the learner variants")
    parser.add_argument("--skip-slow", action="store_true", help="skip sb3-contrib's default policy variants")
    args = parser.parse_args()
    if args.world is None and not args.learner:
        parser.error("nothing to measure: give --world WORLD (the preset's loop) and/or --learner")
    load = os.getloadavg()
    train = bare = None
    if args.world is not None:
        args.world = args.world.absolute()
        train = train_stage_row(args.world, args.task, args.steps, args.eval_every, args.eval_episodes)
        bare = bare_loop_row(args.world, args.task, args.bare_steps)
    learner = learner_variants(args.learner_steps, args.epochs, not args.skip_slow) if args.learner else []
    write_results(learner, train, bare, args, load)


if __name__ == "__main__":
    main()
