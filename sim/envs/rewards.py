"""The reward terms of the paper §III-C, each by name; the env's reward is the sum of the weighted terms."""

from __future__ import annotations


def lane_reward(q_lat_m: float, max_lateral_m: float) -> float:
    """R_lane = 1 - (q_lat / Z_lat)^2."""
    return 1.0 - (q_lat_m / max_lateral_m) ** 2


def pass_reward(pass_margin_m: float, pass_distance_m: float) -> float:
    """R_pass = 1 when the ego is at least Z_pass ahead of the front car, else 0."""
    return 1.0 if pass_margin_m >= pass_distance_m else 0.0


def collision_reward(dilated_overlap_frac: float) -> float:
    """R_collision = -|Dilate(P_ego) ∩ P_other| / |P_ego|."""
    return -dilated_overlap_frac


def comfort_reward(steering_accel_radps2: float) -> float:
    """R_comfort = -|δ̈|."""
    return -abs(steering_accel_radps2)
