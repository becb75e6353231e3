"""The eval stage's config (`drivesim config eval` lists every key with its unit)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_serializer, field_validator, model_validator

from drivesim.pipeline.config import StageConfig
from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.registry import TaskName, task_spec


class EvalConfig(StageConfig):
    """`drivesim eval`: closed-loop episodes with fixed seeds, the paper's metrics, plots and an HTML report."""

    task: TaskName = "overtake"
    """The task to evaluate (sim/envs/registry.py lists the tasks and their gymnasium ids)."""
    scenario: list[str] = []
    """The task's scenarios to restrict the episodes to, at most one of each group (overtake's, the paper's Table II:
    static or dynamic, pass-left or pass-right). Empty: the task's own distribution."""
    policy: str = "expert"
    """`expert` (privileged expert), `random` (a baseline), a `drivesim train` run folder or one of its checkpoints
    (`<run>/checkpoints/<name>.pt`), or an exported `.onnx` file."""
    episodes: int = Field(1000, ge=1, le=10_000_000)
    """Number of episodes; episode i is reset with seed `seed + i`."""
    seed: int = Field(0, ge=0)
    """Seed of the first episode."""
    baseline_episodes: int = Field(200, ge=0, le=10_000_000)
    """Episodes of the baselines beside a trained policy (the expert, and the run's warm start when it kept one), on
    the evaluation's first seeds; at most `episodes`; 0: no baselines."""
    world: list[str] | None = None
    """World folder(s) to evaluate in, each with the same seeds and `episodes` episodes; null = the workspace's world/.
    Several give a row per world and pooled figures."""
    meshes: str | None = None
    """Vehicle mesh library folder; null = the workspace's meshes/ when built, else the procedural library."""
    env: EnvConfig = Field(default_factory=EnvConfig)
    """The env config (keys listed below as env.*); the keys you set override a run's training env config, the
    others come from the run (its view, its thresholds)."""
    video: int = Field(0, ge=0, le=1000)
    """MP4s to render of chosen episodes (alternately the worst and the best)."""
    record: str | int = "failures"
    """Episodes written as Foxglove MCAP, `recordings/<seed>.mcap`: failures (with an intervention, the first 50 by
    seed), all, N (the first N episodes), or none."""
    clearance_histogram_max_m: float = Field(2.0, gt=0)
    """Upper end of the per-step clearance histogram (Fig. 5) [m]."""
    env_id: str | None = None
    """Gymnasium id to evaluate in instead of the task's drivesim env (a user's own registered env)."""
    env_entry_point: str | None = None
    """`module:Class` of a gymnasium.Env subclass, registered as `env_id` when it is not yet: a drivesim env, or your
    own with `drivesim eval --trust-entry-point`."""
    workers: int | None = Field(None, ge=1, le=4096, exclude=True)
    """Worker processes (Ray actors with backend ray); null = one per core (of the cluster). Not part of the
    artifact's identity (same seeds, same numbers)."""
    backend: Literal["local", "ray"] = Field("local", exclude=True)
    """local: worker processes on this machine; ray: Ray actors over a cluster's workers (`pip install
    'drivesim[ray]'`). Not part of the artifact's identity (same seeds, same numbers)."""
    address: str | None = Field(None, exclude=True)
    """With backend ray: the cluster, "auto" (started by `ray start` on this machine) or the head's host:port; null =
    start Ray on this machine for the evaluation. Not part of the artifact's identity."""
    name: str | None = Field(None, exclude=True)
    """The evaluation's folder name under eval/; null = `<task>-<policy>`. Not part of the artifact's identity."""

    @field_validator("record", mode="before")
    @classmethod
    def _record_value(cls, value: Any) -> Any:
        """One readable error for a --record value that is none of the modes (rather than one per union member)."""
        text = str(value).strip().lower()
        if text not in ("failures", "all", "none") and not text.isdigit():
            raise ValueError(f"{value!r}: use failures, all, none or a number of episodes")
        return int(text) if text.isdigit() else text

    @field_validator("env_id")
    @classmethod
    def _env_id_form(cls, value: str | None) -> str | None:
        """A gymnasium id alone (`module:Name-v0` would make gymnasium import `module`)."""
        from drivesim.stages.evaluate.entry_point import check_env_id

        return None if value is None else check_env_id(value)

    @field_validator("env_entry_point")
    @classmethod
    def _entry_point_form(cls, value: str | None) -> str | None:
        """`module:Class`, checked when the config is read (which classes may be registered: `entry_point.py`)."""
        from drivesim.stages.evaluate.entry_point import parse_entry_point

        if value is not None:
            parse_entry_point(value)
        return value

    @field_validator("world", mode="before")
    @classmethod
    def _world_list(cls, value: Any) -> Any:
        """One world folder as a path is still accepted (a list of one); an empty list means the workspace's."""
        if isinstance(value, str):
            return [value]
        if isinstance(value, list | tuple) and not value:
            return None
        return value

    @field_serializer("world")
    def _world_json(self, value: list[str] | None) -> str | list[str] | None:
        """One world is written as its path, as before lists were accepted (the same evaluation keeps its identity)."""
        return value[0] if value is not None and len(value) == 1 else value

    def env_overrides(self) -> dict[str, Any]:
        """The env keys the user set (preset, --config or --set) and the scenarios', to apply over a run's training
        env config."""
        overrides = self.env.model_dump(mode="json", exclude_unset=True)
        settings = {name: env for group in self._task_scenarios() for name, env in group.items()}
        for name in self.scenario:
            overrides.update(settings[name])
        return overrides

    def _task_scenarios(self) -> tuple[dict[str, dict[str, Any]], ...]:
        """The task's scenario groups (`DrivingEnv.scenarios()`; () for none)."""
        return task_spec(self.task).env_class().scenarios() if self.scenario else ()

    @model_validator(mode="after")
    def _check_scenarios(self) -> EvalConfig:
        groups = self._task_scenarios()
        known = [name for group in groups for name in group]
        for name in self.scenario:
            if name not in known:
                offer = f"choose from {', '.join(known)}" if known else "it has none; leave scenario empty"
                raise ValueError(f"scenario {name!r} is not one of the {self.task} task's scenarios: {offer}")
        for group in groups:
            chosen = [name for name in group if name in self.scenario]
            if len(chosen) > 1:
                raise ValueError(f"scenario: {' and '.join(chosen)} exclude each other; choose one")
        return self

    def start_env_config(self) -> dict[str, Any]:
        """The env config of a policy that brings none (the expert): the keys the user set and the scenarios'; the
        env puts them over its task's own settings (`default_config()`)."""
        return self.env_overrides()
