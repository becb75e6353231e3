"""The recorded frame each agent is associated with, as one compiled loop (numba) for `World.closest_frames`.

Why a kernel of our own: a scipy KD-tree query and a dozen numpy operations cost about 40 us for the two agents of an
overtake step, while a loop over every frame of the drive (a few hundred to a few thousand) takes a few microseconds.
`World.closest_frames` keeps the KD-tree for drives with more frames than `BRUTE_FORCE_MAX_FRAMES`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BRUTE_FORCE_MAX_FRAMES = 20_000
"""Drives with more frames than this are searched with the KD-tree (the loop's cost grows with the frame count)."""


@njit(cache=True, nogil=True)
def closest_frames(
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    near_index: np.ndarray,
    path_x_m: np.ndarray,
    path_y_m: np.ndarray,
    path_yaw_rad: np.ndarray,
    arc_m: np.ndarray,
    candidates: int,
    max_arc_gap_m: float,
) -> np.ndarray:
    """For each agent (x_m[b], y_m[b], yaw_rad[b]), the index of its recorded frame: among its `candidates` nearest
    frames (ties by the lower index), the nearest one after a penalty of 1e6 m for a frame heading more than 90
    degrees away and of 1e3 m for one more than `max_arc_gap_m` of arc length from frame near_index[b] (no such
    penalty where near_index[b] < 0); World.closest_frames's rule."""
    n = len(path_x_m)
    k = min(candidates, n)
    best = np.empty(len(x_m), dtype=np.int64)
    top_d = np.empty(k, dtype=np.float64)
    top_i = np.empty(k, dtype=np.int64)
    for b in range(len(x_m)):
        top_d[:] = np.inf
        top_i[:] = -1
        for j in range(n):
            d = np.sqrt((path_x_m[j] - x_m[b]) ** 2 + (path_y_m[j] - y_m[b]) ** 2)
            if d < top_d[k - 1]:
                slot = k - 1
                while slot > 0 and top_d[slot - 1] > d:
                    top_d[slot], top_i[slot] = top_d[slot - 1], top_i[slot - 1]
                    slot -= 1
                top_d[slot], top_i[slot] = d, j
        best_score = np.inf
        best[b] = top_i[0]
        for c in range(k):
            j = top_i[c]
            score = top_d[c]
            heading_gap = abs((yaw_rad[b] - path_yaw_rad[j] + np.pi) % (2 * np.pi) - np.pi)
            if heading_gap > 0.5 * np.pi:
                score += 1e6
            if near_index[b] >= 0 and abs(arc_m[j] - arc_m[near_index[b]]) > max_arc_gap_m:
                score += 1e3
            if score < best_score:
                best_score, best[b] = score, j
    return best
