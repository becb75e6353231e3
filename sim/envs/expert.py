"""The privileged expert: pure pursuit with access to the true state (the reference policy and the DAgger teacher).

It steers to the lateral offset the task chooses (`DrivingEnv.expert_target_offset`: the lane centre by default;
overtake swerves around the front car, follow tracks the front car's path). The target point is one lookahead
ahead on that offset; the lookahead grows with speed so that a swerve stays smooth. The pursuit is computed from the
pose one env step ahead (the current steering held): the command takes effect over that step and the steering is
rate-limited, so pursuing from the current pose counter-steers a step late and overshoots a swerve (off lane,
over-rotation at a bend's exit; experiments/expert_delay).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drivesim.sim.agents import pure_pursuit_curvature
from drivesim.sim.dynamics import rk3_step

if TYPE_CHECKING:
    from drivesim.sim.envs.base import DrivingEnv

EXPERT_CLEARANCE_M = 1.0  # gap the overtaking expert keeps between the footprints, m
EXPERT_LOOKAHEAD_M = 4.0
EXPERT_LOOKAHEAD_S = 0.4


def expert_action(env: DrivingEnv) -> np.ndarray:
    """The expert's normalized steering action, (1,) float32 in [-1, 1]."""
    c, sim = env.config, env.sim
    ego = sim.agents[0]
    ahead = rk3_step(ego.state, 0.0, 0.0, c.dt_s, c.wheelbase_m)
    lookahead = max(EXPERT_LOOKAHEAD_M, EXPERT_LOOKAHEAD_S * ego.state.speed_mps)
    target = env.expert_target_offset()
    tx, ty, _ = sim.reference.pose(ego.arc_m + ego.state.speed_mps * c.dt_s + lookahead, target)
    curvature = pure_pursuit_curvature(ahead, tx, ty, gain=1.0, lookahead_m=lookahead)
    return np.array([np.clip(curvature / c.max_curvature_1pm, -1.0, 1.0)], dtype=np.float32)
