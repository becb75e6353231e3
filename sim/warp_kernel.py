"""The forward warp's CPU kernel: transform, z-buffer splat, crack filling and colour gather of one frame in one
compiled pass (numba), for `warp.forward_warp` on CPU tensors.

Why a kernel of our own: the torch path (warp.py) is a chain of whole-array operations (transform, mask, nonzero,
scatter_reduce, shifted minima, gathers), each a pass over memory with its own dispatch cost; at the policy's
resolution (about 10^4 source points per view) those fixed costs dominate and the warp took 3 ms of a 5.7 ms
simulator step. One loop over the points does the same work in a few tens of microseconds. The arithmetic and the
z-buffer order (nearest depth, then smallest source pixel index) are those of the torch path's packed key, so both
give the same image up to float rounding at pixel borders (tests/test_warp.py compares them). The z-buffer is that
packed key too: one int64 per pixel, so a splat is one compare and a crack's fill one minimum over its neighbourhood
(a depth image beside an index image took twice the reads, and the crack filling was half of a 320 x 200 warp).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

EMPTY_KEY = np.int64((0x7F800000 << 32) | 0xFFFFFFFF)
"""An empty z-buffer pixel: depth +inf and the largest index, so that it sorts after every warped point (the torch
path's `_EMPTY_KEY`)."""
_INDEX_MASK = np.int64(0xFFFFFFFF)


@njit(cache=True, nogil=True, error_model="numpy")
def _project_row(
    depth_row: np.ndarray,
    rays_row: tuple[np.ndarray, np.ndarray, np.ndarray],
    near_m: float,
    M: np.ndarray,
    c: np.ndarray,
    size: tuple[int, int, int, int],
    us: np.ndarray,
    vs: np.ndarray,
    depths: np.ndarray,
    drawn: np.ndarray,
) -> None:
    """`splat`'s transform of one run of source pixels (depth_row (n,), their rays' x, y, z (n,) each) into the
    destination region `size` (ex0, ey0, ew, eh): their pixel coordinates us, vs in it, their depth (+inf for sky)
    and whether each is drawn. Branch-free (selects, no per-point test) so that the compiler vectorizes it: numba's
    "numpy" error model lets a division by zero give inf instead of raising (such points are not drawn), which the
    default model's check per division prevented (the transform took 3x longer)."""
    ex0, ey0, ew, eh = size
    off_u, off_v = np.float32(0.5 - ex0), np.float32(0.5 - ey0)
    inf, zero, one, near = np.float32(np.inf), np.float32(0.0), np.float32(1.0), np.float32(near_m)
    ew_f, eh_f = np.float32(ew), np.float32(eh)
    # The transform in locals: the loop writes to arrays, so the compiler cannot keep M's and c's entries in
    # registers by itself (they might alias).
    m00, m01, m02, m10, m11, m12 = M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2]
    m20, m21, m22, c0, c1, c2 = M[2, 0], M[2, 1], M[2, 2], c[0], c[1], c[2]
    rx, ry, rz = rays_row
    for j in range(depth_row.shape[0]):
        z = depth_row[j]
        sky = z == inf  # sky: the ray turns with the camera, no translation (z taken as 1: the ray itself, exactly)
        scale = one if sky else z
        px, py, pz = rx[j] * scale, ry[j] * scale, rz[j] * scale
        # (0 + a) + b is a + b exactly: a sky point's sums are those without the translation.
        qz = (zero if sky else c2) + m20 * px + m21 * py + m22 * pz
        qx = (zero if sky else c0) + m00 * px + m01 * py + m02 * pz
        qy = (zero if sky else c1) + m10 * px + m11 * py + m12 * pz
        inv_z = one / qz
        u = off_u + qx * inv_z
        v = off_v + qy * inv_z
        us[j], vs[j] = u, v
        depths[j] = inf if sky else qz
        # In range (the comparisons also reject NaN); points nearer than near_m are not drawn, sky ahead is.
        drawn[j] = (z > zero) & (qz > (zero if sky else near)) & (u >= zero) & (u < ew_f) & (v >= zero) & (v < eh_f)


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
    keys: np.ndarray,
) -> None:
    """Splat the source pixels of `window` (x0, y0, x1, y1) into the z-buffer `keys` (eh, ew) int64 filled with
    EMPTY_KEY, whose pixel (0, 0) is destination pixel (ex0, ey0). A key packs the float32 depth's bits above the
    source pixel index, as the torch path's does: positive float bits sort like the floats, so the smallest key is the
    nearest point, and of equally near ones the smallest index (one compare per point).

    rays (3, H*W) float32 K_src^-1 [u, v, 1]; depth_src (H*W,) float32 source depth: a point z * ray for z > 0, a
    point at infinity (the ray, rotated only) for +inf, nothing for z <= 0 or NaN; points nearer than near_m to the
    destination camera are not drawn. M (3, 3), c (3,) float32: q = M p + c (c only for finite points). Row by row:
    the transform of the row's pixels (`_project_row`), then their z-test.
    """
    size = (ex0, ey0, keys.shape[1], keys.shape[0])
    n = max(window[2] - window[0], 0)
    us, vs = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32)
    depths, drawn = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.bool_)
    depth_bits = depths.view(np.int32)  # positive float bits sort like the floats
    for sy in range(window[1], window[3]):
        start = sy * width_src + window[0]
        stop = start + n
        rays_row = (rays[0, start:stop], rays[1, start:stop], rays[2, start:stop])
        _project_row(depth_src[start:stop], rays_row, near_m, M, c, size, us, vs, depths, drawn)
        for j in range(n):
            if drawn[j]:
                key = (np.int64(depth_bits[j]) << 32) | (start + j)
                row, col = int(vs[j]), int(us[j])  # in range, int() truncates like floor
                if key < keys[row, col]:
                    keys[row, col] = key


