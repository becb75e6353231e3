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


@njit(cache=True, nogil=True)
def _pull_rows(colour: np.ndarray, weight: np.ndarray, c_out: np.ndarray, w_out: np.ndarray, y0: int, y1: int) -> None:
    """Rows y0..y1 of one pyramid level up: 2 x 2 means of colour (h, w, 3) and weight (h, w) over the pixels inside
    the image, into c_out (hc, wc, 3) and w_out (hc, wc) (every entry written); the sums row by row, each left to
    right."""
    h, w = weight.shape
    quarter = np.float32(0.25)
    for y in range(y0, y1):
        ya, yb = 2 * y, 2 * y + 1
        for x in range(c_out.shape[1]):
            xa, xb = 2 * x, 2 * x + 1
            if yb < h and xb < w:  # a whole block: the general loop's sums, unrolled
                w_out[y, x] = (weight[ya, xa] + weight[ya, xb] + weight[yb, xa] + weight[yb, xb]) * quarter
                for k in range(3):
                    total = colour[ya, xa, k] + colour[ya, xb, k] + colour[yb, xa, k] + colour[yb, xb, k]
                    c_out[y, x, k] = total * quarter
                continue
            n, w_sum = 0, np.float32(0.0)
            r_sum, g_sum, b_sum = np.float32(0.0), np.float32(0.0), np.float32(0.0)
            for yy in range(ya, min(ya + 2, h)):
                for xx in range(xa, min(xa + 2, w)):
                    n += 1
                    w_sum += weight[yy, xx]
                    r_sum += colour[yy, xx, 0]
                    g_sum += colour[yy, xx, 1]
                    b_sum += colour[yy, xx, 2]
            inv = np.float32(1.0) / np.float32(n)
            w_out[y, x] = w_sum * inv
            c_out[y, x, 0], c_out[y, x, 1], c_out[y, x, 2] = r_sum * inv, g_sum * inv, b_sum * inv


@njit(cache=True, nogil=True)
def _pull_view_block(
    rgb: np.ndarray,
    hole: np.ndarray,
    c_out: np.ndarray,
    w_out: np.ndarray,
    sources: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    need: np.ndarray,
    y: int,
    x: int,
) -> None:
    """`_pull_view_rows` for the first level's pixel (y, x) whose block has a hole or lies on the view's edge."""
    h, w = hole.shape
    y0s, y1s, x0s, x1s = sources
    rows, cols = min(2 * y + 2, h) - 2 * y, min(2 * x + 2, w) - 2 * x
    seen, r, g, b = 0, 0, 0, 0
    for yy in range(2 * y, 2 * y + rows):
        for xx in range(2 * x, 2 * x + cols):
            if hole[yy, xx]:
                need[y0s[yy], x0s[xx]] = need[y0s[yy], x1s[xx]] = True
                need[y1s[yy], x0s[xx]] = need[y1s[yy], x1s[xx]] = True
            else:
                seen += 1
                r += np.int32(rgb[yy, xx, 0])
                g += np.int32(rgb[yy, xx, 1])
                b += np.int32(rgb[yy, xx, 2])
    inv = np.float32(1.0) / np.float32(rows * cols)
    w_out[y, x] = np.float32(seen) * inv
    c_out[y, x, 0] = np.float32(r) * inv
    c_out[y, x, 1] = np.float32(g) * inv
    c_out[y, x, 2] = np.float32(b) * inv


@njit(cache=True, nogil=True)
def _pull_view_rows(
    rgb: np.ndarray,
    hole: np.ndarray,
    c_out: np.ndarray,
    w_out: np.ndarray,
    sources: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    need: np.ndarray,
    holed: np.ndarray,
    y0: int,
    y1: int,
) -> int:
    """`_pull_rows` of the view itself (colour rgb where seen, 0 in the holes; weight 1 where seen) for rows y0..y1
    of the first level, without making the finest level's float arrays. Also marks in `need` the first level's
    pixels that the last push reads for the hole pixels among them (`sources`: that push's (y0s, y1s, x0s, x1s)), and
    lists the first level's pixels whose block has a hole (index y * wc + x) in `holed` from y0 * wc on; returns how
    many. The sums are of whole numbers, in integers: exactly the float sums of any order."""
    h, w = hole.shape
    wc = c_out.shape[1]
    quarter = np.float32(0.25)
    count = 0
    for y in range(y0, y1):
        ya, yb = 2 * y, 2 * y + 1
        for x in range(wc):
            xa, xb = 2 * x, 2 * x + 1
            if yb < h and xb < w and not (hole[ya, xa] or hole[ya, xb] or hole[yb, xa] or hole[yb, xb]):
                w_out[y, x] = np.float32(1.0)  # the common case: a whole block, all seen
                for k in range(3):
                    total = np.int32(rgb[ya, xa, k]) + np.int32(rgb[ya, xb, k])
                    total += np.int32(rgb[yb, xa, k]) + np.int32(rgb[yb, xb, k])
                    c_out[y, x, k] = np.float32(total) * quarter
                continue
            _pull_view_block(rgb, hole, c_out, w_out, sources, need, y, x)
            if w_out[y, x] < np.float32(1.0):
                holed[y0 * wc + count] = y * wc + x
                count += 1
    return count


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
def _bilinear(filled: np.ndarray, ya: int, yb: int, ly: np.float32, xa: int, xb: int, lx: np.float32, k: int) -> float:
    """Channel k of the coarser level `filled` (hc, wc, 3) enlarged bilinearly at one pixel (its sources and weights
    from `_sources`)."""
    one = np.float32(1.0)
    top = filled[ya, xa, k] * (one - lx) + filled[ya, xb, k] * lx
    bottom = filled[yb, xa, k] * (one - lx) + filled[yb, xb, k] * lx
    return top * (one - ly) + bottom * ly


