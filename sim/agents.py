"""Agents of the simulator: state and size, paths generated from the road, and pure pursuit (paper §III-A, §IV-A).

An agent's path is the recorded path (the lane centre) shifted sideways by a lateral offset that varies with arc
length: a constant offset, or for `follow` lane changes at random places. Pure pursuit steers toward the path point
one lookahead distance ahead (the paper's front car: gain 0.8, lookahead 5 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drivesim.sim.dynamics import BicycleState


@dataclass
class LateralProfile:
    """Lateral offset (m, + = left of the recorded path) as a piecewise-linear function of arc length (m)."""

    arc_m: np.ndarray
    offset_m: np.ndarray

    @classmethod
    def constant(cls, offset_m: float) -> LateralProfile:
        """The same offset everywhere."""
        return cls(np.array([0.0]), np.array([float(offset_m)]))

    @classmethod
    def lane_changes(
        cls,
        rng: np.random.Generator,
        start_arc_m: float,
        end_arc_m: float,
        offsets_m: tuple[float, ...],
        first_offset_m: float,
        change_every_m: tuple[float, float] = (20.0, 50.0),
        change_length_m: tuple[float, float] = (15.0, 25.0),
    ) -> LateralProfile:
        """Lane changes at random arc lengths between the given offsets (each change a linear ramp)."""
        arcs, offsets = [start_arc_m], [first_offset_m]
        s, current = start_arc_m, first_offset_m
        while s < end_arc_m:
            s += float(rng.uniform(*change_every_m))
            arcs.append(s)
            offsets.append(current)
            choices = [o for o in offsets_m if o != current] or [current]
            current = float(rng.choice(choices))
            s += float(rng.uniform(*change_length_m))
            arcs.append(s)
            offsets.append(current)
        return cls(np.asarray(arcs), np.asarray(offsets))

    def __call__(self, arc_m: float) -> float:
        """The offset at `arc_m`."""
        return float(np.interp(arc_m, self.arc_m, self.offset_m))


@dataclass
class Agent:
    """One vehicle: bicycle state, footprint size (m), speed set by the task (m/s) and the path it follows."""

    state: BicycleState
    length_m: float
    width_m: float
    target_speed_mps: float
    profile: LateralProfile = field(default_factory=lambda: LateralProfile.constant(0.0))
    frame_index: int = 0
    distance_m: float = 0.0
    arc_m: float = 0.0
    lateral_m: float = 0.0


class ReferencePath:
    """The recorded path as functions of arc length: position, heading and curvature, with lateral offsets."""

    def __init__(self, path: dict[str, np.ndarray]) -> None:
        self.arc_m = np.asarray(path["arc_length_m"], dtype=float)
        self.x_m = np.asarray(path["x_m"], dtype=float)
        self.y_m = np.asarray(path["y_m"], dtype=float)
        self.yaw_rad = np.unwrap(np.asarray(path["yaw_rad"], dtype=float))
        self.curvature_1pm = np.asarray(path["curvature_1pm"], dtype=float)
        self.start_m = float(self.arc_m[0])
        self.end_m = float(self.arc_m[-1])

    def pose(self, arc_m: float, offset_m: float = 0.0) -> tuple[float, float, float]:
        """(x, y, yaw) of the point at `arc_m`, shifted `offset_m` to the left of the path."""
        x = float(np.interp(arc_m, self.arc_m, self.x_m))
        y = float(np.interp(arc_m, self.arc_m, self.y_m))
        yaw = float(np.interp(arc_m, self.arc_m, self.yaw_rad))
        return x - math.sin(yaw) * offset_m, y + math.cos(yaw) * offset_m, yaw

    def curvature(self, arc_m: float) -> float:
        """Road curvature (1/m, + = left) at `arc_m`."""
        return float(np.interp(arc_m, self.arc_m, self.curvature_1pm))

    def _curvatures_along(self, start_m: float, length_m: float) -> np.ndarray:
        """The path's curvature samples in [start, start + length] (1/m), or the one at `start_m` when none is."""
        mask = (self.arc_m >= start_m) & (self.arc_m <= start_m + length_m)
        return self.curvature_1pm[mask] if mask.any() else np.array([self.curvature(start_m)])

    def mean_curvature(self, start_m: float, length_m: float) -> float:
        """Mean signed curvature over [start, start + length] (1/m, + = left)."""
        return float(np.mean(self._curvatures_along(start_m, length_m)))

    def mean_abs_curvature(self, start_m: float, length_m: float) -> float:
        """Mean |curvature| over [start, start + length] (1/m)."""
        return float(np.mean(np.abs(self._curvatures_along(start_m, length_m))))


def pure_pursuit_curvature(
    state: BicycleState, target_x_m: float, target_y_m: float, gain: float = 0.8, lookahead_m: float = 5.0
) -> float:
    """Pure pursuit: the curvature (1/m) of the arc through the target point, scaled by `gain`.

    κ = gain · 2 sin(α) / d, with α the target's bearing in the vehicle frame and d its distance (at least
    `lookahead_m` so a target that fell close does not make the command explode).
    """
    dx, dy = target_x_m - state.x_m, target_y_m - state.y_m
    alpha = math.atan2(dy, dx) - state.yaw_rad
    distance = max(math.hypot(dx, dy), lookahead_m)
    return gain * 2.0 * math.sin(alpha) / distance


def track_arc(reference: ReferencePath, x_m: float, y_m: float, guess_arc_m: float) -> tuple[float, float]:
    """(arc_m, lateral_m) of the point's projection on the reference path, searched near `guess_arc_m`."""
    lo = int(np.searchsorted(reference.arc_m, guess_arc_m - 10.0))
    hi = int(np.searchsorted(reference.arc_m, guess_arc_m + 10.0)) + 1
    lo, hi = max(0, lo), min(len(reference.arc_m), max(hi, lo + 2))
    d2 = (reference.x_m[lo:hi] - x_m) ** 2 + (reference.y_m[lo:hi] - y_m) ** 2
    i = lo + int(np.argmin(d2))
    yaw = reference.yaw_rad[i]
    dx, dy = x_m - reference.x_m[i], y_m - reference.y_m[i]
    along = math.cos(yaw) * dx + math.sin(yaw) * dy
    lateral = -math.sin(yaw) * dx + math.cos(yaw) * dy
    return float(reference.arc_m[i] + along), float(lateral)


def pursue_profile(
    agent: Agent, reference: ReferencePath, arc_m: float, gain: float = 0.8, lookahead_m: float = 5.0
) -> float:
    """The pure-pursuit curvature (1/m) that brings `agent` onto its lateral profile, the target `lookahead_m` ahead."""
    target_arc = arc_m + lookahead_m
    tx, ty, _ = reference.pose(target_arc, agent.profile(target_arc))
    return pure_pursuit_curvature(agent.state, tx, ty, gain, lookahead_m)
