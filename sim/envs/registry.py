"""The task registry: every driving task of drivesim, written once.

Every other list of tasks is derived from `TASKS`: the gymnasium ids (`drivesim/Lane-v0`, ...), the `task` choices
of `drivesim train` and `drivesim eval` (`TaskName`), the batched env classes and the CLI's help. Importing this
module is light (no simulator, no torch); the env class of a task is imported when it is first made.

A task is one class: its module `sim/envs/<task>.py` holds a `DrivingEnv` subclass that owns everything about it,
its env settings (`default_config()`, extending the base's, which is what `drivesim train <task>` trains and
`gymnasium.make(env_id, world=...)` makes), the config keys it reads (`task_keys`), its start state, reward terms,
success, measurements (the evaluation reports those it finds), scenarios and expert target (see `base.py`'s hooks).
The train preset `configs/train/<task>.yaml` is optional and holds budgets only (steps, PPO, envs, warm start).

A new task takes three files: its module, one line in `_SPECS` below, and one test (docs/new_task.md). E.g.:

    # sim/envs/fastlane.py
    class FastLaneEnv(LaneEnv):  # its class docstring says what the task is
        task = "fastlane"

        @classmethod
        def default_config(cls) -> EnvConfig:
            return super().default_config().model_copy(update={"ego_speed_mps": (15.0, 20.0)})

    # here, in _SPECS:
    TaskSpec("fastlane", "drivesim/FastLane-v0", "drivesim.sim.envs.fastlane:FastLaneEnv", "keep the lane, fast"),

tests/test_tasks.py checks every registered task (`gymnasium.make` is the env `drivesim train <task>` builds); the
task's own test checks what it is for.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from drivesim.sim.envs.base import DrivingEnv
    from drivesim.sim.envs.config import EnvConfig


@dataclass(frozen=True)
class TaskSpec:
    """One driving task.

    :param name: the task's name on the command line (`drivesim train <name>`).
    :param env_id: its gymnasium id.
    :param entry_point: `module:Class` of its `DrivingEnv` subclass.
    :param summary: one line for `--help`.
    """

    name: str
    env_id: str
    entry_point: str
    summary: str

    def env_class(self) -> type[DrivingEnv]:
        """The task's env class (imported on first use)."""
        module, name = self.entry_point.split(":")
        return getattr(importlib.import_module(module), name)

    def config_with(self, overrides: dict[str, Any] | None = None) -> EnvConfig:
        """The task's env config as trained (its class's `default_config()`) with `overrides` on top, validated."""
        return self.env_class().config_with(overrides or {})


_SPECS = (
    TaskSpec("lane", "drivesim/Lane-v0", "drivesim.sim.envs.lane:LaneEnv", "keep the lane, alone on the road"),
    TaskSpec("follow", "drivesim/Follow-v0", "drivesim.sim.envs.follow:FollowEnv", "follow a car changing lanes"),
    TaskSpec("overtake", "drivesim/Overtake-v0", "drivesim.sim.envs.overtake:OvertakeEnv", "pass a slower car"),
    TaskSpec("cutin", "drivesim/CutIn-v0", "drivesim.sim.envs.cutin:CutInEnv", "hold the lane as a car cuts in"),
)

TASKS: dict[str, TaskSpec] = {spec.name: spec for spec in _SPECS}
TASK_NAMES: tuple[str, ...] = tuple(TASKS)
# The `task` field of the train and eval configs: a typo is refused when the config is loaded.
TaskName = Literal[TASK_NAMES]  # type: ignore[valid-type]


def task_spec(name: str) -> TaskSpec:
    """The task called `name`; a one-line ValueError naming the tasks otherwise."""
    if name not in TASKS:
        raise ValueError(f"task {name!r}: choose one of {', '.join(TASK_NAMES)}")
    return TASKS[name]


def task_help() -> str:
    """The tasks with their one-line summaries, for `--help` texts."""
    return "; ".join(f"{spec.name}: {spec.summary}" for spec in _SPECS)


def register_envs() -> None:
    """Register every task's env with gymnasium (idempotent)."""
    from gymnasium.envs.registration import register, registry

    for spec in _SPECS:
        if spec.env_id not in registry:
            # The episode length is the env's own (config.episode_steps, reported as truncation): no TimeLimit.
            register(id=spec.env_id, entry_point=spec.entry_point, disable_env_checker=True, order_enforce=False)
