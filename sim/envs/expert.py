"""The privileged expert: pure pursuit with access to the true state (the reference policy and the DAgger teacher).

Overtake: it swerves to the side of the front car with more room, to a lateral offset that keeps `clearance_m`
between the footprints, holds it until the ego is Z_pass ahead, then returns to the lane centre. Follow: it tracks
the front car's path. Lane: it tracks the lane centre. The target point is one lookahead ahead on the chosen
offset; the lookahead grows with speed so that the swerve stays smooth.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drivesim.sim.agents import pure_pursuit_curvature

if TYPE_CHECKING:
    from drivesim.sim.envs.base import DrivingEnv

EXPERT_CLEARANCE_M = 1.0
EXPERT_LOOKAHEAD_M = 4.0
EXPERT_LOOKAHEAD_S = 0.4


def expert_target_offset(env: DrivingEnv) -> float:
    """The lateral offset (m, + = left of the lane centre) the expert steers to now."""
    c, sim = env.config, env.sim
    if not env.has_other:
        return 0.0
    ego, other = sim.agents[0], sim.agents[1]
    if env.task == "follow":
        return other.profile(ego.arc_m + EXPERT_LOOKAHEAD_M)
    if env._m["pass_margin_m"] >= c.pass_distance_m:
        return 0.0
    half_widths = 0.5 * (ego.width_m + other.width_m) + EXPERT_CLEARANCE_M
    o = other.lateral_m
    limit = c.max_lateral_m - 0.5
    target = o - half_widths if o >= 0.0 else o + half_widths
    return float(np.clip(target, -limit, limit))


def expert_action(env: DrivingEnv) -> np.ndarray:
    """The expert's normalized steering action, (1,) float32 in [-1, 1]."""
    c, sim = env.config, env.sim
    ego = sim.agents[0]
    lookahead = max(EXPERT_LOOKAHEAD_M, EXPERT_LOOKAHEAD_S * ego.state.speed_mps)
    target = expert_target_offset(env)
    tx, ty, _ = sim.reference.pose(ego.arc_m + lookahead, target)
    curvature = pure_pursuit_curvature(ego.state, tx, ty, gain=1.0, lookahead_m=lookahead)
    return np.array([np.clip(curvature / c.max_curvature_1pm, -1.0, 1.0)], dtype=np.float32)
