"""The train stage's config (`drivesim config train`); presets per task in `configs/train/<task>.yaml`."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from drivesim.pipeline.config import STRICT_MODEL_CONFIG, StageConfig
from drivesim.policy.net_size import check_network_size
from drivesim.sim.envs.config import EnvConfig, check_torch_device
from drivesim.sim.envs.registry import TASKS, TaskName, task_spec

ConvLayer = tuple[
    Annotated[int, Field(ge=1, le=4096)], Annotated[int, Field(ge=1, le=64)], Annotated[int, Field(ge=1, le=64)]
]
"""One convolution: (out_channels, kernel_px, stride_px), each at least 1."""


class _Section(BaseModel):
    model_config = STRICT_MODEL_CONFIG  # unknown keys refused, finite floats


class PolicyConfig(_Section):
    """The CNN + LSTM (policy/net.py)."""

    conv_layers: list[ConvLayer] = Field(
        default_factory=lambda: [(16, 5, 2), (32, 3, 2), (64, 3, 1)], min_length=1, max_length=32
    )
    """Convolutions as (out_channels, kernel_px, stride_px), 'valid' padding, ReLU after each; at least one."""
    input_pool: int = Field(2, ge=1, le=64)
    """Average-pool factor applied to the standardized image before the first convolution (1: none)."""
    features_dim: int = Field(128, ge=1)
    """Size of the CNN's feature vector fed to the LSTM."""
    lstm_hidden_size: int = Field(128, ge=1)
    """LSTM cells per layer (one LSTM shared by the steering and the value heads)."""
    lstm_layers: int = Field(1, ge=1, le=16)
    """LSTM layers."""
    log_std_init: float = Field(-1.0, ge=-20.0, le=5.0)
    """Initial log standard deviation of the Gaussian steering distribution (normalized steering units)."""
    sequence_length_steps: int = Field(16, ge=1)
    """Length of the fixed sequence chunks the recurrent training pass runs over [env steps]."""
    memory_weight: float = Field(0.0, ge=0.0, le=100.0)
    """Weight of an auxiliary loss in the cloning passes (warm start, imitation): a head on the LSTM predicts where the
    other car is (privileged, a target only), so the LSTM keeps a car out of view; 0: off."""


class PPOConfig(_Section):
    """PPO (sb3-contrib RecurrentPPO); the paper: buffer 32000, minibatch 512, defaults otherwise."""

    buffer_steps: int = Field(32000, ge=1)
    """Transitions collected per update, over all envs [env steps]; rounded to whole chunks per env."""
    minibatch_steps: int = Field(512, ge=1)
    """Transitions per gradient step [env steps]; a multiple of the sequence length."""
    epochs: int = Field(10, ge=1, le=10_000)
    """Passes over the buffer per update."""
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0)
    """Adam learning rate."""
    learning_rate_end_fraction: float = Field(1.0, ge=0.0, le=1.0)
    """PPO's and the update phases' learning rates at the budget's end, as a fraction of their start; linear in the
    budget spent (steps or time, the further); 1: constant."""
    gamma: float = Field(0.99, ge=0.0, le=1.0)
    """Discount factor per step."""
    gae_lambda: float = Field(0.95, ge=0.0, le=1.0)
    """GAE lambda."""
    clip_range: float = Field(0.2, gt=0.0)
    """PPO clipping of the probability ratio."""
    ent_coef: float = Field(0.0, ge=0.0)
    """Entropy bonus weight."""
    vf_coef: float = Field(0.5, ge=0.0)
    """Value loss weight."""
    max_grad_norm: float = Field(0.5, gt=0.0)
    """Gradient norm clip."""
    normalize_reward: bool = True
    """Divide rewards by the running std of the discounted return (SB3 VecNormalize), so the shared trunk's value loss
    stays of order 1."""
    target_kl: float | None = Field(None, gt=0.0)
    """Stop an update's epochs early when the KL divergence exceeds 1.5x this (None: never)."""


