"""An environment that costs (almost) nothing, with drivesim's spaces and info keys.

Used to measure the learner alone (benchmarks/bench_train_speed.py) and to test the training mechanics in seconds.
The picture is a grey image with a bright vertical stripe whose column is the car's lateral offset; the action
steers the offset back (offset += 0.1 * action + drift each step). Reward terms "lane" and "comfort",
terminations "off_lane" and "time_limit"; `expert_action()` steers to the centre. Not a simulator: no view
synthesis, no dynamics.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from drivesim.sim.envs.config import EnvConfig


class CostFreeDrivingEnv(gymnasium.Env):
    """Lane keeping on a one-stripe picture.

    :param observation_shape: (C, H, W) of the uint8 observation.
    :param episode_steps: time limit [steps].
    :param drift: std of the random lateral drift per step [offset units; the lane half-width is 1].
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        observation_shape: tuple[int, int, int] = EnvConfig().observation_shape,
        episode_steps: int = 200,
        drift: float = 0.02,
    ) -> None:
        self.observation_space = spaces.Box(0, 255, observation_shape, np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.episode_steps = episode_steps
        self.drift = drift
        self._frame = np.full(observation_shape, 90, np.uint8)
        self.offset = 0.0
        self.steps = 0
        self.last_action = 0.0
        self.np_random = np.random.default_rng()

    def _obs(self) -> np.ndarray:
        obs = self._frame.copy()
        width = obs.shape[2]
        col = int(np.clip((0.5 + 0.4 * self.offset) * width, 0, width - 1))
        obs[:, :, max(0, col - 2) : col + 3] = 230
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.offset = float(self.np_random.uniform(-0.5, 0.5))
        self.steps = 0
        self.last_action = 0.0
        return self._obs(), {"episode": {"seed": seed}}

    def expert_action(self) -> np.ndarray:
        """The privileged expert: steer proportionally back to the centre."""
        return np.array([np.clip(-5.0 * self.offset, -1.0, 1.0)], np.float32)

    def lane_position(self) -> np.ndarray:
        """The stripe's offset as a lateral offset in metres (the half-width of 1 taken as 2.5 m), heading 0: (2,)."""
        return np.array([2.5 * self.offset, 0.0], np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = float(np.clip(np.asarray(action).reshape(-1)[0], -1.0, 1.0))
        self.offset += 0.1 * a + float(self.np_random.normal(0.0, self.drift))
        self.steps += 1
        rewards = {"lane": 1.0 - self.offset**2, "comfort": -0.1 * abs(a - self.last_action)}
        self.last_action = a
        off_lane = abs(self.offset) > 1.0
        time_limit = self.steps >= self.episode_steps and not off_lane
        info = {
            "rewards": rewards,
            "termination": {
                "off_lane": off_lane,
                "over_rotation": False,
                "collision": False,
                "end_of_data": False,
                "time_limit": time_limit,
            },
            "success": time_limit,
            "state": {"q_lat_m": self.offset},
        }
        return self._obs(), float(sum(rewards.values())), off_lane, time_limit, info
