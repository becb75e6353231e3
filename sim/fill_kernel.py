"""The CPU kernel of the view's hole filling: the pull-push fill of `fill.pull_push_fill` for one uint8 view, in one
compiled call (numba).

Why a kernel of our own: OpenCV's inpainting (Telea's fast marching, what the CPU path used before) took 90-200 us per
view at the policy's 160 x 64 even for a few scattered pixels (it sets up whole-image buffers and a priority queue per
call), about 15 % of a simulator step; the same fill as the GPU path's pull-push takes a few tens of microseconds here
and matched Telea's PSNR on the real lateral views (benchmarks/results/stereo.md). The arithmetic is the torch
path's: 2 x 2 averages over the pixels inside the image (avg_pool2d with ceil_mode), bilinear enlargement with
align_corners=False, so both paths fill alike up to float rounding (tests/test_view_fill.py compares them).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _pull(colour: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid level up: 2 x 2 means of colour (h, w, 3) and weight (h, w) over the pixels inside the image."""
    h, w = weight.shape
    hc, wc = (h + 1) // 2, (w + 1) // 2
    c_out = np.zeros((hc, wc, 3), dtype=np.float32)
    w_out = np.zeros((hc, wc), dtype=np.float32)
    for y in range(hc):
        for x in range(wc):
            n = 0
            for yy in range(2 * y, min(2 * y + 2, h)):
                for xx in range(2 * x, min(2 * x + 2, w)):
                    n += 1
                    w_out[y, x] += weight[yy, xx]
                    for k in range(3):
                        c_out[y, x, k] += colour[yy, xx, k]
            inv = np.float32(1.0) / np.float32(n)
            w_out[y, x] *= inv
            for k in range(3):
                c_out[y, x, k] *= inv
    return c_out, w_out


@njit(cache=True, nogil=True)
def _pull_view(rgb: np.ndarray, hole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_pull` of the view itself (colour rgb where seen, 0 in the holes; weight 1 where seen), without making the
    finest level's float arrays."""
    h, w = hole.shape
    hc, wc = (h + 1) // 2, (w + 1) // 2
    c_out = np.zeros((hc, wc, 3), dtype=np.float32)
    w_out = np.zeros((hc, wc), dtype=np.float32)
    count = np.zeros((hc, wc), dtype=np.float32)
    for yy in range(h):
        y = yy // 2
        for xx in range(w):
            x = xx // 2
            count[y, x] += 1.0
            if not hole[yy, xx]:
                w_out[y, x] += 1.0
                c_out[y, x, 0] += np.float32(rgb[yy, xx, 0])
                c_out[y, x, 1] += np.float32(rgb[yy, xx, 1])
                c_out[y, x, 2] += np.float32(rgb[yy, xx, 2])
    for y in range(hc):
        for x in range(wc):
            inv = np.float32(1.0) / count[y, x]
            w_out[y, x] *= inv
            for k in range(3):
                c_out[y, x, k] *= inv
    return c_out, w_out


@njit(cache=True, nogil=True)
def _sources(size_in: int, size_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear source indices and weights of every output index (align_corners=False, as torch's interpolate)."""
    scale = np.float32(size_in) / np.float32(size_out)
    i0 = np.empty(size_out, dtype=np.int64)
    i1 = np.empty(size_out, dtype=np.int64)
    lam = np.empty(size_out, dtype=np.float32)
    for dst in range(size_out):
        src = max((np.float32(dst) + np.float32(0.5)) * scale - np.float32(0.5), np.float32(0.0))
        i0[dst] = min(int(src), size_in - 1)
        i1[dst] = min(i0[dst] + 1, size_in - 1)
        lam[dst] = src - np.float32(i0[dst])
    return i0, i1, lam


@njit(cache=True, nogil=True)
def _push(filled: np.ndarray, colour: np.ndarray, weight: np.ndarray, hole: np.ndarray, out: np.ndarray) -> None:
    """One level down into out (h, w, 3): each pixel keeps its normalized colour `colour` / `weight` in proportion to
    its coverage (at most 1) and takes the coarser level's `filled`, enlarged bilinearly, for the rest. With a
    `hole` mask (the finest level, colour and weight unused), only the hole pixels are written, from `filled` alone
    (coverage 0), rounded to uint8."""
    h, w = out.shape[0], out.shape[1]
    y0s, y1s, lys = _sources(filled.shape[0], h)
    x0s, x1s, lxs = _sources(filled.shape[1], w)
    one = np.float32(1.0)
    finest = hole.shape[0] > 0
    for y in range(h):
        y0, y1, ly = y0s[y], y1s[y], lys[y]
        for x in range(w):
            if finest and not hole[y, x]:
                continue
            x0, x1, lx = x0s[x], x1s[x], lxs[x]
            alpha, inv_w = np.float32(0.0), np.float32(0.0)
            if not finest:
                alpha = min(weight[y, x], one)
                inv_w = np.float32(1.0) / max(weight[y, x], np.float32(1e-6))
            for k in range(3):
                top = filled[y0, x0, k] * (one - lx) + filled[y0, x1, k] * lx
                bottom = filled[y1, x0, k] * (one - lx) + filled[y1, x1, k] * lx
                coarse = top * (one - ly) + bottom * ly
                if not finest:
                    out[y, x, k] = colour[y, x, k] * inv_w * alpha + coarse * (one - alpha)
                else:
                    out[y, x, k] = min(max(coarse + np.float32(0.5), np.float32(0.0)), np.float32(255.0))


@njit(cache=True, nogil=True)
def pull_push_fill_(rgb: np.ndarray, hole: np.ndarray) -> None:
    """Fill the pixels of `hole` (h, w) bool in the uint8 view `rgb` (h, w, 3) in place from the others (pull-push);
    a view with no hole or no seen pixel is left as it is. Only the hole pixels of the finest level are computed
    (the others keep their colour, as the torch path's coverage 1 gives)."""
    h, w = hole.shape
    holes = 0
    for y in range(h):
        for x in range(w):
            holes += hole[y, x]
    if holes == 0 or holes == h * w or min(h, w) <= 1:
        return
    c, wt = _pull_view(rgb, hole)
    colours = [c]
    weights = [wt]
    while min(weights[-1].shape[0], weights[-1].shape[1]) > 1:
        c, wt = _pull(colours[-1], weights[-1])
        colours.append(c)
        weights.append(wt)
    top_w = weights[-1]
    filled = colours[-1].copy()
    for y in range(top_w.shape[0]):
        for x in range(top_w.shape[1]):
            inv_w = np.float32(1.0) / max(top_w[y, x], np.float32(1e-6))
            for k in range(3):
                filled[y, x, k] *= inv_w
    for level in range(len(weights) - 2, -1, -1):
        out = np.empty_like(colours[level])
        _push(filled, colours[level], weights[level], np.zeros((0, 0), dtype=np.bool_), out)
        filled = out
    _push(filled, filled, top_w, hole, rgb)