class EnvsConfig(_Section):
    """The training environments."""

    source: Literal["simulator", "cost_free"] = "simulator"
    """simulator: drivesim's envs on the given worlds; cost_free: a stand-in env that costs nothing (a one-stripe
    picture; measures the learner alone and tests the training mechanics; needs no world)."""
    count: int = Field(2, ge=1, le=100_000)
    """Episodes simulated at once (one per core with subprocesses; any number with `batched`)."""
    vec_env: Literal["batched", "subproc", "dummy"] = "batched"
    """batched: drivesim's BatchedVecEnv (one batched render call per process, see `processes`); subproc: one
    process per env; dummy: all in this process, one after the other."""
    processes: int = Field(1, ge=1, le=4096)
    """batched: worker processes the episodes are split over, stepping in parallel (1: in the learner's process;
    the number of cores is a good choice when the simulator dominates)."""
    config: EnvConfig = Field(default_factory=EnvConfig)
    """The env config of every training episode: the task's own (`default_config()` in sim/envs/<task>.py) with the
    keys given here on top (sim/envs/config.py lists them)."""
    worker_threads: int = Field(1, ge=1, le=4096)
    """torch threads in each env worker process."""
    backend: Literal["local", "ray"] = "local"
    """local: the envs run on this machine as `vec_env` says; ray: each env in a Ray actor spread over a cluster
    (RayVecEnv), so `count` may exceed this machine's cores (`pip install 'drivesim[ray]'`)."""
    address: str | None = None
    """With backend ray: the cluster, "auto" (started by `ray start` on this machine) or the head's host:port;
    null = start Ray on this machine for the run."""


class EvalConfig(_Section):
    """Periodic evaluation on held-back seeds (deterministic policy, eval mode: any overlap is a collision)."""

    every_steps: int = Field(50000, ge=0)
    """Evaluate every this many env steps (0: never)."""
    episodes: int = Field(8, ge=0)
    """Episodes per evaluation."""
    seed: int = Field(1_000_000, ge=0)
    """First held-back seed (training episodes never use seeds at or above it)."""
    keep_best: bool = False
    """On: the run's policy is its best periodic evaluation's weights (success, then mean return). Off: the last
    update's. The best are in checkpoints/best.pt either way."""


class WarmStartConfig(_Section):
    """Behaviour cloning from the privileged expert on the states the learner visits (DAgger), then a value fit."""

    method: Literal["none", "expert"] = "none"
    """none: PPO from scratch; expert: DAgger from `env.unwrapped.expert_action()` first."""
    iterations: int = Field(4, ge=1, le=10_000)
    """DAgger rounds; round i acts with the expert with probability beta**i, else with the learner."""
    beta: float = Field(0.5, ge=0.0, le=1.0)
    """Expert mixing decay per round (round 0 is all expert)."""
    steps_per_iteration: int = Field(4096, ge=1)
    """Env steps collected per round (all envs together)."""
    epochs: int = Field(4, ge=1, le=10_000)
    """Passes over the aggregated data after each round."""
    learning_rate: float = Field(1e-3, gt=0.0, le=1.0)
    """Adam learning rate for cloning and for the value fit."""
    sequence_length_steps: int | None = Field(None, ge=1)
    """Length of the chunks the cloning fits the LSTM over [env steps] (None: policy.sequence_length_steps); longer
    chunks ask the LSTM to keep what it saw for longer."""
    value_fit_steps: int = Field(4096, ge=0)
    """Env steps of the cloned policy whose returns the value head is fitted to before PPO."""
    value_fit_epochs: int = Field(10, ge=0)
    """Passes over those steps for the value head."""


class ImitationConfig(_Section):
    """Cloning of the privileged expert on PPO's own rollouts after each update, a regularizer that keeps PPO near the
    expert where its reward misleads it (stages/train/imitation.py); off by default, as in the paper."""

    epochs: int = Field(0, ge=0, le=1000)
    """Cloning passes over each rollout after its PPO update (0: off)."""
    learning_rate: float = Field(1e-4, gt=0.0, le=1.0)
    """Adam learning rate of the cloning (the std is left to PPO)."""
    history_steps: int = Field(0, ge=0, le=1_000_000)
    """Labelled states the cloning draws from: the newest rollouts' (the warm start's first), oldest dropped first;
    about 30 KB of memory each. 0: the last rollout only."""


class LaneAuxConfig(_Section):
    """An auxiliary target for the image encoder after each PPO update: the ego's lateral offset and heading relative
    to its lane, which the simulator knows (stages/train/lane_aux.py); off by default."""

    epochs: int = Field(0, ge=0, le=1000)
    """Passes over each rollout after its PPO update (0: off)."""
    learning_rate: float = Field(1e-4, gt=0.0, le=1.0)
    """Adam learning rate of the encoder and the target's linear head."""


