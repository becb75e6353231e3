"""Named termination flags (paper §III-C): off lane, over-rotation, collision, end of data."""

from __future__ import annotations


def termination_flags(
    q_lat_m: float,
    q_rot_rad: float,
    overlap_frac: float,
    collision_threshold: float,
    arc_left_m: float,
    max_lateral_m: float,
    max_rotation_rad: float,
    end_margin_m: float,
) -> dict[str, bool]:
    """{"off_lane", "over_rotation", "collision", "end_of_data"} for the current state."""
    return {
        "off_lane": abs(q_lat_m) > max_lateral_m,
        "over_rotation": abs(q_rot_rad) > max_rotation_rad,
        "collision": overlap_frac > collision_threshold,
        "end_of_data": arc_left_m < end_margin_m,
    }
