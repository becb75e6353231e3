"""The forward warp's CPU kernel: transform, z-buffer splat, crack filling and colour gather of one frame in one
compiled pass (numba), for `warp.forward_warp` on CPU tensors.

Why a kernel of our own: the torch path (warp.py) is a chain of whole-array operations (transform, mask, nonzero,
scatter_reduce, shifted minima, gathers), each a pass over memory with its own dispatch cost; at the policy's
resolution (about 10^4 source points per view) those fixed costs dominate and the warp took 3 ms of a 5.7 ms
simulator step. One loop over the points does the same work in a few tens of microseconds. The arithmetic and the
z-buffer order (nearest depth, then smallest source pixel index) are those of the torch path's packed key, so both
give the same image up to float rounding at pixel borders (tests/test_warp.py compares them). The z-buffer here is
a depth image plus a source-index image (-1: empty), which needs no bit casts.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def splat(
    rays: np.ndarray,
    depth_src: np.ndarray,
    near_m: float,
    M: np.ndarray,
    c: np.ndarray,
    window: np.ndarray,
    width_src: int,
    ex0: int,
    ey0: int,
    depth: np.ndarray,
    index: np.ndarray,
) -> None:
    """Splat the source pixels of `window` (x0, y0, x1, y1) into the z-buffer (depth (eh, ew) float32 filled with
    +inf, index (eh, ew) int64 filled with -1), whose pixel (0, 0) is destination pixel (ex0, ey0).

    rays (3, H*W) float32 K_src^-1 [u, v, 1]; depth_src (H*W,) float32 source depth: a point z * ray for z > 0, a
    point at infinity (the ray, rotated only) for +inf, nothing for z <= 0 or NaN; points nearer than near_m to the
    destination camera are not drawn. M (3, 3), c (3,) float32: q = M p + c (c only for finite points).
    """
    eh, ew = depth.shape
    off_u = np.float32(0.5 - ex0)
    off_v = np.float32(0.5 - ey0)
    inf = np.float32(np.inf)
    near = np.float32(near_m)
    for sy in range(window[1], window[3]):
        for sx in range(window[0], window[2]):
            i = sy * width_src + sx
            z = depth_src[i]
            if not z > 0:
                continue
            sky = z == inf
            if sky:
                px, py, pz, f, z_min = rays[0, i], rays[1, i], rays[2, i], np.float32(0.0), np.float32(0.0)
            else:
                px, py, pz, f, z_min = rays[0, i] * z, rays[1, i] * z, rays[2, i] * z, np.float32(1.0), near
            qz = c[2] * f + M[2, 0] * px + M[2, 1] * py + M[2, 2] * pz
            if not qz > z_min:
                continue
            inv_z = np.float32(1.0) / qz
            qx = c[0] * f + M[0, 0] * px + M[0, 1] * py + M[0, 2] * pz
            u = np.floor(off_u + qx * inv_z)
            if not (u >= 0 and u < ew):
                continue
            qy = c[1] * f + M[1, 0] * px + M[1, 1] * py + M[1, 2] * pz
            v = np.floor(off_v + qy * inv_z)
            if not (v >= 0 and v < eh):
                continue
            zd = inf if sky else qz
            row, col = int(v), int(u)
            old_z, old_i = depth[row, col], index[row, col]
            if zd < old_z or (zd == old_z and (old_i < 0 or i < old_i)):
                depth[row, col] = zd
                index[row, col] = i


@njit(cache=True, nogil=True)
def fill_cracks(depth: np.ndarray, index: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Empty pixels (index -1) with warped pixels on both sides along a row, column or diagonal within r px take
    the nearest surface of their (2r+1)^2 neighbourhood, for r = 1, then 2, ... `radius` (warp._fill_cracks's
    rule)."""
    h, w = depth.shape
    for r in range(1, radius + 1):
        out_depth, out_index = depth.copy(), index.copy()
        for y in range(h):
            for x in range(w):
                if index[y, x] >= 0:
                    continue
                enclosed = False
                for k in range(4):
                    dy = 0 if k == 0 else 1
                    dx = 1 if k == 0 else (0 if k == 1 else (1 if k == 2 else -1))
                    side_a = False
                    side_b = False
                    for d in range(1, r + 1):
                        ya, xa, yb, xb = y + d * dy, x + d * dx, y - d * dy, x - d * dx
                        if 0 <= ya < h and 0 <= xa < w and index[ya, xa] >= 0:
                            side_a = True
                        if 0 <= yb < h and 0 <= xb < w and index[yb, xb] >= 0:
                            side_b = True
                    if side_a and side_b:
                        enclosed = True
                        break
                if not enclosed:
                    continue
                best_z, best_i = np.float32(np.inf), np.int64(-1)
                for yy in range(max(y - r, 0), min(y + r + 1, h)):
                    for xx in range(max(x - r, 0), min(x + r + 1, w)):
                        z, i = depth[yy, xx], index[yy, xx]
                        if i >= 0 and (best_i < 0 or z < best_z or (z == best_z and i < best_i)):
                            best_z, best_i = z, i
                out_depth[y, x], out_index[y, x] = best_z, best_i
        depth, index = out_depth, out_index
    return depth, index


@njit(cache=True, nogil=True)
def gather_colour(index: np.ndarray, colour: np.ndarray, y0: int, x0: int, out: np.ndarray) -> None:
    """out (h, w, 3): the colour (colour (H*W, 3), any dtype) of the source pixel of each pixel of the region
    starting at (y0, x0) of the z-buffer's source indices, 0 where empty."""
    h, w = out.shape[0], out.shape[1]
    for y in range(h):
        for x in range(w):
            i = index[y0 + y, x0 + x]
            for k in range(3):
                out[y, x, k] = colour[i, k] if i >= 0 else 0
