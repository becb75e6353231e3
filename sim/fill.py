"""No black in the policy's view (issue 20): fill what the recorded frame's warp leaves empty.

A forward warp of one recorded frame leaves two kinds of hole: wedges along the image sides where the agent looks past
what the camera saw (lateral offset, rotation), and disocclusions behind poles and trees. They are filled in up to
three steps:
1. once per recorded frame, when the simulator prepares it: the frame is widened by a margin on its left and right,
   filled from its neighbouring frames (`widen_frame`; `ViewConfig.source_margin`, `margin_frames`); the view's own
   warp then carries recorded data into most of the side wedges, at the cost of a wider source only;
2. an option, per view (`ViewConfig.fill_frames`, off by default): neighbouring recorded frames are warped into the
   side wedges' bounding boxes (the holes joined to an image side, `side_wedges`) and merged by depth and visibility
   (`fill_wedges_from_neighbours`): it reaches some disocclusions too, but warps up to three more frames per step;
3. what no frame saw is inpainted (`inpaint_holes`, a pull-push fill): smooth continuation of the border colours,
   with depth +inf (so an inserted car is drawn over it).

On a GPU the views are filled as one batch: step 1 as on the CPU (the widened frames are the device's frame stack),
step 2 not at all, and step 3 is the same pull-push fill as torch operations over the batch (`pull_push_fill`: each
hole pixel takes the normalized average of the seen pixels at the finest level of an image pyramid that has any,
blended across levels); the CPU's is a compiled loop of the same arithmetic (`fill_kernel.py`).

`FillStats` counts, per view, how many pixels each step filled, so a benchmark can say how much of the view is real
recorded data, neighbour data, or invented; what step 1 brings counts as the view's own frame (a benchmark that
wants it apart renders the same poses with `source_margin=0`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn.functional import avg_pool2d, interpolate

from drivesim.sim import fill_kernel
from drivesim.sim.cpu_threads import parallel_slot
from drivesim.sim.warp import forward_warp

__all__ = [
    "FillStats",
    "WideFrame",
    "fill_wedges_from_neighbours",
    "hole_box",
    "inpaint_holes",
    "merge_into_holes",
    "pull_push_fill",
    "side_wedges",
    "widen_frame",
]

WEDGE_MIN_PX = 24
"""Side wedges of fewer pixels than this are left to inpainting (no neighbour warp for them)."""
NEIGHBOUR_MIN_GAIN = 0.1
"""A neighbour frame that fills less than this fraction of a wedge still open ends the search for that wedge (what is
left no nearby frame saw: a wedge turned past the recorded field of view)."""

Box = tuple[int, int, int, int]
"""(x0, y0, w, h) of an image region, pixels."""
NeighbourWarp = Callable[[int, Box], "tuple[np.ndarray, np.ndarray, np.ndarray] | None"]
"""(frame offset, box) -> that neighbour frame's warp of the box (rgb (h, w, 3) uint8, depth (h, w), valid (h, w)
bool), or None when there is no such frame."""


@dataclass
class FillStats:
    """Pixels of one or more views by where their colour came from.

    :param total_px: all pixels. :param frame_px: from the view's own recorded frame (warp and crack filling).
    :param neighbour_px: from a neighbouring recorded frame. :param inpainted_px: invented by inpainting.
    """

    total_px: int = 0
    frame_px: int = 0
    neighbour_px: int = 0
    inpainted_px: int = 0

    def add(self, other: FillStats) -> None:
        """Accumulate another view's counts."""
        self.total_px += other.total_px
        self.frame_px += other.frame_px
        self.neighbour_px += other.neighbour_px
        self.inpainted_px += other.inpainted_px

    def fractions(self) -> dict[str, float]:
        """The counts as fractions of all pixels (keys frame, neighbour, inpainted, unfilled)."""
        n = max(self.total_px, 1)
        return {
            "frame": self.frame_px / n,
            "neighbour": self.neighbour_px / n,
            "inpainted": self.inpainted_px / n,
            "unfilled": (self.total_px - self.frame_px - self.neighbour_px - self.inpainted_px) / n,
        }


