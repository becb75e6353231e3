"""The rasterizer's CPU kernel: the depth test of every (triangle, pixel) of the triangles' bounding boxes in one
compiled loop (numba), for `raster.Rasterizer` on CPU.

Why a kernel of our own: the torch path expands triangles into (triangle, pixel) pairs and 8 x 8 tiles and
scatters packed keys, a chain of whole-array operations whose fixed costs dominate for the few hundred small
triangles of a car in the policy's region of interest. The loop evaluates the same edge functions in the same
float32 arithmetic (w_i = c_i + a_i x + b_i y from the bbox corner, inside when all w_i >= 0, depth = |det| / sum w,
at or beyond the near plane), and keeps per pixel the nearest depth, then the smallest candidate, as the torch
path's packed key does.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def depth_test(
    table: np.ndarray,
    bbox: np.ndarray,
    camera: np.ndarray,
    width_px: int,
    height_px: int,
    near_m: float,
    depth: np.ndarray,
    winner: np.ndarray,
) -> None:
    """Fill the z-buffer (depth (B*H*W,) float32, +inf initially; winner (B*H*W,) int64, -1 initially) with every
    triangle's covered pixels.

    table (13, n) float32: bbox width, then (a, b, c) of the three edge functions at the bbox corner, |det|, the
    corner x, y; bbox (n, 4) int64 inclusive x0, y0, x1, y1; camera (n,) int64 the camera of each candidate.
    """
    near = np.float32(near_m)
    plane = height_px * width_px
    for t in range(table.shape[1]):
        a0, b0, c0 = table[1, t], table[2, t], table[3, t]
        a1, b1, c1 = table[4, t], table[5, t], table[6, t]
        a2, b2, c2 = table[7, t], table[8, t], table[9, t]
        abs_det = table[10, t]
        x0, y0, x1, y1 = bbox[t, 0], bbox[t, 1], bbox[t, 2], bbox[t, 3]
        base = camera[t] * plane
        for y in range(y0, y1 + 1):
            yo = np.float32(y - y0)
            for x in range(x0, x1 + 1):
                xo = np.float32(x - x0)
                w0 = c0 + a0 * xo + b0 * yo
                w1 = c1 + a1 * xo + b1 * yo
                w2 = c2 + a2 * xo + b2 * yo
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                ssum = w0 + w1 + w2
                if not (ssum > 0 and ssum * near <= abs_det):
                    continue
                z = abs_det / ssum
                p = base + y * width_px + x
                if z < depth[p] or (z == depth[p] and t < winner[p]):
                    depth[p] = z
                    winner[p] = t