@njit(cache=True, nogil=True)
def _mark_coarser(weight: np.ndarray, need: np.ndarray, need_coarser: np.ndarray) -> None:
    """Mark in `need_coarser` the coarser level's pixels that the push of this level's `need` pixels reads: the
    bilinear sources of those not fully covered (coverage below 1; a covered pixel keeps its own colour)."""
    h, w = need.shape
    y0s, y1s, _ = _sources(need_coarser.shape[0], h)
    x0s, x1s, _ = _sources(need_coarser.shape[1], w)
    for y in range(h):
        for x in range(w):
            if need[y, x] and weight[y, x] < np.float32(1.0):
                need_coarser[y0s[y], x0s[x]] = need_coarser[y0s[y], x1s[x]] = True
                need_coarser[y1s[y], x0s[x]] = need_coarser[y1s[y], x1s[x]] = True


@njit(cache=True, nogil=True)
def _push_needed(filled: np.ndarray, colour: np.ndarray, weight: np.ndarray, need: np.ndarray) -> np.ndarray:
    """One level down, at the pixels of `need` only (the others are never read): each keeps its normalized colour
    `colour` / `weight` in proportion to its coverage (at most 1) and takes the coarser level's `filled`, enlarged
    bilinearly, for the rest (not read where the coverage is 1: its share is 0). Returns the level (h, w, 3)."""
    h, w = need.shape
    out = np.empty((h, w, 3), dtype=np.float32)
    y0s, y1s, lys = _sources(filled.shape[0], h)
    x0s, x1s, lxs = _sources(filled.shape[1], w)
    one = np.float32(1.0)
    for y in range(h):
        for x in range(w):
            if not need[y, x]:
                continue
            alpha = min(weight[y, x], one)
            inv_w = one / max(weight[y, x], np.float32(1e-6))
            for k in range(3):
                coarse = np.float32(0.0)
                if alpha < one:
                    coarse = _bilinear(filled, y0s[y], y1s[y], lys[y], x0s[x], x1s[x], lxs[x], k)
                out[y, x, k] = colour[y, x, k] * inv_w * alpha + coarse * (one - alpha)
    return out


@njit(cache=True, nogil=True)
def _push_holes(
    filled: np.ndarray, hole: np.ndarray, rgb: np.ndarray, holed: np.ndarray, start: int, count: int
) -> None:
    """The last push, for the blocks holed[start:start + count] (first-level indices y * wc + x) of the view: each
    hole pixel takes the first level's `filled` enlarged bilinearly, rounded to uint8 (seen pixels keep theirs)."""
    h, w = hole.shape
    wc = filled.shape[1]
    y0s, y1s, lys = _sources(filled.shape[0], h)
    x0s, x1s, lxs = _sources(wc, w)
    for i in range(start, start + count):
        by, bx = holed[i] // wc, holed[i] % wc
        for y in range(2 * by, min(2 * by + 2, h)):
            for x in range(2 * bx, min(2 * bx + 2, w)):
                if hole[y, x]:
                    for k in range(3):
                        coarse = _bilinear(filled, y0s[y], y1s[y], lys[y], x0s[x], x1s[x], lxs[x], k)
                        rgb[y, x, k] = min(max(coarse + np.float32(0.5), np.float32(0.0)), np.float32(255.0))


