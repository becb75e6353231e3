"""Overtake starts that can hardly be won: the front car so close and the closing speed so high that even the hardest
swerve the ego's steering allows does not get its footprint clear of the front car's, or the pass cannot finish before
the road or the time runs out (labelled unwinnable). On the default starts of four worlds 6-8 % are labelled; the
privileged expert succeeds on 7-15 % of them and 95-99.6 % of the others (experiments/winnable): a strong predictor,
not a proof that no driver could win them.

The test looks at the hardest swerve to either side, optimistic for the driver where it simplifies:
- the ego swerves at once (no reaction time, the first step included), the steering angle rising at
  `max_steering_rate_radps` to the angle of `max_curvature_1pm`;
- its heading is held once it reaches a cap: the over-rotation limit `max_rotation_rad` or a shallower one of
  `HEADING_CAPS_RAD` (holding it exactly needs an instant counter-steer);
- the footprints are the env's rectangles (the ego's turned by its heading, so its front corner swings away from
  the car as it turns), compared every `CHECK_EVERY_S`; the swerve escapes when the ego is wholly beside the front
  car without having touched it and with its centre inside the lane limit `max_lateral_m`.
Both cars keep their speeds (the ego only steers); the road's curve where the pass happens is taken as constant
(road coordinates: a swerve to the inside of a bend has less steering to spare, the outside more). A start is also
unwinnable when the ego cannot get past at these speeds before the recorded road or the episode's time runs out
(`pass_fits`). A swerve at full lock is the quickest way sideways, but not provably the only way out, so the label is
checked against the expert (experiments/winnable/bench_winnable.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

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
    pass_distance_m: float = 0.0
    """How far ahead of the front car the ego must get to have passed it (the task's Z_pass)."""
    road_left_m: float = math.inf
    """Recorded road ahead of the ego before the episode ends for the end of the data."""
    time_left_s: float = math.inf
    """Time before the episode's time limit."""
    road_curvature_1pm: float = 0.0
    """The road's curvature where the pass happens (+ = left); both cars start steering with it."""


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
    its heading (its front corner swings away from the car as it turns).

    The swerve is integrated first (`_swerve_checks`), up to the first check that finds the ego beside the car
    (straightening out then only swings its rear further away); the footprints of all its checks are then compared in
    one vectorized call."""
    import shapely

    from drivesim.sim.footprint import footprints

    checks = _swerve_checks(
        start.ego_speed_mps, start.ego_lateral_m, start.ego_yaw_rad, 0.5 * start.ego_length_m,
        0.5 * start.ego_width_m, side * start.other_lateral_m + 0.5 * start.other_width_m, side, horizon_s,
        heading_cap_rad, math.atan(limits.max_curvature_1pm * limits.wheelbase_m), limits.max_steering_rate_radps,
        limits.wheelbase_m, limits.max_lateral_m, start.road_curvature_1pm,
    )  # fmt: skip
    if checks is None:
        return False
    xs, ys, headings, ts = checks
    egos = footprints(xs, ys, headings, start.ego_length_m, start.ego_width_m)
    other_arc_mps = start.other_speed_mps / (1.0 - start.road_curvature_1pm * start.other_lateral_m)
    others = footprints(
        start.gap_m + other_arc_mps * ts, np.full(len(ts), start.other_lateral_m), np.zeros(len(ts)),
        start.other_length_m, start.other_width_m,
    )  # fmt: skip
    return not bool(shapely.intersects(egos, others).any())


@njit(cache=True)
def _swerve_checks(
    speed_mps: float,
    lateral_m: float,
    yaw_rad: float,
    half_length_m: float,
    half_width_m: float,
    clear_of_m: float,
    side: float,
    horizon_s: float,
    heading_cap_rad: float,
    max_steer_rad: float,
    steering_rate_radps: float,
    wheelbase_m: float,
    max_lateral_m: float,
    road_curvature_1pm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The ego's poses (x, y, heading, t arrays) at the checks of `_swerve_clears`'s swerve, up to and with the first
    that has its footprint wholly past `clear_of_m` (the car's side, times `side`); None when the centre leaves the
    lane or the horizon passes first. A compiled loop: the same loop in Python took 1.8 ms per start (8 swerves)."""
    n_max = int(horizon_s / CHECK_EVERY_S) + 2
    xs, ys, hs, ts = np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max)
    n = 0
    # Road coordinates (arc x, lateral y, heading relative to the road) on a road of constant curvature; the steering
    # starts with the road's curve (as the env's start) and turns at its rate to full lock toward `side`.
    x, y, heading, t, since_check = 0.0, lateral_m, yaw_rad, 0.0, np.inf
    steer = max(-max_steer_rad, min(max_steer_rad, np.arctan(road_curvature_1pm * wheelbase_m)))
    lock = side * max_steer_rad
    while t <= horizon_s:
        if since_check >= CHECK_EVERY_S:
            since_check = 0.0
            xs[n], ys[n], hs[n], ts[n] = x, y, heading, t
            n += 1
            # The footprint's lateral extent, as its corners give it: y +- (half_l |sin| + half_w |cos|).
            reach = half_length_m * abs(np.sin(heading)) + half_width_m * abs(np.cos(heading))
            if side * (y - side * reach) > clear_of_m:
                return xs[:n], ys[:n], hs[:n], ts[:n]
        dt = INTEGRATION_STEP_S
        turn = steering_rate_radps * dt
        steer = min(steer + turn, lock) if lock > steer else max(steer - turn, lock)
        stretch = 1.0 - road_curvature_1pm * y  # < 1 on the inside of the bend: less road per metre driven
        if stretch < 0.05:
            return None
        arc_rate = speed_mps * np.cos(heading) / stretch
        heading += (speed_mps * np.tan(steer) / wheelbase_m - road_curvature_1pm * arc_rate) * dt
        heading = max(-heading_cap_rad, min(heading_cap_rad, heading))
        x += arc_rate * dt
        y += speed_mps * np.sin(heading) * dt
        if abs(y) > max_lateral_m:
            return None
        t += dt
        since_check += dt
    return None


def pass_fits(start: OvertakeStart) -> bool:
    """Whether, at the two cars' fixed speeds, the ego can get `pass_distance_m` ahead of the front car before the
    recorded road or the time runs out (optimistic: the swerve's extra length and the return to the lane are free)."""
    closing_mps = start.ego_speed_mps - start.other_speed_mps
    if closing_mps <= 0.0:
        return False
    pass_s = (start.gap_m + start.pass_distance_m) / closing_mps
    return pass_s <= start.time_left_s and start.ego_speed_mps * pass_s <= start.road_left_m


def is_winnable(start: OvertakeStart, limits: SteeringLimits) -> bool:
    """False when the pass cannot be completed in the road and time left (`pass_fits`) or neither hardest swerve
    keeps the ego clear of the front car (the module docstring's test); True otherwise (the start may still be hard)."""
    if not pass_fits(start):
        return False
    closing_mps = start.ego_speed_mps - start.other_speed_mps
    bumper_gap_m = start.gap_m - 0.5 * (start.ego_length_m + start.other_length_m)
    horizon_s = max(bumper_gap_m, 0.0) / closing_mps + (start.ego_length_m + start.other_length_m) / closing_mps
    horizon_s = min(horizon_s, HORIZON_MAX_S)
    caps = [limits.max_rotation_rad, *(c for c in HEADING_CAPS_RAD if c < limits.max_rotation_rad)]
    return any(_swerve_clears(start, limits, side, horizon_s, cap) for cap in caps for side in (1.0, -1.0))
