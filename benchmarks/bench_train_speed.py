"""Env steps per second of `learn()`: where the learner's time goes, and the real overtake env end to end.

Part 1, the learner alone, on the cost-free env (3x64x160 uint8 images, 2 envs; issue 9 "Speed is a feature"):
sb3-contrib's default CnnLstmPolicy, then one change at a time up to drivesim's policy (small CNN, one shared LSTM,
fused recurrent pass, fixed-length chunks, thread settings), and plain PPO with the same CNN as the ceiling.
Part 2 (with --world), the real overtake env through `drivesim.stages.train.run.build_model` with the preset's
settings: end to end, split into simulator / rest of the rollout / optimization, 4 epochs and the paper's 10.

    .venv/bin/python benchmarks/bench_train_speed.py                       # part 1, 4096 steps per variant
    .venv/bin/python benchmarks/bench_train_speed.py --world /tmp/ws-demo/world --steps 8192

Writes benchmarks/results/train_speed.md (with the load average: the machine may be shared).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from sb3_contrib import RecurrentPPO
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from drivesim.policy.net import encoder_macs
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.recurrent import ChunkedRecurrentPPO, TimedVecEnv
from drivesim.stages.train.sb3_policy import DrivingLstmPolicy, EncoderExtractor

RESULTS = Path(__file__).parent / "results" / "train_speed.md"
LEARNER = "The learner alone (cost-free env)"
REAL = "End to end with the real simulator (overtake)"
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
    common = {"n_steps": 1024, "batch_size": 512, "n_epochs": epochs, "device": "cpu", "seed": 0, "verbose": 0}
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


def real_env_rows(world: Path, steps: int, envs: int) -> list[Row]:
    from drivesim.pipeline.config import load_config
    from drivesim.stages.train.envs import EnvSource
    from drivesim.stages.train.run import build_model

    rows = []
    # Batched envs in the learner's process (`envs` of them, then 8), 8 split over 2 worker processes that step in
    # parallel (the learner with its 2 torch threads throughout, then with 1 while it collects the rollout), the
    # same with the paper's 10 epochs, and SB3's one process per env as the alternative.
    variants = ((4, "batched", envs, 1, None), (4, "batched", 8, 1, None), (4, "batched", 8, 2, None),
                (4, "batched", 8, 2, 1), (10, "batched", 8, 2, 1), (4, "subproc", 2, 1, None))  # fmt: skip
    for epochs, vec_env, count, processes, rollout_threads in variants:
        overrides = [f"ppo.epochs={epochs}", f"envs.count={count}", f"envs.vec_env={vec_env}",
                     f"envs.processes={processes}", f"ppo.buffer_steps={steps}"]  # fmt: skip
        if rollout_threads is not None:
            overrides.append(f"rollout_threads={rollout_threads}")
        cfg = load_config(TrainConfig, preset="train/overtake", overrides=overrides)
        source = EnvSource(task="overtake", worlds=[world], processes=cfg.envs.processes)
        venv = source.make_vec(cfg.envs.count, cfg.envs.vec_env, seed=0)
        where = f"{processes} worker processes" if processes > 1 else "in the learner's process"
        if rollout_threads is not None:
            where += f", {rollout_threads} learner thread during rollouts"
        rows.append(
            measure(
                f"overtake, real simulator ({cfg.envs.vec_env}, {count} envs"
                f"{', ' + where if vec_env == 'batched' else ''}), {epochs} epochs, buffer {cfg.ppo.buffer_steps}",
                lambda env, cfg=cfg: build_model(cfg, env),
                steps,
                venv,
                threads=cfg.learner_threads,
            )
        )
    return rows


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


def _sections() -> dict[str, str]:
    """The result file's two sections (learner alone, real simulator) as last written."""
    if not RESULTS.is_file():
        return {}
    parts = RESULTS.read_text().split("\n## ")
    return {p.split("\n", 1)[0]: "## " + p for p in parts[1:]}


def write_results(
    learner: list[Row], real: list[Row], args: argparse.Namespace, load: tuple[float, float, float]
) -> None:
    """Rewrite the sections measured now; keep the other one as it was."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    when = (
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.node()} "
        f"({os.cpu_count()} cores), torch {torch.__version__}; load average before: {load[0]:.2f} / {load[1]:.2f} "
        f"/ {load[2]:.2f} (1/5/15 min)."
    )
    sections = _sections()
    if learner:
        sections[LEARNER] = "\n".join(
            [
                f"## {LEARNER}",
                "",
                when + f" Cost-free env, 2 envs, {args.steps} steps, rollout 1024 steps per env, "
                f"minibatch 512, {args.epochs} epochs. `python benchmarks/bench_train_speed.py` redoes it.",
                "",
                *_table(learner),
                "",
            ]
        )
    if real:
        sections[REAL] = "\n".join(
            [
                f"## {REAL}",
                "",
                when + f" The overtake preset on {args.world}, "
                f"{args.real_steps} env steps per run, the buffer cut to that. `python benchmarks/bench_train_speed.py "
                "--only-real --world WORLD` redoes it.",
                "",
                *_table(real),
                "",
            ]
        )
    text = "# Training speed: env steps per second of `learn()`\n\n" + "\n".join(
        sections[k] for k in (LEARNER, REAL) if k in sections
    )
    RESULTS.write_text(text.rstrip() + "\n")
    print(f"wrote {RESULTS}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4096, help="env steps per variant")
    parser.add_argument("--epochs", type=int, default=4, help="PPO epochs of the learner variants")
    parser.add_argument("--skip-slow", action="store_true", help="skip sb3-contrib's default policy variants")
    parser.add_argument("--world", type=Path, default=None, help="a world folder: also the real overtake env")
    parser.add_argument("--real-steps", type=int, default=8192, help="env steps of each real-env run")
    parser.add_argument("--envs", type=int, default=4, help="envs of the real-env runs")
    parser.add_argument("--only-real", action="store_true", help="only the real-env runs")
    args = parser.parse_args()
    load = os.getloadavg()
    learner = [] if args.only_real else learner_variants(args.steps, args.epochs, not args.skip_slow)
    real = [] if args.world is None else real_env_rows(args.world, args.real_steps, args.envs)
    write_results(learner, real, args, load)


if __name__ == "__main__":
    main()
