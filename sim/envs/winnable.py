"""Overtake starts no driver can survive: the front car so close and the closing speed so high that even the hardest
swerve the ego's steering allows cannot get its footprint clear of the front car's before the bumpers meet.

The test is deliberately optimistic for the driver, so a start it calls unwinnable is one no policy can win:
- the ego swerves at once (no reaction time, the first step included) toward either side, the steering angle
  rising at `max_steering_rate_radps` to the angle of `max_curvature_1pm`;
- its heading is held at the over-rotation limit `max_rotation_rad` once it gets there (a real car would need to
  counter-steer earlier);
- the footprints are compared by their lateral extents alone (a yawed ego is wider than its width);
- a side is possible when the ego's centre stays within the lane limit `max_lateral_m` there.
Both cars keep their speeds (the ego only steers); the road's own curve is ignored (both cars follow it).
Contact can happen only once the bumper gap, front distance minus half of each length, has closed at the closing
speed; by then the ego must be at least half of the two widths away from the front car's lateral offset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

INTEGRATION_STEP_S = 0.005
"""Step of the swerve's integration [s]; 1/20 of the env's step, fine against the 0.1-s decision."""


@dataclass(frozen=True)
class OvertakeStart:
    """The start of an overtake episode, in road coordinates (lateral + = left), metres, m/s and radians."""

    gap_m: float
    """Front car's distance ahead of the ego along the road, centre to centre."""
    ego_speed_mps: float
    other_speed_mps: float
    ego_lateral_m: float
    ego_yaw_rad: float
    """The ego's heading relative to the road."""
    other_lateral_m: float
    ego_length_m: float
    ego_width_m: float
    other_length_m: float
    other_width_m: float


@dataclass(frozen=True)
class SteeringLimits:
    """What any driver of the ego is held to (the env config's values)."""

    wheelbase_m: float
    max_curvature_1pm: float
    max_steering_rate_radps: float
    max_rotation_rad: float
    max_lateral_m: float


def time_to_contact_s(start: OvertakeStart) -> float:
    """Seconds until the bumpers meet at constant speeds (0 when they overlap already, inf when not closing)."""
    bumper_gap_m = start.gap_m - 0.5 * (start.ego_length_m + start.other_length_m)
    closing_mps = start.ego_speed_mps - start.other_speed_mps
    if bumper_gap_m <= 0.0:
        return 0.0
    return math.inf if closing_mps <= 0.0 else bumper_gap_m / closing_mps


def best_swerve_m(start: OvertakeStart, limits: SteeringLimits, side: float, duration_s: float) -> float:
    """The farthest lateral position toward `side` (+1 left, -1 right) the ego reaches within `duration_s`
    under the limits (the module docstring's optimistic swerve)."""
    max_steer_rad = math.atan(limits.max_curvature_1pm * limits.wheelbase_m)
    v = start.ego_speed_mps
    y, heading, steer, t = start.ego_lateral_m, start.ego_yaw_rad, 0.0, 0.0
    farthest = side * y
    while t < duration_s:
        dt = min(INTEGRATION_STEP_S, duration_s - t)
        steer = min(steer + limits.max_steering_rate_radps * dt, max_steer_rad)
        heading += side * v * math.tan(steer) / limits.wheelbase_m * dt
        heading = max(-limits.max_rotation_rad, min(limits.max_rotation_rad, heading))
        y += v * math.sin(heading) * dt
        t += dt
        farthest = max(farthest, side * y)
    return side * farthest


def is_winnable(start: OvertakeStart, limits: SteeringLimits) -> bool:
    """False when no steering within the limits keeps the ego clear of the front car (the module docstring's test);
    True otherwise (the start may still be hard)."""
    half_widths_m = 0.5 * (start.ego_width_m + start.other_width_m)
    if abs(start.ego_lateral_m - start.other_lateral_m) >= half_widths_m:
        return True  # already beside it
    contact_s = time_to_contact_s(start)
    if math.isinf(contact_s):
        return True
    for side in (1.0, -1.0):
        clear_at_m = start.other_lateral_m + side * half_widths_m  # the ego's centre must get past this
        if abs(clear_at_m) > limits.max_lateral_m:
            continue  # off the lane before it is clear on this side
        if side * (best_swerve_m(start, limits, side, contact_s) - clear_at_m) >= 0.0:
            return True
    return False