@njit(cache=True, nogil=True)
def fill_cracks(keys: np.ndarray, radius: int) -> np.ndarray:
    """Empty pixels (EMPTY_KEY) with warped pixels on both sides along a row, column or diagonal within r px take
    the nearest surface (the smallest key) of their (2r+1)^2 neighbourhood, for r = 1, then 2, ... `radius`
    (warp._fill_cracks's rule). Changes `keys` in place and returns it."""
    h, w = keys.shape
    # Whether each pixel is warped, with a border of `radius` unwarped pixels so that no look-up needs a bounds test.
    seen = np.zeros((h + 2 * radius, w + 2 * radius), dtype=np.bool_)
    # The empty pixels, listed in the same pass (written always, counted when empty: no branch); each pass visits
    # only those still empty and applies its fills after deciding all of them (a fill never feeds another fill of the
    # same pass, as in the torch path). The pass's own test is the cheapest filter: a pixel inside a large hole fails
    # it at its first look-ups (a distance-to-warped mask computed to skip those cost more than the tests it saved).
    ys = np.empty(h * w, dtype=np.int64)
    xs = np.empty(h * w, dtype=np.int64)
    count = 0
    for y in range(h):
        for x in range(w):
            warped = keys[y, x] != EMPTY_KEY
            seen[y + radius, x + radius] = warped
            ys[count], xs[count] = y, x
            count += not warped
    fill_k = np.empty(count, dtype=np.int64)
    filled = np.zeros(count, dtype=np.bool_)
    for r in range(1, radius + 1):
        for n in range(count):
            y, x = ys[n], xs[n]
            filled[n] = _enclosed(seen, y + radius, x + radius, r)
            if not filled[n]:
                continue
            best = EMPTY_KEY  # empty pixels sort last, so the minimum is the nearest warped one
            for yy in range(max(y - r, 0), min(y + r + 1, h)):
                for xx in range(max(x - r, 0), min(x + r + 1, w)):
                    best = min(best, keys[yy, xx])
            fill_k[n] = best
        kept = 0
        for n in range(count):
            y, x = ys[n], xs[n]
            if filled[n]:
                keys[y, x] = fill_k[n]
                seen[y + radius, x + radius] = True
            else:
                ys[kept], xs[kept] = y, x
                kept += 1
        count = kept
    return keys


@njit(cache=True, nogil=True, inline="always")
def _enclosed(seen: np.ndarray, y: int, x: int, r: int) -> bool:
    """Whether padded pixel (y, x) of `seen` has seen pixels within r px on both sides along its row, its column or
    a diagonal."""
    if r == 1:  # the first pass, over every candidate: the four pairs of opposite neighbours, unrolled
        return (  # bitwise, not short-circuit: eight loads and no branch to mispredict
            (seen[y, x - 1] & seen[y, x + 1])
            | (seen[y - 1, x] & seen[y + 1, x])
            | (seen[y - 1, x - 1] & seen[y + 1, x + 1])
            | (seen[y - 1, x + 1] & seen[y + 1, x - 1])
        )
    for k in range(4):
        dy = 0 if k == 0 else 1
        dx = 1 if k == 0 else (0 if k == 1 else (1 if k == 2 else -1))
        side_a = False
        side_b = False
        for d in range(1, r + 1):
            side_a |= seen[y + d * dy, x + d * dx]
            side_b |= seen[y - d * dy, x - d * dx]
        if side_a and side_b:
            return True
    return False


