"""The train stage's config (`drivesim config train`); presets per task in `configs/train/<task>.yaml`."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivesim.pipeline.config import StageConfig
from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.registry import TaskName


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True, validate_assignment=True)


class PolicyConfig(_Section):
    """The CNN + LSTM (stages/policy_net.py)."""

    conv_layers: list[tuple[int, int, int]] = Field(default_factory=lambda: [(16, 5, 2), (32, 3, 2), (64, 3, 1)])
    """Convolutions as (out_channels, kernel_px, stride_px), 'valid' padding, ReLU after each."""
    input_pool: int = 2
    """Average-pool factor applied to the standardized image before the first convolution (1: none)."""
    features_dim: int = 128
    """Size of the CNN's feature vector fed to the LSTM."""
    lstm_hidden_size: int = 128
    """LSTM cells per layer (one LSTM shared by the steering and the value heads)."""
    lstm_layers: int = 1
    """LSTM layers."""
    log_std_init: float = -1.0
    """Initial log standard deviation of the Gaussian steering distribution (normalized steering units)."""
    sequence_length_steps: int = 16
    """Length of the fixed sequence chunks the recurrent training pass runs over [env steps]."""


class PPOConfig(_Section):
    """PPO (sb3-contrib RecurrentPPO); the paper: buffer 32000, minibatch 512, defaults otherwise."""

    buffer_steps: int = 32000
    """Transitions collected per update, over all envs [env steps]; rounded to whole chunks per env."""
    minibatch_steps: int = 512
    """Transitions per gradient step [env steps]; a multiple of the sequence length."""
    epochs: int = 10
    """Passes over the buffer per update."""
    learning_rate: float = 3e-4
    """Adam learning rate."""
    gamma: float = 0.99
    """Discount factor per step."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clip_range: float = 0.2
    """PPO clipping of the probability ratio."""
    ent_coef: float = 0.0
    """Entropy bonus weight."""
    vf_coef: float = 0.5
    """Value loss weight."""
    max_grad_norm: float = 0.5
    """Gradient norm clip."""
    normalize_reward: bool = True
    """Divide rewards by the running std of the discounted return (SB3 VecNormalize), so the shared trunk's value
    loss stays of order 1 (without it lane keeping learned several times slower, benchmarks/results)."""
    target_kl: float | None = None
    """Stop an update's epochs early when the KL divergence exceeds 1.5x this (None: never)."""


class EnvsConfig(_Section):
    """The training environments."""

    source: Literal["simulator", "cost_free"] = "simulator"
    """simulator: drivesim's envs on the given worlds; cost_free: a stand-in env that costs nothing (a one-stripe
    picture; measures the learner alone and tests the training mechanics; needs no world)."""
    count: int = 2
    """Episodes simulated at once (one per core with subprocesses; any number with `batched`)."""
    vec_env: Literal["batched", "subproc", "dummy"] = "batched"
    """batched: drivesim's BatchedVecEnv (one batched render call per process, see `processes`); subproc: one
    process per env; dummy: all in this process, one after the other."""
    processes: int = 1
    """batched: worker processes the episodes are split over, stepping in parallel (1: in the learner's process;
    the number of cores is a good choice when the simulator dominates)."""
    config: EnvConfig = Field(default_factory=EnvConfig)
    """The env config of every training episode (sim/envs/config.py; its keys are listed below as envs.config.*)."""
    worker_threads: int = 1
    """torch threads in each env worker process."""
    backend: Literal["local", "ray"] = "local"
    """local: the envs run on this machine as `vec_env` says; ray: each env in a Ray actor spread over a cluster
    (RayVecEnv), so `count` may exceed this machine's cores (`pip install 'drivesim[ray]'`)."""
    address: str | None = None
    """With backend ray: the cluster, "auto" (started by `ray start` on this machine) or the head's host:port;
    null = start Ray on this machine for the run."""


class EvalConfig(_Section):
    """Periodic evaluation on held-back seeds (deterministic policy, eval mode: any overlap is a collision)."""

    every_steps: int = 50000
    """Evaluate every this many env steps (0: never)."""
    episodes: int = 8
    """Episodes per evaluation."""
    seed: int = 1_000_000
    """First held-back seed (training episodes never use seeds at or above it)."""
    keep_best: bool = True
    """The run's policy is the weights of its best evaluation (success rate, then mean return; kept in
    checkpoints/best.pt), not the last update's. Off: the last update's."""


class WarmStartConfig(_Section):
    """Behaviour cloning from the privileged expert on the states the learner visits (DAgger), then a value fit."""

    method: Literal["none", "expert"] = "none"
    """none: PPO from scratch; expert: DAgger from `env.unwrapped.expert_action()` first."""
    iterations: int = 4
    """DAgger rounds; round i acts with the expert with probability beta**i, else with the learner."""
    beta: float = 0.5
    """Expert mixing decay per round (round 0 is all expert)."""
    steps_per_iteration: int = 4096
    """Env steps collected per round (all envs together)."""
    epochs: int = 4
    """Passes over the aggregated data after each round."""
    learning_rate: float = 1e-3
    """Adam learning rate for cloning and for the value fit."""
    value_fit_steps: int = 4096
    """Env steps of the cloned policy whose returns the value head is fitted to before PPO."""
    value_fit_epochs: int = 10
    """Passes over those steps for the value head."""


class TrainConfig(StageConfig):
    """`drivesim train`: PPO with a CNN and an LSTM (paper §III-C, §IV-A)."""

    task: TaskName = "overtake"
    """The task to train (sim/envs/registry.py)."""
    total_steps: int = 2_000_000
    """Env steps to train for (warm start not counted)."""
    time_limit_s: float | None = None
    """Stop after this much training wall time, at the end of an update, and finish the run [s] (None: no limit)."""
    seed: int = 0
    """Seed of the policy's initialization and of the training episodes."""
    learner_threads: int = 2
    """torch threads of the learner (this process)."""
    checkpoint_every_steps: int = 100_000
    """Keep a numbered checkpoint every this many env steps (checkpoints/last.pt is rewritten after every update)."""
    policy: PolicyConfig = Field(default_factory=PolicyConfig)
    """The network."""
    ppo: PPOConfig = Field(default_factory=PPOConfig)
    """PPO settings."""
    envs: EnvsConfig = Field(default_factory=EnvsConfig)
    """Training environments."""
    eval: EvalConfig = Field(default_factory=EvalConfig)
    """Periodic evaluation."""
    warm_start: WarmStartConfig = Field(default_factory=WarmStartConfig)
    """Warm start from the privileged expert."""

    @model_validator(mode="after")
    def _check_sizes(self) -> TrainConfig:
        seq = self.policy.sequence_length_steps
        if seq < 1 or self.ppo.minibatch_steps % seq:
            raise ValueError(
                f"ppo.minibatch_steps ({self.ppo.minibatch_steps}) must be a multiple of "
                f"policy.sequence_length_steps ({seq})"
            )
        if self.envs.count < 1:
            raise ValueError("envs.count must be at least 1")
        return self

    def steps_per_env(self) -> int:
        """Rollout length per env per update: buffer_steps / envs, rounded up to whole sequence chunks."""
        seq = self.policy.sequence_length_steps
        per_env = -(-self.ppo.buffer_steps // self.envs.count)
        return max(seq, -(-per_env // seq) * seq)
