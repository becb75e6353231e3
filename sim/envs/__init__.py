"""The driving tasks as gymnasium environments (drivesim/Lane-v0, Follow-v0, Overtake-v0, CutIn-v0).

Importing this package registers them: `import drivesim.sim.envs`, then `gymnasium.make("drivesim/Overtake-v0",
world=..., meshes=...)`. The list of tasks is `registry.TASKS`.
"""

from drivesim.sim.envs.registry import TASK_NAMES, TASKS, register_envs, task_spec

__all__ = ["TASKS", "TASK_NAMES", "register_envs", "task_spec"]

register_envs()
