"""Two vehicles' rectangles on the ground: their distance and the area they share, compiled (numba).

Why not shapely here, which `footprint.py` uses everywhere else: an env step near the other car measured its clearance
and both overlaps by making shapely Polygons, nearly all of it object creation: the rewards part of a car-drawn
overtake step took 0.05 ms that way and takes 0.02 ms now (benchmarks/results/car_step.md). For two convex
quadrilaterals the same figures are a few dozen lines: the distance is 0 when no separating axis exists among the
four edge normals, else the smallest vertex-to-edge distance; the shared area is one rectangle clipped by the
other's four edges (Sutherland-Hodgman), then the shoelace formula.
tests/test_footprint.py checks both against shapely on random pairs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def rectangle(x_m: float, y_m: float, yaw_rad: float, length_m: float, width_m: float) -> np.ndarray:
    """(4, 2) corners of the rectangle centred on (x, y) and turned by yaw, counter-clockwise, as
    `footprint.footprint` orders them (front left, rear left, rear right, front right)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    half_l, half_w = 0.5 * length_m, 0.5 * width_m
    along = np.array([half_l, -half_l, -half_l, half_l])
    across = np.array([half_w, half_w, -half_w, -half_w])
    out = np.empty((4, 2))
    for k in range(4):
        out[k, 0] = x_m + along[k] * c - across[k] * s
        out[k, 1] = y_m + along[k] * s + across[k] * c
    return out


@njit(cache=True, nogil=True)
def _separated(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether an edge normal of `a` separates the two convex polygons (a gap, not a touch)."""
    n = a.shape[0]
    for i in range(n):
        ex, ey = a[(i + 1) % n, 0] - a[i, 0], a[(i + 1) % n, 1] - a[i, 1]
        nx, ny = ey, -ex  # outward for a counter-clockwise polygon
        limit = nx * a[i, 0] + ny * a[i, 1]
        if _all_beyond(b, nx, ny, limit):
            return True
    return False


@njit(cache=True, nogil=True)
def _all_beyond(points: np.ndarray, nx: float, ny: float, limit: float) -> bool:
    """Whether every point lies strictly beyond the line n . p = limit."""
    for k in range(points.shape[0]):  # noqa: SIM110 (numba compiles no generator expressions)
        if nx * points[k, 0] + ny * points[k, 1] <= limit:
            return False
    return True


@njit(cache=True, nogil=True)
def _point_segment_m(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    """Distance from point p to segment ab."""
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else min(max(((px - ax) * dx + (py - ay) * dy) / length2, 0.0), 1.0)
    return math.hypot(px - (ax + t * dx), py - (ay + t * dy))


@njit(cache=True, nogil=True)
def distance_m(a: np.ndarray, b: np.ndarray) -> float:
    """The smallest distance between two convex counter-clockwise polygons (n, 2): 0 when they touch or overlap."""
    if not (_separated(a, b) or _separated(b, a)):
        return 0.0
    best = np.inf
    for p, q in ((a, b), (b, a)):
        m = q.shape[0]
        for i in range(p.shape[0]):
            for j in range(m):
                d = _point_segment_m(p[i, 0], p[i, 1], q[j, 0], q[j, 1], q[(j + 1) % m, 0], q[(j + 1) % m, 1])
                best = min(best, d)
    return best


@njit(cache=True, nogil=True)
def shared_area_m2(subject: np.ndarray, clip: np.ndarray) -> float:
    """The area of the intersection of two convex counter-clockwise polygons (n, 2) and (m, 2)."""
    poly = subject.copy()
    m = clip.shape[0]
    for j in range(m):
        if poly.shape[0] == 0:
            return 0.0
        ax, ay = clip[j, 0], clip[j, 1]
        ex, ey = clip[(j + 1) % m, 0] - ax, clip[(j + 1) % m, 1] - ay
        n = poly.shape[0]
        out = np.empty((2 * n, 2))
        count = 0
        for i in range(n):
            px, py = poly[i, 0], poly[i, 1]
            qx, qy = poly[(i + 1) % n, 0], poly[(i + 1) % n, 1]
            side_p = ex * (py - ay) - ey * (px - ax)  # >= 0: inside (left of the clip edge)
            side_q = ex * (qy - ay) - ey * (qx - ax)
            if side_p >= 0.0:
                out[count, 0], out[count, 1] = px, py
                count += 1
            if (side_p >= 0.0) != (side_q >= 0.0):
                t = side_p / (side_p - side_q)
                out[count, 0], out[count, 1] = px + t * (qx - px), py + t * (qy - py)
                count += 1
        poly = out[:count]
    area = 0.0
    n = poly.shape[0]
    for i in range(n):
        area += poly[i, 0] * poly[(i + 1) % n, 1] - poly[(i + 1) % n, 0] * poly[i, 1]
    return max(0.5 * area, 0.0)
