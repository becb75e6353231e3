"""The procedural road: a centreline of straights, clothoid transitions and circular arcs, and offsets of it.

Curvature is piecewise linear in arc length (a clothoid's defining property), so heading is its exact integral and
positions follow by integrating (cos, sin) of heading on a fine grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import cumulative_trapezoid

from drivesim.stages.synth.config import RoadConfig

SAMPLE_SPACING_M = 0.25


@dataclass(frozen=True)
class RoadPath:
    """A planar path sampled along its arc length (world ENU, metres, radians; yaw unwrapped, continuous).

    :param arc_length_m: (N,) arc length from the start, strictly increasing.
    :param x_m: (N,) east position.
    :param y_m: (N,) north position.
    :param yaw_rad: (N,) heading of the tangent (counter-clockwise from east).
    :param curvature_1pm: (N,) signed curvature (positive = turning left).
    """

    arc_length_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    curvature_1pm: np.ndarray

    @property
    def length_m(self) -> float:
        """Total arc length."""
        return float(self.arc_length_m[-1])

    def at(self, s_m: np.ndarray | float) -> dict[str, np.ndarray]:
        """Position, heading and curvature at arc length(s) `s_m`, linearly interpolated."""
        s = np.clip(np.asarray(s_m, dtype=float), 0.0, self.length_m)
        return {
            "x_m": np.interp(s, self.arc_length_m, self.x_m),
            "y_m": np.interp(s, self.arc_length_m, self.y_m),
            "yaw_rad": np.interp(s, self.arc_length_m, self.yaw_rad),
            "curvature_1pm": np.interp(s, self.arc_length_m, self.curvature_1pm),
        }

    def offset(self, lateral_m: float) -> RoadPath:
        """The parallel path `lateral_m` to the left (negative = right), re-parametrized by its own arc length."""
        nx, ny = -np.sin(self.yaw_rad), np.cos(self.yaw_rad)
        stretch = 1.0 - lateral_m * self.curvature_1pm
        if np.any(stretch <= 0.0):
            raise ValueError(f"offset {lateral_m} m exceeds the radius of a bend of this path")
        s = np.concatenate([[0.0], cumulative_trapezoid(stretch, self.arc_length_m)])
        return RoadPath(
            arc_length_m=s,
            x_m=self.x_m + lateral_m * nx,
            y_m=self.y_m + lateral_m * ny,
            yaw_rad=self.yaw_rad.copy(),
            curvature_1pm=self.curvature_1pm / stretch,
        )

    def frames(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (N,2), unit tangents (N,2), unit left normals (N,2)) at arc lengths `s_m`."""
        p = self.at(s_m)
        yaw = p["yaw_rad"]
        points = np.stack([p["x_m"], p["y_m"]], axis=-1)
        tangents = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
        normals = np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1)
        return points, tangents, normals


def curvature_profile(cfg: RoadConfig, rng: np.random.Generator, centre_max_curvature_1pm: float) -> np.ndarray:
    """Knots (arc length m, curvature 1/m) of a piecewise-linear curvature profile at least `cfg.length_m` long.

    Straights alternate with bends (clothoid in, arc, clothoid out); a bend turns back toward the start heading
    when the road has drifted more than 45 degrees from it, so long roads wander but do not loop.
    """
    knots = [(0.0, 0.0)]
    s = 0.0
    heading = 0.0
    max_turn = np.deg2rad(cfg.max_heading_change_deg)
    while s < cfg.length_m:
        s += rng.uniform(*cfg.straight_length_m)
        knots.append((s, 0.0))
        if s >= cfg.length_m:
            break
        kappa = rng.uniform(0.35, 1.0) * centre_max_curvature_1pm
        kappa *= -np.sign(heading) if abs(heading) > np.deg2rad(45.0) else rng.choice([-1.0, 1.0])
        transition = rng.uniform(*cfg.transition_length_m)
        arc = rng.uniform(*cfg.arc_length_m)
        # a bend turns by kappa * (arc + transition): cap it so that no single bend exceeds max_turn
        turn = abs(kappa) * (arc + transition)
        if turn > max_turn:
            arc = max(0.0, max_turn / abs(kappa) - transition)
        heading += kappa * (arc + transition)
        knots += [(s + transition, kappa), (s + transition + arc, kappa), (s + 2 * transition + arc, 0.0)]
        s += 2 * transition + arc
    s_end = max(s, cfg.length_m)
    knots.append((s_end + 1e-6, 0.0))
    return np.array(knots)


def build_centreline(cfg: RoadConfig, rng: np.random.Generator, start_yaw_rad: float = 0.0) -> RoadPath:
    """The road centreline, starting at the world origin with heading `start_yaw_rad`.

    Its curvature is bounded so that the right lane centre (the driven path) stays within `cfg.max_curvature_1pm`.
    """
    lane_offset_m = 0.5 * cfg.lane_width_m
    # the inner lane of a bend curves harder: kappa / (1 - d kappa) <= max  <=>  kappa <= max / (1 + d max)
    centre_max = cfg.max_curvature_1pm / (1.0 + lane_offset_m * cfg.max_curvature_1pm)
    knots = curvature_profile(cfg, rng, centre_max)
    n = int(np.ceil(knots[-1, 0] / SAMPLE_SPACING_M)) + 1
    s = np.linspace(0.0, knots[-1, 0], n)
    kappa = np.interp(s, knots[:, 0], knots[:, 1])
    yaw = start_yaw_rad + np.concatenate([[0.0], cumulative_trapezoid(kappa, s)])
    x = np.concatenate([[0.0], cumulative_trapezoid(np.cos(yaw), s)])
    y = np.concatenate([[0.0], cumulative_trapezoid(np.sin(yaw), s)])
    return RoadPath(arc_length_m=s, x_m=x, y_m=y, yaw_rad=yaw, curvature_1pm=kappa)