def hole_box(valid: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, w, h) bounding box of the False pixels of `valid` (h, w) bool, or None when there are none."""
    rows = np.flatnonzero(~valid.all(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(~valid[rows[0] : rows[-1] + 1].all(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


def side_wedges(valid: np.ndarray, min_px: int = WEDGE_MIN_PX) -> list[Box]:
    """Bounding boxes (x0, y0, w, h) of the side wedges of a view whose seen pixels are `valid` (h, w) bool: the
    unseen pixels left of the first seen pixel of their row (left wedge), right of the last (right wedge), and in the
    same way above and below the seen pixels of their column (top and bottom wedges); a row or column with no seen
    pixel belongs to both of its wedges. Order: left, right, top, bottom; wedges of fewer than `min_px` pixels are
    left out."""
    H, W = valid.shape
    boxes = []
    for (before, after), transposed in ((_outside_seen(valid), False), (_outside_seen(valid.T), True)):
        n = H if transposed else W
        for width_px, from_start in ((before, True), (after, False)):
            lines = np.flatnonzero(width_px > 0)
            if lines.size == 0 or int(width_px.sum()) < min_px:
                continue
            w = int(width_px.max())
            start, first, count = (0 if from_start else n - w), int(lines[0]), int(lines[-1] - lines[0] + 1)
            boxes.append((first, start, count, w) if transposed else (start, first, w, count))
    return boxes


def _outside_seen(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of `valid` (h, w) bool: how many unseen pixels precede its first seen pixel and follow its last (all
    w for a row with none)."""
    W = valid.shape[1]
    any_seen = valid.any(axis=1)
    before = np.where(any_seen, np.argmax(valid, axis=1), W)
    after = np.where(any_seen, np.argmax(valid[:, ::-1], axis=1), W)
    return before, after


def fill_wedges_from_neighbours(
    rgb: np.ndarray, depth_m: np.ndarray, valid: np.ndarray, offsets: Sequence[int], warp: NeighbourWarp
) -> tuple[np.ndarray, int]:
    """Fill the side wedges of a view in place from neighbouring recorded frames: for each wedge, the frames at
    `offsets` (in order) are warped into its box by `warp` and merged by depth (`merge_into_holes`), until the wedge
    is closed or a frame adds less than NEIGHBOUR_MIN_GAIN of what is open (pixels given up on are not searched again
    for another wedge they are in). Returns the (h, w) bool mask of the pixels filled this way and their count.

    :param rgb, depth_m, valid: the view's own warp (rgb and depth changed in place).
    """
    hole, filled = ~valid, np.zeros_like(valid)
    if not offsets:
        return filled, 0
    tried = np.zeros_like(valid)  # hole pixels a wedge's search already gave up on (a corner is in two wedges)
    total = 0
    for wedge in side_wedges(valid):
        box = _open_box(hole, filled | tried, wedge)
        open_px = 0 if box is None else int(np.count_nonzero(_cut(hole, box) & ~_cut(filled, box)))
        for offset in offsets if box is not None else ():
            other = warp(offset, box)
            if other is None:
                continue
            newly = merge_into_holes(rgb, depth_m, hole, filled, box, *other)
            total += newly
            open_px -= newly
            if newly < NEIGHBOUR_MIN_GAIN * (open_px + newly):
                break
            box = _open_box(hole, filled | tried, box)
            if box is None:
                break
        _cut(tried, wedge)[...] |= _cut(hole, wedge) & ~_cut(filled, wedge)
    return filled, total


def _cut(image: np.ndarray, box: Box) -> np.ndarray:
    """The part of `image` inside `box` (a view, not a copy)."""
    x0, y0, w, h = box
    return image[y0 : y0 + h, x0 : x0 + w]