@njit(cache=True, nogil=True)
def _has_hole_and_seen(hole: np.ndarray, hole_count: int) -> bool:
    """Whether a view with `hole_count` hole pixels has both hole and seen pixels, and a pyramid to fill the one from
    the other."""
    h, w = hole.shape
    return 0 < hole_count < h * w and min(h, w) > 1


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
def _pyramid(h: int, w: int) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Colour (hc, wc, 3) and weight (hc, wc) float32 arrays (not initialized) and False `need` (hc, wc) bool masks
    of the pyramid's levels above an (h, w) view: halved (rounded up) until one side is 1."""
    hc, wc = (h + 1) // 2, (w + 1) // 2
    colours = [np.empty((hc, wc, 3), dtype=np.float32)]  # every entry written by the pull
    weights = [np.empty((hc, wc), dtype=np.float32)]
    needs = [np.zeros((hc, wc), dtype=np.bool_)]
    while min(hc, wc) > 1:
        hc, wc = (hc + 1) // 2, (wc + 1) // 2
        colours.append(np.empty((hc, wc, 3), dtype=np.float32))
        weights.append(np.empty((hc, wc), dtype=np.float32))
        needs.append(np.zeros((hc, wc), dtype=np.bool_))
    return colours, weights, needs


@njit(cache=True, nogil=True)
def _view_sources(level: np.ndarray, hole: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first level's pixels (y0s, y1s, x0s, x1s) that the last push reads for each row and column of the view."""
    y0s, y1s, _ = _sources(level.shape[0], hole.shape[0])
    x0s, x1s, _ = _sources(level.shape[1], hole.shape[1])
    return y0s, y1s, x0s, x1s


@njit(cache=True, nogil=True)
def _push_down(colours: list[np.ndarray], weights: list[np.ndarray], needs: list[np.ndarray]) -> np.ndarray:
    """After the view's pull (the first level's `needs[0]` marked): pull the coarser levels, mark what each level's
    push reads from the next, then push from the coarsest level down to the first, computing only the needed pixels.
    Returns the first level."""
    filled = _pull_coarser(colours, weights)  # first: the marks read each level's coverage
    for level in range(len(weights) - 1):
        _mark_coarser(weights[level], needs[level], needs[level + 1])
    for level in range(len(weights) - 2, -1, -1):
        filled = _push_needed(filled, colours[level], weights[level], needs[level])
    return filled


@njit(cache=True, nogil=True)
def pull_push_fill_(rgb: np.ndarray, hole: np.ndarray, hole_count: int) -> None:
    """Fill the pixels of `hole` (h, w) bool, `hole_count` of them (the caller's count: a pass over the mask less),
    in the uint8 view `rgb` (h, w, 3) in place from the others (pull-push); a view with no hole or no seen pixel is
    left as it is. Each level's push computes only the pixels the next finer
    one reads (the hole pixels' sources, and theirs where a pixel is not fully covered), and the last only the blocks
    with a hole: the same pixels as pushing whole levels, in a fraction of the time when holes are few."""
    if not _has_hole_and_seen(hole, hole_count):
        return
    colours, weights, needs = _pyramid(hole.shape[0], hole.shape[1])
    holed = np.empty(weights[0].size, dtype=np.int64)
    sources = _view_sources(weights[0], hole)
    count = _pull_view_rows(rgb, hole, colours[0], weights[0], sources, needs[0], holed, 0, weights[0].shape[0])
    filled = _push_down(colours, weights, needs)
    _push_holes(filled, hole, rgb, holed, 0, count)


@njit(cache=True, nogil=True, parallel=True)
def pull_push_fill_bands_(rgb: np.ndarray, hole: np.ndarray, hole_count: int, bands: int) -> None:
    """`pull_push_fill_` with the pull of the view and the last push cut into `bands` parts of rows done at the same
    time in numba's threads (the same arithmetic: the same pixels); the coarser levels are small, one thread."""
    if not _has_hole_and_seen(hole, hole_count):
        return
    colours, weights, needs = _pyramid(hole.shape[0], hole.shape[1])
    holed = np.empty(weights[0].size, dtype=np.int64)
    counts = np.zeros(bands, dtype=np.int64)
    sources = _view_sources(weights[0], hole)
    rows, wc = weights[0].shape
    for b in prange(bands):
        # Bands may mark the same pixel of needs[0] (rows at their border): each writes True, nothing else.
        y0, y1 = b * rows // bands, (b + 1) * rows // bands
        counts[b] = _pull_view_rows(rgb, hole, colours[0], weights[0], sources, needs[0], holed, y0, y1)
    filled = _push_down(colours, weights, needs)
    for b in prange(bands):
        _push_holes(filled, hole, rgb, holed, b * rows // bands * wc, counts[b])
