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
from numba import njit, prange

_NO_HOLE = np.zeros((0, 0), dtype=np.bool_)
"""`_push_rows`'s hole mask for the levels above the view: none (every pixel written)."""


@njit(cache=True, nogil=True)
def _pull_rows(colour: np.ndarray, weight: np.ndarray, c_out: np.ndarray, w_out: np.ndarray, y0: int, y1: int) -> None:
    """Rows y0..y1 of one pyramid level up: 2 x 2 means of colour (h, w, 3) and weight (h, w) over the pixels inside
    the image, into c_out (hc, wc, 3) and w_out (hc, wc) (zeros)."""
    h, w = weight.shape
    for y in range(y0, y1):
        for x in range(c_out.shape[1]):
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


@njit(cache=True, nogil=True)
def _pull_view_rows(rgb: np.ndarray, hole: np.ndarray, c_out: np.ndarray, w_out: np.ndarray, y0: int, y1: int) -> None:
    """`_pull_rows` of the view itself (colour rgb where seen, 0 in the holes; weight 1 where seen), without making
    the finest level's float arrays; the sums in the same order (the two source rows, each left to right)."""
    h, w = hole.shape
    for y in range(y0, y1):
        for yy in range(2 * y, min(2 * y + 2, h)):
            for xx in range(w):
                x = xx // 2
                if not hole[yy, xx]:
                    w_out[y, x] += 1.0
                    c_out[y, x, 0] += np.float32(rgb[yy, xx, 0])
                    c_out[y, x, 1] += np.float32(rgb[yy, xx, 1])
                    c_out[y, x, 2] += np.float32(rgb[yy, xx, 2])
        rows = np.float32(min(2 * y + 2, h) - 2 * y)
        for x in range(c_out.shape[1]):
            inv = np.float32(1.0) / (rows * np.float32(min(2 * x + 2, w) - 2 * x))
            w_out[y, x] *= inv
            for k in range(3):
                c_out[y, x, k] *= inv


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
def _push_rows(
    filled: np.ndarray, colour: np.ndarray, weight: np.ndarray, hole: np.ndarray, out: np.ndarray, y0: int, y1: int
) -> None:
    """Rows y0..y1 of one level down into out (h, w, 3): each pixel keeps its normalized colour `colour` / `weight`
    in proportion to its coverage (at most 1) and takes the coarser level's `filled`, enlarged bilinearly, for the
    rest. With a `hole` mask (the finest level, colour and weight unused), only the hole pixels are written, from
    `filled` alone (coverage 0), rounded to uint8."""
    h, w = out.shape[0], out.shape[1]
    y0s, y1s, lys = _sources(filled.shape[0], h)
    x0s, x1s, lxs = _sources(filled.shape[1], w)
    one = np.float32(1.0)
    finest = hole.shape[0] > 0
    for y in range(y0, y1):
        ya, yb, ly = y0s[y], y1s[y], lys[y]
        for x in range(w):
            if finest and not hole[y, x]:
                continue
            xa, xb, lx = x0s[x], x1s[x], lxs[x]
            alpha, inv_w = np.float32(0.0), np.float32(0.0)
            if not finest:
                alpha = min(weight[y, x], one)
                inv_w = np.float32(1.0) / max(weight[y, x], np.float32(1e-6))
            for k in range(3):
                top = filled[ya, xa, k] * (one - lx) + filled[ya, xb, k] * lx
                bottom = filled[yb, xa, k] * (one - lx) + filled[yb, xb, k] * lx
                coarse = top * (one - ly) + bottom * ly
                if not finest:
                    out[y, x, k] = colour[y, x, k] * inv_w * alpha + coarse * (one - alpha)
                else:
                    out[y, x, k] = min(max(coarse + np.float32(0.5), np.float32(0.0)), np.float32(255.0))


