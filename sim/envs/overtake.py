"""drivesim/Overtake-v0: pass a slower front car without collision and return to the lane."""

from __future__ import annotations

from typing import Any

import numpy as np

from drivesim.sim.envs.base import DrivingEnv
from drivesim.sim.envs.config import OTHER_CAR_KEYS, EnvConfig
from drivesim.sim.envs.expert import EXPERT_CLEARANCE_M
from drivesim.sim.envs.rewards import pass_reward
from drivesim.sim.envs.winnable import OvertakeStart, SteeringLimits, is_winnable

MAX_REDRAWS = 100
"""Most redraws of an unwinnable start with `redraw_unwinnable`."""

SCENARIOS: tuple[dict[str, dict[str, Any]], ...] = (
    {"static": {"other_speed_mps": (0.0, 0.0)}, "dynamic": {"other_speed_mps": (1.0, 4.0)}},
    {"pass-left": {"front_side": "right"}, "pass-right": {"front_side": "left"}},
)
"""The paper's Table II scenarios as env settings: the front car static or moving; the ego passing on its left or
right (the front car on the other side). One of each group at most."""


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
    pursuit (gain 0.8, lookahead 5 m) at its lateral offset. info["episode"]["winnable"] is False for a start
    the hardest swerve cannot escape (sim/envs/winnable.py); with `redraw_unwinnable` such a start is drawn again
    from the same generator (the same seed, the same episode; info["episode"]["redraws"] counts the draws discarded).

    ## Episode end
    Success: pass_margin_m > Z_pass = pass_distance_m and |q_lat| < return_lateral_m, without intervention. In
    evaluation the episode is terminated at the success; in training it goes on (R_pass is paid for every step
    ahead) and info["success"] at its end says whether it succeeded and had no intervention since
    (`end_on_success_in_training` ends it at the success instead). Terminated on off_lane, over_rotation, collision
    (undilated overlap above collision_overlap_train of the ego's area in training, collision_overlap_eval in
    evaluation: any overlap in both by default) or end_of_data. Truncated:
    time_limit after episode_steps steps.

    ## Evaluation extras
    info["state"]["pass_margin_m"]; info["episode"]["winnable"] (the report's winnable / unwinnable table); the
    Table II scenarios (`scenarios()`: static or dynamic front car, pass-left or pass-right).
    """

    task = "overtake"
    has_other = True
    task_keys = (
        *OTHER_CAR_KEYS, "other_speed_mps", "pass_distance_m", "return_lateral_m", "weight_pass",
        "redraw_unwinnable", "end_on_success_in_training",
    )  # fmt: skip

    @classmethod
    def default_config(cls) -> EnvConfig:
        """The base's, with a dilated-overlap penalty of 50 (a margin worth keeping before any overlap ends the
        episode) and a third of the training episodes in grey."""
        return super().default_config().model_copy(update={"weight_collision": 50.0, "grey_probability": 0.3})

    @classmethod
    def scenarios(cls) -> tuple[dict[str, dict[str, Any]], ...]:
        return SCENARIOS

    def reset_state(self, seed: int | None) -> None:
        """Draw the start state; label it winnable or not, and redraw an unwinnable one when the config says so."""
        super().reset_state(seed)
        redraws = 0
        while self.config.redraw_unwinnable and not self._start_winnable() and redraws < MAX_REDRAWS:
            super().reset_state(None)  # the generator goes on: still one episode per seed
            redraws += 1
        self._seed = seed
        self._episode["seed"] = seed
        self._episode["winnable"] = self._start_winnable()
        if redraws:
            self._episode["redraws"] = redraws

    def _start_winnable(self) -> bool:
        c, ep, ego = self.config, self._episode, self.sim.agents[0]
        start = OvertakeStart(
            gap_m=self._gap_m,
            ego_speed_mps=ep["ego_speed_mps"],
            other_speed_mps=ep["other_speed_mps"],
            ego_lateral_m=ego.lateral_m,
            ego_yaw_rad=self._m["q_rot_rad"],
            other_lateral_m=self._other_lateral_m,
            ego_length_m=ep["ego_length_m"],
            ego_width_m=ep["ego_width_m"],
            other_length_m=ep["other_length_m"],
            other_width_m=ep["other_width_m"],
            pass_distance_m=c.pass_distance_m,
            road_left_m=self.sim.reference.end_m - c.end_margin_m - ego.arc_m,
            time_left_s=c.episode_steps * c.dt_s,
            road_curvature_1pm=self.sim.reference.mean_curvature(ego.arc_m, self._gap_m),
        )
        limits = SteeringLimits(
            c.wheelbase_m, c.max_curvature_1pm, c.max_steering_rate_radps, c.max_rotation_rad, c.max_lateral_m
        )
        return is_winnable(start, limits)

    def _task_measurements(self) -> dict[str, float]:
        ego, other = self.sim.agents[0], self.sim.agents[1]
        return {"pass_margin_m": ego.distance_m - other.distance_m - self._gap_m}

    def _reward_terms(self, steering_accel_radps2: float) -> dict[str, float]:
        """The base's terms and pass = weight_pass · R_pass, in the order lane, pass, collision, comfort."""
        terms = super()._reward_terms(steering_accel_radps2)
        c = self.config
        passed = c.weight_pass * pass_reward(self._m["pass_margin_m"], c.pass_distance_m)
        return {"lane": terms.pop("lane"), "pass": passed, **terms}

    def _success_now(self, intervention: bool) -> bool:
        m, c = self._m, self.config
        return (not intervention) and m["pass_margin_m"] > c.pass_distance_m and abs(m["q_lat_m"]) < c.return_lateral_m

    def _ends_at_success(self) -> bool:
        return self.mode == "eval" or self.config.end_on_success_in_training

    def _episode_success(self, ended: bool, intervention: bool, succeeded_now: bool) -> bool:
        if self._ends_at_success():
            return succeeded_now
        # A training episode that went on after the pass: it succeeded if it passed and had no intervention since.
        return self._succeeded and ended and not intervention

    def expert_target_offset(self) -> float:
        """Swerve to the side of the front car with more room, keeping EXPERT_CLEARANCE_M between the footprints,
        until the ego is Z_pass ahead; then back to the lane centre."""
        c, sim = self.config, self.sim
        if self._m["pass_margin_m"] >= c.pass_distance_m:
            return 0.0
        ego, other = sim.agents[0], sim.agents[1]
        half_widths = 0.5 * (ego.width_m + other.width_m) + EXPERT_CLEARANCE_M
        o = other.lateral_m
        limit = c.max_lateral_m - 0.5
        target = o - half_widths if o >= 0.0 else o + half_widths
        return float(np.clip(target, -limit, limit))
