"""drivesim/Follow-v0: follow a front car that changes lanes at random."""

from __future__ import annotations

import numpy as np

from drivesim.sim.agents import LateralProfile, ReferencePath
from drivesim.sim.envs.base import DrivingEnv
from drivesim.sim.envs.config import OTHER_CAR_KEYS
from drivesim.sim.envs.expert import EXPERT_LOOKAHEAD_M


class FollowEnv(DrivingEnv):
    """Car following (paper §III-C): track the trajectory of a front car that changes lanes.

    ## Action and observation spaces
    As drivesim/Lane-v0 (normalized steering curvature; the (3, h, w) uint8 camera region of interest), with the
    front car inserted into the view.

    ## Rewards
    lane = weight_lane · (1 - (e / Z_lat)²) with e the ego's lateral distance from the front car's path
    (info["state"]["tracking_error_m"]); collision = weight_collision · -|Dilate(P_ego) ∩ P_other| / |P_ego|;
    comfort = -weight_comfort · |δ̈|.

    ## Start state
    The ego as in Lane-v0; the front car front_distance_m ahead and front_lateral_m to a random side, heading
    along the road; both at one common speed drawn from follow_speed_mps. The front car drives with pure pursuit
    (pursuit_gain, pursuit_lookahead_m) on a path that changes between its start offset, the lane centre and the
    mirrored offset at random places.

    ## Episode end
    As Lane-v0, plus collision: the undilated footprints overlap by more than collision_overlap_train of the ego's
    area in training (collision_overlap_eval in evaluation). info["success"]: ended without an intervention.

    ## Evaluation extras
    info["state"]["tracking_error_m"], reported as the mean tracking error and along the track (Fig. 6).
    """

    task = "follow"
    has_other = True
    task_keys = (*OTHER_CAR_KEYS, "follow_speed_mps")

    def _speeds(self, rng: np.random.Generator) -> tuple[float, float]:
        speed = float(rng.uniform(*self.config.follow_speed_mps))
        return speed, speed

    def _other_profile(
        self, rng: np.random.Generator, arc_m: float, lateral_m: float, ref: ReferencePath
    ) -> LateralProfile:
        return LateralProfile.lane_changes(rng, arc_m, ref.end_m, (lateral_m, 0.0, -lateral_m), lateral_m)

    def _task_measurements(self) -> dict[str, float]:
        ego, other = self.sim.agents[0], self.sim.agents[1]
        return {"tracking_error_m": ego.lateral_m - other.profile(ego.arc_m)}

    def _lane_error(self) -> float:
        return self._m["tracking_error_m"]

    def expert_target_offset(self) -> float:
        """The front car's path, one expert lookahead ahead of the ego."""
        ego, other = self.sim.agents[0], self.sim.agents[1]
        return other.profile(ego.arc_m + EXPERT_LOOKAHEAD_M)
