"""drivesim/Overtake-v0: pass a slower front car without collision and return to the lane."""

from __future__ import annotations

import numpy as np

from drivesim.sim.envs.base import DrivingEnv


class OvertakeEnv(DrivingEnv):
    """Overtaking (paper §III-C, §IV-A).

    ## Action and observation spaces
    As drivesim/Lane-v0 (normalized steering curvature; the (3, h, w) uint8 camera region of interest), with the
    front car inserted into the view.

    ## Rewards
    lane = weight_lane · (1 - (q_lat / Z_lat)²); pass = weight_pass · 1[pass_margin_m ≥ Z_pass], where
    pass_margin_m = ∫v_e dt - ∫v_f dt - the start gap (how far the ego is ahead of the front car along the road,
    centre to centre); collision = weight_collision · -|Dilate(P_ego) ∩ P_other| / |P_ego| (ego dilated by 1 m in
    length and 0.4 m in width); comfort = -weight_comfort · |δ̈|.

    ## Start state
    The ego as in Lane-v0 at a speed drawn from ego_speed_mps; the front car front_distance_m ahead and
    front_lateral_m to a random side, heading along the road, at a speed from other_speed_mps, driving with pure
    pursuit (gain 0.8, lookahead 5 m) at its lateral offset.

    ## Episode end
    Success: pass_margin_m > Z_pass = pass_distance_m and |q_lat| < return_lateral_m, without intervention. In
    evaluation the episode is terminated at the success; in training it goes on (R_pass is paid for every step
    ahead) and info["success"] at its end says whether it succeeded and had no intervention since
    (`end_on_success_in_training` ends it at the success instead). Terminated on off_lane, over_rotation, collision
    (undilated overlap > 5 % of the ego's area in training, > 0 % in evaluation) or end_of_data. Truncated:
    time_limit after episode_steps steps.
    """

    task = "overtake"
    has_other = True

    def _speeds(self, rng: np.random.Generator) -> tuple[float, float]:
        c = self.config
        return float(rng.uniform(*c.ego_speed_mps)), float(rng.uniform(*c.other_speed_mps))

    def _success(self, intervention: bool) -> bool:
        m, c = self._m, self.config
        return (not intervention) and m["pass_margin_m"] > c.pass_distance_m and abs(m["q_lat_m"]) < c.return_lateral_m
