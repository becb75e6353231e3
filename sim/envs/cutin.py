"""drivesim/CutIn-v0: hold the lane while a faster car from the adjacent lane passes and cuts in ahead."""

from __future__ import annotations

import numpy as np

from drivesim.sim.agents import LateralProfile, ReferencePath
from drivesim.sim.envs.base import DrivingEnv
from drivesim.sim.envs.config import OTHER_CAR_KEYS, EnvConfig

START_BEHIND_M = (2.0, 6.0)
"""Range of how far behind the ego (centre to centre, along the road) the other car starts, m."""
CUT_DURATION_S = 2.0
"""Time the other car takes to move from its lane into the ego's, s."""


class CutInEnv(DrivingEnv):
    """Cut-in: another car comes from the adjacent lane faster than the ego, passes and cuts in ahead.

    ## Action and observation spaces
    As drivesim/Lane-v0 (normalized steering curvature; the (3, h, w) uint8 camera region of interest), with the
    other car inserted into the view once it is in front of the camera.

    ## Rewards
    lane = weight_lane · (1 - (q_lat / Z_lat)²); collision = weight_collision · -|Dilate(P_ego) ∩ P_other| / |P_ego|
    (the paper's dilated polygons: the gap term); comfort = -weight_comfort · |δ̈|.

    ## Start state
    The ego as in Lane-v0 at a speed from ego_speed_mps (held). The other car starts 2-6 m behind it in the
    adjacent lane (front_lateral_m to a random side) at a speed from other_speed_mps (above the ego's in
    `default_config()`: it passes only when faster), drives with pure pursuit and, once it is front_distance_m
    ahead of the ego (centre to centre, along the road), moves into the ego's lane centre over CUT_DURATION_S.

    ## Episode end
    As Lane-v0, plus collision: the undilated footprints overlap by more than collision_overlap_train of the ego's
    area in training (collision_overlap_eval in evaluation). info["success"]: the episode reached its time limit (or
    the end of the recorded road) without an intervention.
    """

    task = "cutin"
    has_other = True
    task_keys = (*OTHER_CAR_KEYS, "other_speed_mps")

    @classmethod
    def default_config(cls) -> EnvConfig:
        """The base's, with an other car faster than the ego in the adjacent lane, 15-s episodes and the road its
        pass needs."""
        return (
            super()
            .default_config()
            .model_copy(
                update={
                    "ego_speed_mps": (5.0, 8.0),
                    "other_speed_mps": (10.0, 12.0),  # faster than the ego, so that it passes it from behind
                    "front_distance_m": (5.0, 15.0),  # where it cuts in, ahead of the ego
                    "front_lateral_m": (3.2, 3.8),  # the adjacent lane's centre
                    "episode_steps": 150,  # 15 s: the cut-in happens within about 11 s of the start
                    "min_path_length_m": 190.0,  # the other car drives 12 m/s for 15 s
                    "weight_collision": 50.0,
                }
            )
        )

    def _farthest_start_ahead_m(self) -> float | None:
        return None  # it starts behind the ego; front_distance_m is where it cuts in

    def _place_other(
        self,
        rng: np.random.Generator,
        ego_arc_m: float,
        ref: ReferencePath,
        ego_speed_mps: float,
        other_speed_mps: float,
    ) -> tuple[float, float, LateralProfile]:
        c = self.config
        behind_m = float(rng.uniform(*START_BEHIND_M))
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        side = {"left": 1.0, "right": -1.0}.get(c.front_side, side)
        lateral_m = side * float(rng.uniform(*c.front_lateral_m))
        cut_gap_m = float(rng.uniform(*c.front_distance_m))
        arc_m = ego_arc_m - behind_m
        closing_mps = max(other_speed_mps - ego_speed_mps, 0.1)
        # The other car's arc when it is cut_gap_m ahead of the ego (both at their held speeds), shifted by the
        # pure-pursuit lookahead, which makes it start turning that much before its profile does.
        cut_arc_m = arc_m + other_speed_mps * (behind_m + cut_gap_m) / closing_mps + c.pursuit_lookahead_m
        ramp_m = max(other_speed_mps * CUT_DURATION_S, 1.0)
        profile = LateralProfile(
            np.array([arc_m, cut_arc_m, cut_arc_m + ramp_m]), np.array([lateral_m, lateral_m, 0.0])
        )
        return arc_m, lateral_m, profile