@njit(cache=True, nogil=True)
def _has_hole_and_seen(hole: np.ndarray) -> bool:
    """Whether a view has both hole pixels and seen pixels, and a pyramid to fill the one from the other."""
    h, w = hole.shape
    holes = 0
    for y in range(h):
        for x in range(w):
            holes += hole[y, x]
    return 0 < holes < h * w and min(h, w) > 1


@njit(cache=True, nogil=True)
def _pull_coarser(colours: list[np.ndarray], weights: list[np.ndarray]) -> np.ndarray:
    """Pull every level above the first (filled by the caller) and return the coarsest level's normalized colour
    (colour / weight), where the push starts."""
    for level in range(1, len(weights)):
        _pull_rows(colours[level - 1], weights[level - 1], colours[level], weights[level], 0, weights[level].shape[0])
    filled = colours[-1].copy()
    top = weights[-1]
    for y in range(top.shape[0]):
        for x in range(top.shape[1]):
            inv_w = np.float32(1.0) / max(top[y, x], np.float32(1e-6))
            for k in range(3):
                filled[y, x, k] *= inv_w
    return filled


@njit(cache=True, nogil=True)
def _pyramid(h: int, w: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Zeroed colour (hc, wc, 3) and weight (hc, wc) float32 arrays of the pyramid's levels above an (h, w) view:
    halved (rounded up) until one side is 1."""
    hc, wc = (h + 1) // 2, (w + 1) // 2
    colours = [np.zeros((hc, wc, 3), dtype=np.float32)]
    weights = [np.zeros((hc, wc), dtype=np.float32)]
    while min(hc, wc) > 1:
        hc, wc = (hc + 1) // 2, (wc + 1) // 2
        colours.append(np.zeros((hc, wc, 3), dtype=np.float32))
        weights.append(np.zeros((hc, wc), dtype=np.float32))
    return colours, weights


@njit(cache=True, nogil=True)
def pull_push_fill_(rgb: np.ndarray, hole: np.ndarray) -> None:
    """Fill the pixels of `hole` (h, w) bool in the uint8 view `rgb` (h, w, 3) in place from the others (pull-push);
    a view with no hole or no seen pixel is left as it is. Only the hole pixels of the finest level are computed
    (the others keep their colour, as the torch path's coverage 1 gives)."""
    if not _has_hole_and_seen(hole):
        return
    colours, weights = _pyramid(hole.shape[0], hole.shape[1])
    _pull_view_rows(rgb, hole, colours[0], weights[0], 0, weights[0].shape[0])
    filled = _pull_coarser(colours, weights)
    for level in range(len(weights) - 2, -1, -1):
        out = np.empty_like(colours[level])
        _push_rows(filled, colours[level], weights[level], _NO_HOLE, out, 0, out.shape[0])
        filled = out
    _push_rows(filled, filled, weights[0], hole, rgb, 0, rgb.shape[0])


@njit(cache=True, nogil=True, parallel=True)
def pull_push_fill_bands_(rgb: np.ndarray, hole: np.ndarray, bands: int) -> None:
    """`pull_push_fill_` with each level's rows cut into `bands` parts done at the same time in numba's threads (the
    same arithmetic, row for row: the same pixels)."""
    if not _has_hole_and_seen(hole):
        return
    colours, weights = _pyramid(hole.shape[0], hole.shape[1])
    rows = weights[0].shape[0]
    for b in prange(bands):
        _pull_view_rows(rgb, hole, colours[0], weights[0], b * rows // bands, (b + 1) * rows // bands)
    filled = _pull_coarser(colours, weights)  # the coarser levels are small: one thread
    for level in range(len(weights) - 2, -1, -1):
        out = np.empty_like(colours[level])
        rows = out.shape[0]
        for b in prange(bands):
            _push_rows(
                filled, colours[level], weights[level], _NO_HOLE, out, b * rows // bands, (b + 1) * rows // bands
            )
        filled = out
    rows = rgb.shape[0]
    for b in prange(bands):
        _push_rows(filled, filled, weights[0], hole, rgb, b * rows // bands, (b + 1) * rows // bands)