@njit(cache=True, nogil=True)
def warp_region(
    rays: np.ndarray,
    depth_src: np.ndarray,
    colour: np.ndarray,
    near_m: float,
    M: np.ndarray,
    c: np.ndarray,
    window: np.ndarray,
    width_src: int,
    rendered: np.ndarray,
    roi: np.ndarray,
    radius: int,
    rgb_out: np.ndarray,
    depth_out: np.ndarray,
    valid_out: np.ndarray,
) -> None:
    """One frame's splat, crack filling (`radius` px, 0: none) and colour gather in one call: the z-buffer of the
    rendered region (ex0, ey0, ew, eh) is made here, and its part `roi` (x0, y0, w, h) written to rgb_out (h, w, 3),
    depth_out (h, w) float32 (+inf where empty) and valid_out (h, w) bool. Arguments as `splat`; colour (H*W, 3)."""
    ex0, ey0, ew, eh = rendered[0], rendered[1], rendered[2], rendered[3]
    keys = np.full((eh, ew), EMPTY_KEY, dtype=np.int64)
    splat(rays, depth_src, near_m, M, c, window, width_src, ex0, ey0, keys)
    if radius > 0:
        fill_cracks(keys, radius)
    y0, x0 = roi[1] - ey0, roi[0] - ex0
    depth_bits = depth_out.view(np.int32)  # EMPTY_KEY's upper half is +inf's bits
    for y in range(depth_out.shape[0]):
        for x in range(depth_out.shape[1]):
            key = keys[y0 + y, x0 + x]
            depth_bits[y, x] = np.int32(key >> 32)
            valid_out[y, x] = key != EMPTY_KEY
            i = key & _INDEX_MASK
            for k in range(3):
                rgb_out[y, x, k] = colour[i, k] if key != EMPTY_KEY else 0


@njit(cache=True, nogil=True, parallel=True)
def warp_bands(
    rays: np.ndarray,
    depth_src: np.ndarray,
    colour: np.ndarray,
    near_m: float,
    M: np.ndarray,
    c: np.ndarray,
    windows: np.ndarray,
    width_src: int,
    rendered: np.ndarray,
    rois: np.ndarray,
    radius: int,
    rgb_out: np.ndarray,
    depth_out: np.ndarray,
    valid_out: np.ndarray,
) -> None:
    """`warp_region` of n horizontal bands at the same time, one per thread: band b has its source window
    windows[b], its rendered region rendered[b] and its rows rois[b] (x0, y0, w, h), which land in rows
    rois[b, 1] - rois[0, 1] onwards of the outputs (the whole region's rgb_out, depth_out, valid_out)."""
    for b in prange(rois.shape[0]):
        top = rois[b, 1] - rois[0, 1]
        bottom = top + rois[b, 3]
        warp_region(
            rays, depth_src, colour, near_m, M, c, windows[b], width_src, rendered[b], rois[b], radius,
            rgb_out[top:bottom], depth_out[top:bottom], valid_out[top:bottom],
        )  # fmt: skip


@njit(cache=True, nogil=True)
def source_window(
    min_depth_m: float,
    rays_src: np.ndarray,
    corners_dst: np.ndarray,
    K_src: np.ndarray,
    T_dst_src: np.ndarray,
    width_src: int,
    height_src: int,
) -> np.ndarray:
    """`warp._source_window`'s rectangle (x0, y0, x1, y1) as int64, or (-1, -1, -1, -1) for none, from its constants
    (rays_src (4, 3) of the source image's corners, corners_dst (4, 3) of the destination region's) and the B poses
    T_dst_src (B, 4, 4), float64 throughout: its numpy form took about 20 us per view, mostly per-call costs."""
    none = np.full(4, -1, dtype=np.int64)
    lo_u, lo_v, hi_u, hi_v = np.inf, np.inf, -np.inf, -np.inf
    finite = np.isfinite(min_depth_m)
    for b in range(T_dst_src.shape[0]):
        R, t = T_dst_src[b, :3, :3], T_dst_src[b, :3, 3]
        m = np.inf
        for k in range(4):
            m = min(m, rays_src[k, 0] * R[2, 0] + rays_src[k, 1] * R[2, 1] + rays_src[k, 2] * R[2, 2])
        d_lo = min_depth_m * m + t[2] if finite else np.inf
        if m <= 0 or d_lo < 0.1:
            return none
        for k in range(8):  # the region's corners at d_lo, then its directions (points at infinity)
            c = corners_dst[k % 4]
            q = c * d_lo - t if (finite and k < 4) else c.copy()
            # R^T q: the destination point or ray in the source frame
            x = R[0, 0] * q[0] + R[1, 0] * q[1] + R[2, 0] * q[2]
            y = R[0, 1] * q[0] + R[1, 1] * q[1] + R[2, 1] * q[2]
            z = R[0, 2] * q[0] + R[1, 2] * q[1] + R[2, 2] * q[2]
            if z <= 1e-6:
                return none
            w = K_src[2, 0] * x + K_src[2, 1] * y + K_src[2, 2] * z
            u = (K_src[0, 0] * x + K_src[0, 1] * y + K_src[0, 2] * z) / w
            v = (K_src[1, 0] * x + K_src[1, 1] * y + K_src[1, 2] * z) / w
            lo_u, lo_v, hi_u, hi_v = min(lo_u, u), min(lo_v, v), max(hi_u, u), max(hi_v, v)
    x0, y0 = max(int(np.floor(lo_u)) - 2, 0), max(int(np.floor(lo_v)) - 2, 0)
    x1, y1 = min(int(np.ceil(hi_u)) + 3, width_src), min(int(np.ceil(hi_v)) + 3, height_src)
    out = np.empty(4, dtype=np.int64)
    out[0], out[1], out[2], out[3] = x0, y0, max(x1, x0), max(y1, y0)
    return out
