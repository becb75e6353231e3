"""The recorded frame each agent is associated with, as one compiled loop (numba) for `World.closest_frames`.

Why a kernel of our own: a scipy KD-tree query and a dozen numpy operations cost about 40 us for the two agents of an
overtake step, while a loop over the drive's frames takes a few microseconds. The loop skips blocks of consecutive
frames whose bounding circle lies beyond the current 8th-nearest frame, so a long drive costs about what a short one
does.
`World.closest_frames` keeps the KD-tree for drives with more frames than `BRUTE_FORCE_MAX_FRAMES`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BRUTE_FORCE_MAX_FRAMES = 20_000
"""Drives with more frames than this are searched with the KD-tree (the loop's cost grows with the frame count)."""


BLOCK_FRAMES = 64
"""Consecutive frames per block of the path; a block farther than an agent's current 8th-nearest frame is skipped."""


def path_blocks(path_x_m: np.ndarray, path_y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each block of `BLOCK_FRAMES` consecutive frames as a bounding circle: centre x, centre y and radius (m)."""
    n = len(path_x_m)
    starts = np.arange(0, n, BLOCK_FRAMES)
    cx = np.add.reduceat(path_x_m, starts) / np.diff(np.append(starts, n))
    cy = np.add.reduceat(path_y_m, starts) / np.diff(np.append(starts, n))
    block = np.arange(n) // BLOCK_FRAMES
    distance = np.hypot(path_x_m - cx[block], path_y_m - cy[block])
    radius = np.maximum.reduceat(distance, starts)
    return cx, cy, radius


@njit(cache=True, nogil=True)
def _scan_block(
    block: int, x: float, y: float, path_x_m: np.ndarray, path_y_m: np.ndarray, top_d: np.ndarray, top_i: np.ndarray
) -> None:
    """Merge the frames of `block` into the sorted top-k (distance, then the lower index on a tie)."""
    k = len(top_d)
    for j in range(block * BLOCK_FRAMES, min(len(path_x_m), (block + 1) * BLOCK_FRAMES)):
        d = np.sqrt((path_x_m[j] - x) ** 2 + (path_y_m[j] - y) ** 2)
        if d < top_d[k - 1] or (d == top_d[k - 1] and j < top_i[k - 1]):
            slot = k - 1
            while slot > 0 and (top_d[slot - 1] > d or (top_d[slot - 1] == d and top_i[slot - 1] > j)):
                top_d[slot], top_i[slot] = top_d[slot - 1], top_i[slot - 1]
                slot -= 1
            top_d[slot], top_i[slot] = d, j


@njit(cache=True, nogil=True)
def _nearest_frames(
    x: float, y: float, path_x_m: np.ndarray, path_y_m: np.ndarray, blocks: tuple, top_d: np.ndarray, top_i: np.ndarray
) -> None:
    """The k nearest frames to (x, y) into top_d / top_i: the nearest block first, then every block whose bounding
    circle can still hold a nearer frame than the current k-th."""
    cx, cy, radius = blocks
    top_d[:] = np.inf
    top_i[:] = -1
    bound = np.empty(len(cx))
    for blk in range(len(cx)):
        bound[blk] = np.sqrt((cx[blk] - x) ** 2 + (cy[blk] - y) ** 2) - radius[blk]
    first = int(np.argmin(bound))
    _scan_block(first, x, y, path_x_m, path_y_m, top_d, top_i)
    for blk in range(len(cx)):
        if blk != first and bound[blk] <= top_d[len(top_d) - 1] + 1e-9:
            _scan_block(blk, x, y, path_x_m, path_y_m, top_d, top_i)


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
    blocks: tuple,
) -> np.ndarray:
    """For each agent (x_m[b], y_m[b], yaw_rad[b]), the index of its recorded frame: among its `candidates` nearest
    frames (ties by the lower index), the nearest one after a penalty of 1e6 m for a frame heading more than 90
    degrees away and of 1e3 m for one more than `max_arc_gap_m` of arc length from frame near_index[b] (no such
    penalty where near_index[b] < 0); World.closest_frames's rule. `blocks`: `path_blocks` of the path."""
    n = len(path_x_m)
    k = min(candidates, n)
    best = np.empty(len(x_m), dtype=np.int64)
    top_d = np.empty(k, dtype=np.float64)
    top_i = np.empty(k, dtype=np.int64)
    for b in range(len(x_m)):
        _nearest_frames(x_m[b], y_m[b], path_x_m, path_y_m, blocks, top_d, top_i)
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