def _open_box(hole: np.ndarray, closed: np.ndarray, box: Box) -> Box | None:
    """The bounding box of the hole pixels not `closed` (filled, or given up on) inside `box`, in image coordinates;
    None when there is none."""
    inner = hole_box(~_cut(hole, box) | _cut(closed, box))
    return None if inner is None else (inner[0] + box[0], inner[1] + box[1], inner[2], inner[3])


def merge_into_holes(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    hole: np.ndarray,
    filled: np.ndarray,
    box: tuple[int, int, int, int],
    other_rgb: np.ndarray,
    other_depth_m: np.ndarray,
    other_valid: np.ndarray,
) -> int:
    """Fill the holes of a view in place from another frame's warp of the box `box` (x0, y0, w, h) of it: a hole
    pixel takes the other warp's colour and depth where that warp has a surface there and the pixel is still unfilled
    or holds a farther surface (a z-buffer over the neighbours). Returns how many hole pixels were newly filled.

    :param rgb, depth_m: the view (h, w, 3) uint8 and (h, w) float32, changed in place.
    :param hole: (h, w) bool, the pixels the view's own frame left empty. :param filled: (h, w) bool, the hole pixels
        filled so far, updated in place. :param other_rgb, other_depth_m, other_valid: the other warp of the box.
    """
    x0, y0, w, h = box
    region = (slice(y0, y0 + h), slice(x0, x0 + w))
    was_filled = filled[region]
    take = hole[region] & other_valid & (~was_filled | (other_depth_m < depth_m[region]))
    newly = int(np.count_nonzero(take & ~was_filled))
    rgb[region][take] = other_rgb[take]
    depth_m[region][take] = other_depth_m[take]
    was_filled |= take
    return newly


def inpaint_holes(rgb: np.ndarray, hole: np.ndarray, threads: int = 1) -> int:
    """Inpaint the pixels of `hole` (h, w) bool in the uint8 view `rgb` (h, w, 3) in place; returns how many there
    were. The pull-push fill of `pull_push_fill` (the GPU path's) in one compiled call (`fill_kernel.py`), its rows
    shared among `threads` threads (the same pixels): smooth continuation of the colours around each hole, small or a
    whole side wedge. A view that is all hole stays as it is (black)."""
    count = int(np.count_nonzero(hole))
    if 0 < count < hole.size:
        with parallel_slot(threads) as granted:
            if granted > 1:
                fill_kernel.pull_push_fill_bands_(rgb, hole, count, granted)
            else:
                fill_kernel.pull_push_fill_(rgb, hole, count)
    return count