class TrainConfig(StageConfig):
    """`drivesim train`: PPO with a CNN and an LSTM (paper §III-C, §IV-A)."""

    task: TaskName = "overtake"
    """The task to train (sim/envs/registry.py)."""
    total_steps: int = Field(2_000_000, ge=1)
    """Env steps to train for (warm start not counted)."""
    towns: list[int] = []
    """Procedural towns (seeds) to train on as well: town N is `<workspace>/towns/seed<N>/world`, built first when
    missing, added to the run's worlds; [] for none."""
    time_limit_s: float | None = Field(None, gt=0.0)
    """Stop after this much training wall time, at the end of an update, and finish the run [s] (None: no limit)."""
    seed: int = Field(0, ge=0)
    """Seed of the policy's initialization and of the training episodes."""
    ensemble: int = Field(1, ge=1, le=16)
    """Policies to train with seeds seed, seed + 1, ..., made into one ensemble run whose steering is the mean of theirs
    (`policy/ensemble.py`); 1: one policy."""
    learner_threads: int = Field(2, ge=1, le=4096)
    """torch threads of the learner (this process)."""
    rollout_threads: int | None = Field(None, ge=1, le=4096)
    """torch threads of the learner while it collects a rollout (None: learner_threads); 1 leaves the cores to the env
    worker processes when envs.processes > 1."""
    device: str = "cpu"
    """torch device of the learner (PPO's updates, the warm start, the imitation): "cpu" or "cuda". With a GPU, set
    envs.config.render_device too, so the views are rendered there as well."""
    checkpoint_every_steps: int = Field(100_000, ge=1)
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
    imitation: ImitationConfig = Field(default_factory=ImitationConfig)
    """Imitation of the privileged expert alongside PPO."""
    lane_aux: LaneAuxConfig = Field(default_factory=LaneAuxConfig)
    """The encoder's auxiliary target (where the ego is in its lane) alongside PPO."""

    @field_validator("device")
    @classmethod
    def _device(cls, value: str) -> str:
        return check_torch_device(value)

    @model_validator(mode="before")
    @classmethod
    def _task_env_config(cls, data: Any) -> Any:
        """envs.config: the task's env settings (`default_config()` of its class) under the keys given."""
        task = data.get("task", cls.model_fields["task"].default) if isinstance(data, dict) else None
        if not isinstance(task, str) or task not in TASKS:
            return data  # not a mapping or a bad task: refused by the fields' own checks
        defaults = task_spec(task).env_class().default_config().model_dump()
        envs = data.get("envs")
        if isinstance(envs, EnvsConfig):  # typed (or an assignment): its config's keys set by hand over the task's
            config = EnvConfig.model_validate({**defaults, **envs.config.model_dump(exclude_unset=True)})
            return {**data, "envs": envs.model_copy(update={"config": config})}
        if envs is not None and not isinstance(envs, dict):
            return data
        envs = dict(envs or {})
        given = envs.get("config")
        if isinstance(given, EnvConfig):
            given = given.model_dump(exclude_unset=True)
        if given is not None and not isinstance(given, dict):
            return data  # not a mapping: refused by the field's own check
        return {**data, "envs": {**envs, "config": {**defaults, **(given or {})}}}

    @field_validator("towns")
    @classmethod
    def _town_seeds(cls, value: list[int]) -> list[int]:
        if any(seed < 0 for seed in value):
            raise ValueError("town seeds are 0 or more")
        return value

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
        clone_seq = self.warm_start.sequence_length_steps
        if clone_seq not in (None, seq) and self.imitation.epochs > 0 and self.imitation.history_steps > 0:
            raise ValueError(
                f"warm_start.sequence_length_steps ({clone_seq}) must equal policy.sequence_length_steps ({seq}) "
                "when imitation.history_steps keeps the warm start's chunks"
            )
        pol = self.policy
        check_network_size(
            self.envs.config.observation_shape,
            pol.conv_layers,
            pol.features_dim,
            pol.lstm_hidden_size,
            pol.lstm_layers,
            pol.input_pool,
        )
        return self

    def steps_per_env(self) -> int:
        """Rollout length per env per update: buffer_steps / envs, rounded up to whole sequence chunks."""
        seq = self.policy.sequence_length_steps
        per_env = -(-self.ppo.buffer_steps // self.envs.count)
        return max(seq, -(-per_env // seq) * seq)
