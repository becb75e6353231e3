"""Vehicle footprints on the ground plane: polygons, overlap and clearance (paper §III-B, §IV-A).

A vehicle's footprint is the rectangle of its length x width centred on its pose (x, y) and turned by its yaw, in the
world frame (local ENU, metres). shapely does the polygon work, except in an env step, where a compiled kernel of
two rectangles gives the same clearance and overlap without making Polygons (`footprint_kernel.py`): the paper's
collision reward is
`R_collision = -|Dilate(P_ego) ∩ P_other| / |P_ego|` with the ego dilated by 1 m in length and 0.4 m in width
(0.5 m more at each end, 0.2 m more on each side); an intervention in evaluation is any overlap of the undilated
polygons (> 0), and a collision in training an overlap above 5 % of the ego's area.
"""

from __future__ import annotations

import numpy as np
from shapely import Polygon, distance, polygons

from drivesim.sim import footprint_kernel

# The paper's dilation of the ego polygon for R_collision (§IV-A): +1 m in length, +0.4 m in width.
COLLISION_DILATION_LENGTH_M = 1.0
COLLISION_DILATION_WIDTH_M = 0.4


def footprint(x_m: float, y_m: float, yaw_rad: float, length_m: float, width_m: float) -> Polygon:
    """The vehicle's rectangle on the ground, centred on (x, y) and turned by yaw (world frame)."""
    half_l, half_w = 0.5 * length_m, 0.5 * width_m
    corners = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rotated = corners @ np.array([[c, s], [-s, c]])
    return Polygon(rotated + np.array([x_m, y_m]))


def footprint_corners(
    x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, length_m: float, width_m: float
) -> np.ndarray:
    """(n, 4, 2) corners of n rectangles as `footprint` makes them (arrays of n poses, one size)."""
    half_l, half_w = 0.5 * length_m, 0.5 * width_m
    corners = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    x = corners[None, :, 0] * c[:, None] - corners[None, :, 1] * s[:, None] + np.asarray(x_m)[:, None]
    y = corners[None, :, 0] * s[:, None] + corners[None, :, 1] * c[:, None] + np.asarray(y_m)[:, None]
    return np.stack([x, y], axis=-1)


def footprints(x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, length_m: float, width_m: float) -> np.ndarray:
    """`footprint` of n poses at once: an (n,) array of shapely Polygons (made in one call, not one object each)."""
    return polygons(footprint_corners(x_m, y_m, yaw_rad, length_m, width_m))


def clearance_m(a: Polygon, b: Polygon) -> float:
    """The smallest distance between two footprints (0 when they touch or overlap)."""
    return float(distance(a, b))


def collision_overlap(
    ego_pose: tuple[float, float, float],
    ego_size_m: tuple[float, float],
    other_pose: tuple[float, float, float],
    other_size_m: tuple[float, float],
    dilate: bool = True,
) -> float:
    """The paper's collision measure: |Dilate(P_ego) ∩ P_other| / |P_ego| (without dilation when `dilate` is False).

    :param ego_pose: (x_m, y_m, yaw_rad) of the ego. :param ego_size_m: (length_m, width_m) of the ego.
    :param other_pose: the other vehicle's pose. :param other_size_m: its (length_m, width_m).
    """
    length_m, width_m = ego_size_m
    extra_l = COLLISION_DILATION_LENGTH_M if dilate else 0.0
    extra_w = COLLISION_DILATION_WIDTH_M if dilate else 0.0
    ego = footprint_kernel.rectangle(*ego_pose, length_m + extra_l, width_m + extra_w)
    other = footprint_kernel.rectangle(*other_pose, *other_size_m)
    return footprint_kernel.shared_area_m2(ego, other) / (length_m * width_m)


def pose_clearance_m(
    ego_pose: tuple[float, float, float],
    ego_size_m: tuple[float, float],
    other_pose: tuple[float, float, float],
    other_size_m: tuple[float, float],
) -> float:
    """`clearance_m` of two vehicles' footprints given as poses (x_m, y_m, yaw_rad) and sizes (length_m, width_m),
    without making polygons (what an env step measures)."""
    ego = footprint_kernel.rectangle(*ego_pose, *ego_size_m)
    other = footprint_kernel.rectangle(*other_pose, *other_size_m)
    return float(footprint_kernel.distance_m(ego, other))