def pull_push_fill(rgb: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Views (B, h, w, 3) uint8 with every pixel where `valid` (B, h, w) is False filled from the seen pixels around
    it, all views at once on their device: the pull-push fill of Gortler et al. (1996). Pull: a pyramid of
    2x2 averages of colour and coverage; push: from the coarsest level down, each level's pixels keep their own
    normalized colour in proportion to their coverage and take the coarser level's (bilinear) for the rest. A view
    with no seen pixel stays as it is. We write it (about twenty lines of torch) because OpenCV's inpainting runs one
    view at a time on the CPU; `inpaint_holes` is the same fill for one view on the CPU."""
    if bool(valid.all()):
        return rgb
    weight = valid[:, None].to(torch.float32)
    colour = rgb.permute(0, 3, 1, 2).to(torch.float32) * weight
    levels = [(colour, weight)]
    while min(levels[-1][1].shape[-2:]) > 1:
        c, w = levels[-1]
        levels.append((avg_pool2d(c, 2, ceil_mode=True), avg_pool2d(w, 2, ceil_mode=True)))
    c, w = levels[-1]
    filled = c / w.clamp(min=1e-6)
    for c, w in reversed(levels[:-1]):
        coarse = interpolate(filled, size=c.shape[-2:], mode="bilinear", align_corners=False)
        alpha = w.clamp(max=1.0)
        filled = c / w.clamp(min=1e-6) * alpha + coarse * (1.0 - alpha)
    out = filled.add_(0.5).clamp_(0, 255).to(torch.uint8).permute(0, 2, 3, 1)
    return torch.where(valid[..., None], rgb, out)


@dataclass
class WideFrame:
    """A recorded frame widened by margins on its left and right that neighbouring frames fill (`widen_frame`).

    :param rgb: (h, w + 2 margin_px, 3) uint8. :param depth_m: (h, w + 2 margin_px) float32, 0 where no frame saw
        (no data: never warped), +inf for sky. :param K: intrinsics of the widened image (principal point moved right
        by margin_px). :param margin_px: width of each margin. :param neighbour_px: margin pixels the neighbours filled.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    K: np.ndarray
    margin_px: int
    neighbour_px: int


def widen_frame(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    margin_px: int,
    neighbours: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> WideFrame:
    """The frame `rgb` (h, w, 3) uint8 / `depth_m` (h, w) with intrinsics `K`, widened by `margin_px` on each side,
    the margins filled from neighbouring recorded frames: each (rgb_j, depth_j, T_this_other) in `neighbours` (the
    other frame's camera to this one's, 4 x 4), in order, is warped into the margins and fills the pixels the ones
    before it left empty. A view that looks past the frame's sides then warps recorded data there with the frame's
    own warp, at no cost per view but a wider source.

    Why once per frame and not per view (`fill_wedges_from_neighbours`): the neighbours are merged in the frame's own
    camera when it is prepared, instead of being warped again at every step (per view, frames -1, +1, -2 cost 3.0x
    the warp alone per follow step, benchmarks/results/view_fill_speed.md).
    Why the first neighbour wins and not the nearest surface: the nearer a frame is in time, the smaller the pose
    change its depth errors are warped over; on the real stereo snippet's lateral view (`bench/stereo.py`) a
    depth test across frames -1, -2, -3, +1 gave 23.18 dB with holes counted against 23.41 dB this way, and adding
    frames -4, -5, +2 lowered the depth test's figure to 22.98 dB while this way's stayed at 23.40.
    """
    h, w = depth_m.shape
    wide_w = w + 2 * margin_px
    K_wide = np.asarray(K, dtype=np.float64).copy()
    K_wide[0, 2] += margin_px
    wide_rgb = np.zeros((h, wide_w, 3), dtype=np.uint8)
    wide_depth = np.zeros((h, wide_w), dtype=np.float32)
    wide_rgb[:, margin_px : margin_px + w] = rgb
    wide_depth[:, margin_px : margin_px + w] = depth_m
    open_px = np.ones((h, wide_w), dtype=bool)  # margin pixels no neighbour has filled yet
    open_px[:, margin_px : margin_px + w] = False
    boxes = ((0, 0, margin_px, h), (margin_px + w, 0, margin_px, h)) if margin_px > 0 else ()
    for other_rgb, other_depth_m, T_this_other in neighbours:
        other = (  # writable arrays: a world's frames are read-only memory maps, which torch warns about
            torch.from_numpy(np.require(other_rgb, np.uint8, ("C", "W"))),
            torch.from_numpy(np.require(other_depth_m, np.float32, ("C", "W"))),
        )
        for box in boxes:
            out = forward_warp(*other, K, T_this_other, K_wide, wide_w, h, roi=box)
            region = _cut(open_px, box)
            take = region & out.valid.numpy()
            _cut(wide_rgb, box)[take] = out.rgb.numpy()[take]
            _cut(wide_depth, box)[take] = out.depth_m.numpy()[take]
            region &= ~take
    neighbour_px = 2 * margin_px * h - int(np.count_nonzero(open_px))
    return WideFrame(wide_rgb, wide_depth, K_wide, margin_px, neighbour_px)
