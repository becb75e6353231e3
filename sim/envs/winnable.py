"""Overtake starts that can hardly be won: the front car so close and the closing speed so high that even the hardest
swerve the ego's steering allows does not get its footprint clear of the front car's (labelled unwinnable). On the
default starts about 5 % are labelled; the privileged expert fails 81 % of them and 2 % of the others
(benchmarks/results/winnable.md): a strong predictor, not a proof that no driver could win them.

The test looks at the hardest swerve to either side, optimistic for the driver where it simplifies:
- the ego swerves at once (no reaction time, the first step included), the steering angle rising at
  `max_steering_rate_radps` to the angle of `max_curvature_1pm`;
- its heading is held once it reaches a cap: the over-rotation limit `max_rotation_rad` or a shallower one of
  `HEADING_CAPS_RAD` (holding it exactly needs an instant counter-steer);
- the footprints are the env's rectangles (the ego's turned by its heading, so its front corner swings away from
  the car as it turns), compared every `CHECK_EVERY_S`; the swerve escapes when the ego is wholly beside the front
  car without having touched it and with its centre inside the lane limit `max_lateral_m`.
Both cars keep their speeds (the ego only steers); the road's own curve is ignored (both cars follow it). A swerve at
full lock is the quickest way sideways, but not provably the only way out, so the label is checked against the
expert (benchmarks/bench_winnable.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

INTEGRATION_STEP_S = 0.005
"""Step of the swerve's integration [s]; 1/20 of the env's step, fine against the 0.1-s decision."""
CHECK_EVERY_S = 0.02
"""How often along the swerve the footprints are compared [s] (the cars close at most 10 m/s: 0.2 m apart)."""
HORIZON_MAX_S = 5.0
"""Longest swerve looked at [s]."""
HEADING_CAPS_RAD = (0.3, 0.2, 0.1)
"""Headings held after the swerve's turn-in, besides the over-rotation limit [rad]: a steep swerve gets sideways
fastest, a shallow one keeps the turned ego narrow where the lane leaves little room."""


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


def _swerve_clears(
    start: OvertakeStart, limits: SteeringLimits, side: float, horizon_s: float, heading_cap_rad: float
) -> bool:
    """Whether the hardest swerve toward `side` (+1 left, -1 right) gets the ego's footprint wholly beside the front
    car's (their lateral extents apart) without the footprints overlapping, the centre leaving the lane or the heading
    passing the over-rotation limit, within `horizon_s`. The footprints are the env's rectangles, the ego's turned by
    its heading (its front corner swings away from the car as it turns)."""
    from drivesim.sim.footprint import footprint

    max_steer_rad = math.atan(limits.max_curvature_1pm * limits.wheelbase_m)
    v = start.ego_speed_mps
    x, y, heading, steer, t, since_check = 0.0, start.ego_lateral_m, start.ego_yaw_rad, 0.0, 0.0, math.inf
    other_half_w = 0.5 * start.other_width_m
    while t <= horizon_s:
        if since_check >= CHECK_EVERY_S:
            since_check = 0.0
            other_x = start.gap_m + start.other_speed_mps * t
            ego = footprint(x, y, heading, start.ego_length_m, start.ego_width_m)
            other = footprint(other_x, start.other_lateral_m, 0.0, start.other_length_m, start.other_width_m)
            if ego.intersects(other):
                return False
            _, min_y, _, max_y = ego.bounds
            if side * (min_y if side > 0 else max_y) > side * start.other_lateral_m + other_half_w:
                return True  # wholly beside it: straightening out only swings the ego's rear further away
        dt = INTEGRATION_STEP_S
        steer = min(steer + limits.max_steering_rate_radps * dt, max_steer_rad)
        heading += side * v * math.tan(steer) / limits.wheelbase_m * dt
        heading = max(-heading_cap_rad, min(heading_cap_rad, heading))
        x += v * math.cos(heading) * dt
        y += v * math.sin(heading) * dt
        if abs(y) > limits.max_lateral_m:
            return False
        t += dt
        since_check += dt
    return False


def is_winnable(start: OvertakeStart, limits: SteeringLimits) -> bool:
    """False when neither hardest swerve keeps the ego clear of the front car (the module docstring's test); True
    otherwise (the start may still be hard)."""
    closing_mps = start.ego_speed_mps - start.other_speed_mps
    if closing_mps <= 0.0:
        return True
    bumper_gap_m = start.gap_m - 0.5 * (start.ego_length_m + start.other_length_m)
    horizon_s = max(bumper_gap_m, 0.0) / closing_mps + (start.ego_length_m + start.other_length_m) / closing_mps
    horizon_s = min(horizon_s, HORIZON_MAX_S)
    caps = [limits.max_rotation_rad, *(c for c in HEADING_CAPS_RAD if c < limits.max_rotation_rad)]
    return any(_swerve_clears(start, limits, side, horizon_s, cap) for cap in caps for side in (1.0, -1.0))
