"""The eval stage's config (`drivesim config eval` lists every key with its unit)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_serializer, field_validator, model_validator

from drivesim.pipeline.config import StageConfig, load_yaml_text, preset_path
from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.registry import TaskName

# The paper's Table II scenarios as env settings: the front car static or moving, the ego passing on its left or right.
SCENARIOS: dict[str, dict[str, Any]] = {
    "static": {"other_speed_mps": (0.0, 0.0)},
    "dynamic": {"other_speed_mps": (1.0, 4.0)},
    "pass-left": {"front_side": "right"},
    "pass-right": {"front_side": "left"},
}
Scenario = Literal["static", "dynamic", "pass-left", "pass-right"]


class EvalConfig(StageConfig):
    """`drivesim eval`: closed-loop episodes with fixed seeds, the paper's metrics, plots and an HTML report."""

    task: TaskName = "overtake"
    """The task to evaluate (sim/envs/registry.py lists the tasks and their gymnasium ids)."""
    scenario: list[Scenario] = []
    """The paper's Table II scenarios to restrict the episodes to: static or dynamic (front car at 0 m/s, or 1-4
    m/s), pass-left or pass-right (the ego passes on that side); combine one of each, e.g. [static, pass-left].
    Empty: the task's own distribution (the report's scenario table then splits its episodes)."""
    policy: str = "expert"
    """`expert` (the env's privileged expert), `random` (uniform random steering, a baseline), a run folder of
    `drivesim train` (or one of its checkpoints, `<run>/checkpoints/<name>.pt`), or an exported `.onnx` file."""
    episodes: int = Field(1000, ge=1, le=10_000_000)
    """Number of episodes; episode i is reset with seed `seed + i`."""
    seed: int = Field(0, ge=0)
    """Seed of the first episode."""
    world: list[str] | None = None
    """World folder(s) to evaluate in, each with the same seeds and `episodes` episodes (one path or a list);
    null = the workspace's world/. Several worlds give a table with a row per world and the pooled figures."""
    meshes: str | None = None
    """Vehicle mesh library folder; null = the workspace's meshes/ when built, else the procedural library."""
    env: EnvConfig = Field(default_factory=EnvConfig)
    """The env config (keys listed below as env.*); the keys you set override a run's training env config, the
    others come from the run (its view, its thresholds)."""
    video: int = Field(0, ge=0, le=1000)
    """MP4s to render of chosen episodes (alternately the worst and the best)."""
    record: str | int = "failures"
    """Episodes written as Foxglove MCAP files, `recordings/<seed>.mcap`: failures = those with an intervention, the
    first 50 by seed; all; N (a number) = the first N episodes; none or 0 = no recordings
    (stages/evaluate/record.py)."""
    clearance_histogram_max_m: float = Field(2.0, gt=0)
    """Upper end of the per-step clearance histogram (Fig. 5) [m]."""
    env_id: str | None = None
    """Gymnasium id to evaluate in instead of the task's drivesim env (a user's own registered env)."""
    env_entry_point: str | None = None
    """`module:Class` registering `env_id` first when it is not registered yet."""
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
        for name in self.scenario:
            overrides.update(SCENARIOS[name])
        return overrides

    @model_validator(mode="after")
    def _check_scenarios(self) -> EvalConfig:
        for pair in (("static", "dynamic"), ("pass-left", "pass-right")):
            if set(pair) <= set(self.scenario):
                raise ValueError(f"scenario: {pair[0]} and {pair[1]} exclude each other; choose one")
        return self

    def start_env_config(self) -> dict[str, Any]:
        """The env config of a policy that brings none (the expert): the task's training preset's env settings
        (e.g. cutin's faster other car), then the keys the user set. A user's own env (`env_id`) gets only those."""
        preset = {} if self.env_id is not None else task_preset_env(self.task)
        return {**preset, **self.env_overrides()}


def task_preset_env(task: str) -> dict[str, Any]:
    """`envs.config` of the task's training preset (`configs/train/<task>.yaml`), {} when it sets none."""
    path = preset_path(f"train/{task}")
    data = load_yaml_text(path.read_text()) if path.is_file() else {}
    return dict(((data or {}).get("envs") or {}).get("config") or {})
