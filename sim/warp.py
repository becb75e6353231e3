"""Forward warp of an RGB-D frame into another camera: the image-based view synthesis of the paper (eq. 2).

Each source pixel p with depth z is back-projected (z K_src^-1 p), moved by T_dst_src, projected with K_dst and
splatted to its nearest destination pixel; a z-buffer keeps the nearest point per pixel through `scatter_reduce(amin)`
of a packed int64 key (float32 depth bits << 32 | source pixel index: positive float bits sort like the floats).
Pixels with infinite depth (sky) are warped as points at infinity (rotation only), so the sky is not a hole.
Small cracks (1-2 px, with warped pixels on both sides along a row, column or diagonal) are filled with the nearest
surface around them; larger disocclusions stay empty (`valid` False).

Only the requested region of interest of the destination image is rendered: source pixels landing outside it (plus a
2 px margin that hole filling reads) are dropped before the scatter, and only a source rectangle that provably holds
every pixel that can land in it is transformed at all (`_source_window`), so the cost scales with what the policy
sees.
What depends on the camera model alone (the rays K^-1 p) is cached per intrinsics and size; what depends on the source
frame (its back-projected points, packed colours) is cached per source tensor object and version counter, so warping
one recorded frame to many agents' poses pays for it once. An in-place torch change of a frame invalidates its entry;
writing into the numpy array under a `torch.from_numpy` tensor does not (pass a new tensor for a new frame).
On CPU the transform, z-buffer, crack filling and colour gather run as one compiled kernel per frame
(`warp_kernel.py`, numba) with the same arithmetic and z-buffer order; the torch path below is what runs on a GPU
(and on CPU with `use_kernel=False`). The two give the same image up to float rounding at pixel borders.
Conventions: pixel centres at integer coordinates (see geometry.scale_intrinsics), depth = z along the optical axis.
"""

from __future__ import annotations

import functools
import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn.functional import pad

from drivesim.sim.cpu_threads import parallel_slot

__all__ = ["KernelWarp", "WarpResult", "forward_warp", "rendered_region"]

_INF_BITS = 0x7F800000  # float32 +inf
# Empty z-buffer entry: larger than every real key, and its high half decodes to a depth of +inf.
_EMPTY_KEY = (_INF_BITS << 32) | 0xFFFFFFFF
_LOW32 = 0xFFFFFFFF
_FILL_RADIUS_PX = 2
_NEAR_M = 1e-3
_SOURCE_CACHE_SIZE = 8


@dataclass
class WarpResult:
    """A warped view.

    :param rgb: (B, h, w, 3) colour, same dtype as the source (0 where empty).
    :param depth_m: (B, h, w) float32 z in the destination camera, +inf where empty or sky.
    :param valid: (B, h, w) bool, True where a source pixel (or a filled crack) landed, sky included.
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    valid: torch.Tensor


@dataclass
class _Source:
    """Per-source-frame constants: points (B, 3, HW) in the source camera (z K^-1 p; the ray K^-1 p for sky),
    `finite` (B, 1, HW) 1.0 for pixels with a finite depth else 0.0, `near` (B, HW) the smallest destination z a
    point may have to be drawn (never reached for pixels without depth), `sky` (B, HW) bool, the colour table
    (B * HW,) int32 packed RGB8 for uint8 sources or (3, B * HW) channel-major otherwise, and the smallest finite
    depth (inf when there is none)."""

    points: torch.Tensor
    finite: torch.Tensor
    near: torch.Tensor
    sky: torch.Tensor
    colour: torch.Tensor
    min_depth_m: float


_SOURCE_CACHE: OrderedDict[tuple, tuple[torch.Tensor, torch.Tensor, _Source]] = OrderedDict()
_RAYS_CACHE: OrderedDict[tuple, torch.Tensor] = OrderedDict()
# The kernel path keeps only a float per frame, for as many frames as the view synthesizer keeps; weak references
# (a dead tensor's id may come back for another one) so that the cache never holds frames alive.
_MIN_DEPTH_CACHE: OrderedDict[tuple, tuple[weakref.ref, weakref.ref, float]] = OrderedDict()
_MIN_DEPTH_CACHE_SIZE = 2048
_NEVER = 3.0e38  # a z no point reaches (finite, so that 0 * _NEVER stays 0)


def _rays(height_px: int, width_px: int, K: torch.Tensor) -> torch.Tensor:
    """(3, H*W) float32 rays K^-1 [u, v, 1] of every pixel centre, cached per image size, intrinsics and device."""
    key = (height_px, width_px, str(K.device), tuple(K.flatten().tolist()))
    rays = _RAYS_CACHE.get(key)
    if rays is None:
        v, u = torch.meshgrid(
            torch.arange(height_px, dtype=torch.float64, device=K.device),
            torch.arange(width_px, dtype=torch.float64, device=K.device),
            indexing="ij",
        )
        pixels = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)])
        rays = (torch.linalg.inv(K) @ pixels).to(torch.float32)
        _RAYS_CACHE[key] = rays
        if len(_RAYS_CACHE) > _SOURCE_CACHE_SIZE:
            _RAYS_CACHE.popitem(last=False)
    return rays


def _prepare_source(
    rgb: torch.Tensor, depth_m: torch.Tensor, K_src: torch.Tensor, caller_tensors: tuple[torch.Tensor, torch.Tensor]
) -> _Source:
    """The per-frame constants of (B, H, W) frames, cached per tensor objects the caller passed (`caller_tensors`,
    held by the cache so their ids stay unique) and their version counters (bumped by any in-place torch change)."""
    rgb_in, depth_in = caller_tensors
    key = (id(depth_in), depth_in._version, id(rgb_in), rgb_in._version, tuple(K_src.flatten().tolist()))
    cached = _SOURCE_CACHE.get(key)
    if cached is not None:
        _SOURCE_CACHE.move_to_end(key)
        return cached[2]
    B, H, W = depth_m.shape
    dev = depth_m.device
    rays = _rays(H, W, K_src)
    z = depth_m.reshape(B, 1, H * W).to(torch.float32)
    has_depth = (z > 0) & torch.isfinite(z)  # NaN compares False
    sky = torch.isposinf(z)
    depth_f, sky_f = has_depth.to(torch.float32), sky.to(torch.float32)
    # Smallest destination z to draw: _NEAR_M for points, 0 for sky, never (a huge finite value) for no data.
    near = (depth_f * _NEAR_M).add_((1.0 - depth_f - sky_f) * _NEVER)[:, 0]
    if rgb.dtype == torch.uint8:  # RGB8 + a zero byte, read as one int32 per pixel
        rgba = torch.cat([rgb.reshape(B * H * W, 3), torch.zeros((B * H * W, 1), dtype=torch.uint8, device=dev)], 1)
        colour = rgba.view(torch.int32).reshape(-1)
    else:
        colour = rgb.reshape(B * H * W, 3).T.contiguous()
    min_depth = float(torch.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0).add_((1.0 - depth_f) * _NEVER).min())
    min_depth = min_depth if min_depth < 0.5 * _NEVER else float("inf")
    scale = torch.nan_to_num(z, nan=0.0, posinf=1.0, neginf=0.0)
    source = _Source(rays * scale, depth_f, near, sky[:, 0], colour, min_depth)
    _SOURCE_CACHE[key] = (rgb_in, depth_in, source)
    if len(_SOURCE_CACHE) > _SOURCE_CACHE_SIZE:
        _SOURCE_CACHE.popitem(last=False)
    return source


def _source_window(
    min_depth_m: float,
    K_src: np.ndarray,
    src_size: tuple[int, int],
    T_dst_src: np.ndarray,
    K_dst: np.ndarray,
    region: tuple[int, int, int, int],
) -> tuple[int, int, int, int] | None:
    """A source pixel rectangle (x0, y0, x1, y1), end exclusive, holding every source pixel that can land in the
    destination `region` (x0, y0, x1, y1), or None when no useful bound exists (then all pixels are warped).

    Destination depths are bounded below by d_lo = min_depth * min(r3 . K_src^-1 p) + t_z over the source image (r3
    the last row of R_dst_src; the minimum of that linear function is at an image corner). The region's frustum from
    d_lo to infinity is convex and, when all its vertices (and directions) lie in front of the source camera, projects
    into the convex hull of their projections.
    """
    from drivesim.sim import warp_kernel  # numba compiles (or loads its cache) on first import

    H, W = src_size
    rays_src, corners_dst = _window_rays(
        np.asarray(K_src, dtype=np.float64).tobytes(), np.asarray(K_dst, dtype=np.float64).tobytes(),
        tuple(src_size), tuple(int(v) for v in region),
    )  # fmt: skip
    window = warp_kernel.source_window(
        float(min_depth_m), rays_src, corners_dst, np.asarray(K_src, dtype=np.float64),
        np.ascontiguousarray(np.asarray(T_dst_src, dtype=np.float64).reshape(-1, 4, 4)), W, H,
    )  # fmt: skip
    return None if window[0] < 0 else tuple(int(v) for v in window)


@functools.lru_cache(maxsize=64)
def _window_rays(
    K_src: bytes, K_dst: bytes, src_size: tuple[int, int], region: tuple[int, int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """_source_window's constants (the same for every step of a view): rays K_src^-1 p of the source image's corners
    and K_dst^-1 p of the destination region's corners (with a pixel of margin), each (4, 3). Intrinsics as the bytes
    of float64 (3, 3) arrays, so that they can key the cache."""
    H, W = src_size
    rx0, ry0, rx1, ry1 = region
    K_src_inv = np.linalg.inv(np.frombuffer(K_src, dtype=np.float64).reshape(3, 3))
    K_dst_inv = np.linalg.inv(np.frombuffer(K_dst, dtype=np.float64).reshape(3, 3))
    corners_src = np.array([[-0.5, -0.5, 1], [W - 0.5, -0.5, 1], [-0.5, H - 0.5, 1], [W - 0.5, H - 0.5, 1]])
    corners_dst = np.array([[rx0 - 1.5, ry0 - 1.5, 1], [rx1 + 0.5, ry0 - 1.5, 1], [rx0 - 1.5, ry1 + 0.5, 1],
                            [rx1 + 0.5, ry1 + 0.5, 1]])  # fmt: skip
    return corners_src @ K_src_inv.T, corners_dst @ K_dst_inv.T


def _as_tensor(x: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64), device=device)


def _fill_cracks(keys: torch.Tensor, radius: int = _FILL_RADIUS_PX) -> torch.Tensor:
    """Fill empty pixels that have warped pixels on both sides along a row, column or diagonal, within 1 px first
    (from the nearest surface in the 3x3 neighbourhood), then within `radius` px for the cracks still open."""
    B, h, w = keys.shape
    for r in range(1, radius + 1):
        valid = keys != _EMPTY_KEY
        padded = pad(valid, (r, r, r, r))  # False outside the image

        def at(dy: int, dx: int, image: torch.Tensor = padded, r: int = r) -> torch.Tensor:
            return image[:, r + dy : r + dy + h, r + dx : r + dx + w]

        enclosed = torch.zeros_like(valid)
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            side_a, side_b = at(dy, dx), at(-dy, -dx)
            for d in range(2, r + 1):
                side_a, side_b = side_a | at(d * dy, d * dx), side_b | at(-d * dy, -d * dx)
            enclosed |= side_a & side_b
        fill = enclosed & ~valid
        if not bool(fill.any()):
            continue
        # Nearest surface in the (2r+1)^2 neighbourhood: a separable minimum over shifted views.
        kp = pad(keys, (r, r, r, r), value=_EMPTY_KEY)
        rows = kp[:, :, 0:w]
        for d in range(1, 2 * r + 1):
            rows = torch.minimum(rows, kp[:, :, d : d + w])
        best = rows[:, 0:h]
        for d in range(1, 2 * r + 1):
            best = torch.minimum(best, rows[:, d : d + h])
        keys = torch.where(fill, best, keys)
    return keys


def rendered_region(
    out_width_px: int, out_height_px: int, roi: tuple[int, int, int, int], fill_holes: bool
) -> tuple[int, int, int, int]:
    """(ex0, ey0, ew, eh): the part of the destination image a warp into `roi` (x0, y0, w, h) renders, the ROI plus
    the margin crack filling reads, clipped to the image."""
    x0, y0, w, h = roi
    margin = _FILL_RADIUS_PX if fill_holes else 0
    ex0, ey0 = max(x0 - margin, 0), max(y0 - margin, 0)
    ex1, ey1 = min(x0 + w + margin, out_width_px), min(y0 + h + margin, out_height_px)
    return ex0, ey0, ex1 - ex0, ey1 - ey0


def forward_warp(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K_src: np.ndarray | torch.Tensor,
    T_dst_src: np.ndarray | torch.Tensor,
    K_dst: np.ndarray | torch.Tensor,
    out_width_px: int,
    out_height_px: int,
    roi: tuple[int, int, int, int] | None = None,
    fill_holes: bool = True,
    use_kernel: bool = True,
    source_index: torch.Tensor | np.ndarray | None = None,
) -> WarpResult:
    """Warp B RGB-D source frames into B destination cameras.

    :param rgb: (B, H, W, 3) uint8 or float source colour (or (H, W, 3) for B = 1).
    :param depth_m: (B, H, W) source depth (z along the optical axis, m); +inf = sky (point at infinity);
        zero, negative or NaN = no data (the pixel is not warped).
    :param K_src: (3, 3) source intrinsics.
    :param T_dst_src: (4, 4) or (B, 4, 4) source optical frame -> destination optical frame.
    :param K_dst: (3, 3) destination intrinsics for the full out_width_px x out_height_px image.
    :param roi: (x0, y0, w, h) region of the destination image to render (default: all of it).
    :param fill_holes: fill 1-2 px cracks (never large disocclusions).
    :param use_kernel: on CPU, run the compiled kernel (warp_kernel.py, same result); False: the torch path, which
        is what runs on a GPU.
    :param source_index: (B,) int, view b's frame among the N frames of rgb / depth_m (N need not be B): the frames'
        constants are then prepared once for all N and cached with those tensors, so a batch of views of frames kept
        on the device pays no per-call preparation. None: view b warps frame b.
    :returns: WarpResult of size (B, h, w) of the region.
    """
    caller_tensors = (rgb, depth_m)
    squeeze = depth_m.dim() == 2
    if squeeze:
        rgb, depth_m = rgb[None], depth_m[None]
    device = depth_m.device
    frame_of_view = None if source_index is None else torch.as_tensor(source_index, device=device).to(torch.int64)
    if frame_of_view is not None and use_kernel and device.type == "cpu":
        # The compiled path keeps nothing per frame but its smallest depth: hand it the views' frames.
        rgb, depth_m = rgb.index_select(0, frame_of_view), depth_m.index_select(0, frame_of_view)
        caller_tensors, frame_of_view = (rgb, depth_m), None
    B = depth_m.shape[0] if frame_of_view is None else int(frame_of_view.numel())
    T = _as_tensor(T_dst_src, device)
    if T.dim() == 2:
        T = T[None].expand(B, 4, 4)
    if T.shape != (B, 4, 4):
        raise ValueError(f"T_dst_src must be (4, 4) or ({B}, 4, 4), got {tuple(T.shape)}")
    x0, y0, w, h = roi if roi is not None else (0, 0, out_width_px, out_height_px)
    if w <= 0 or h <= 0 or x0 < 0 or y0 < 0 or x0 + w > out_width_px or y0 + h > out_height_px:
        raise ValueError(f"roi {roi} is not inside the {out_width_px}x{out_height_px} destination image")
    extended = rendered_region(out_width_px, out_height_px, (x0, y0, w, h), fill_holes)
    if use_kernel and device.type == "cpu":
        result = _warp_with_kernel(
            rgb,
            depth_m,
            K_src,
            T_dst_src,
            K_dst,
            extended,
            (x0, y0, w, h),
            fill_holes,
            caller_tensors,
            partial=extended[2:] != (out_width_px, out_height_px),
        )
    else:
        K_s = _as_tensor(K_src, device)
        source = _prepare_source(rgb, depth_m, K_s, caller_tensors)
        keys = _nearest_keys(source, K_s, T, _as_tensor(K_dst, device), depth_m.shape[1:], extended,
                             (out_width_px, out_height_px), frame_of_view)  # fmt: skip
        if fill_holes:
            keys = _fill_cracks(keys)
        ex0, ey0 = extended[:2]
        keys = keys[:, y0 - ey0 : y0 - ey0 + h, x0 - ex0 : x0 - ex0 + w].reshape(B, h * w)
        result = _gather(keys, source, rgb.dtype, depth_m.shape[1:], (h, w), frame_of_view)
    return WarpResult(rgb=result.rgb[0], depth_m=result.depth_m[0], valid=result.valid[0]) if squeeze else result


def _nearest_keys(
    source: _Source,
    K_s: torch.Tensor,
    T: torch.Tensor,
    K_d: torch.Tensor,
    source_size: tuple[int, int],
    extended: tuple[int, int, int, int],
    out_size: tuple[int, int],
    frame_of_view: torch.Tensor | None,
) -> torch.Tensor:
    """The torch path's z-buffer: (B, eh, ew) keys of the rendered region `extended`, each the nearest point's
    (depth bits << 32 | source pixel), `_EMPTY_KEY` where none lands."""
    H, W = source_size
    ex0, ey0, ew, eh = extended
    B = T.shape[0]
    device = T.device
    # q = K_dst (R P + t finite): finite points move with the camera, points at infinity only turn.
    M = (K_d @ T[:, :3, :3]).to(torch.float32)
    c = (K_d @ T[:, :3, 3:]).to(torch.float32)  # (B, 3, 1)
    P, fin, near, sky = source.points, source.finite[:, 0], source.near, source.sky
    if frame_of_view is not None:
        P, fin, near, sky = (t.index_select(0, frame_of_view) for t in (P, fin, near, sky))
    window_pixels = None
    window = None
    if (ew, eh) != out_size:
        window = _source_window(
            source.min_depth_m, K_s.cpu().numpy(), (H, W), T.cpu().numpy(), K_d.cpu().numpy(),
            (ex0, ey0, ex0 + ew, ey0 + eh),
        )  # fmt: skip
    if window is not None and (window[2] - window[0]) * (window[3] - window[1]) < H * W:
        # Only the source pixels that can land in the region: a rectangle of the source frame.
        sx0, sy0, sx1, sy1 = window
        P = P.reshape(B, 3, H, W)[:, :, sy0:sy1, sx0:sx1].reshape(B, 3, -1)
        fin = fin.reshape(B, H, W)[:, sy0:sy1, sx0:sx1].reshape(B, -1)
        near = near.reshape(B, H, W)[:, sy0:sy1, sx0:sx1].reshape(B, -1)
        sky = sky.reshape(B, H, W)[:, sy0:sy1, sx0:sx1].reshape(B, -1)
        window_pixels = (
            torch.arange(sy0, sy1, device=device)[:, None] * W + torch.arange(sx0, sx1, device=device)
        ).reshape(-1)
    # Written out per row (not bmm) so that a frame warps bit-identically alone or in a batch.
    q = [
        torch.addcmul(torch.addcmul(torch.addcmul(c[:, i] * fin, M[:, i, 0:1], P[:, 0]), M[:, i, 1:2], P[:, 1]),
                      M[:, i, 2:3], P[:, 2])
        for i in range(3)
    ]  # fmt: skip
    qz = q[2]
    in_front = qz > near
    inv_z = 1.0 / qz
    u = torch.floor(torch.addcmul(torch.full_like(qz, 0.5 - ex0), q[0], inv_z))
    v = torch.floor(torch.addcmul(torch.full_like(qz, 0.5 - ey0), q[1], inv_z))
    inside = in_front & (u >= 0) & (u < ew) & (v >= 0) & (v < eh)
    n_src = qz.shape[1]
    flat = inside.reshape(-1).nonzero().squeeze(1)  # b * n_src + source pixel (of the window)
    depth = qz.reshape(-1).index_select(0, flat)
    depth.masked_fill_(sky.reshape(-1).index_select(0, flat), torch.inf)  # points at infinity
    b_idx = flat // n_src if B > 1 else torch.zeros_like(flat)
    pixel = flat - b_idx * n_src
    if window_pixels is not None:
        pixel = window_pixels.index_select(0, pixel)
    key = (depth.view(torch.int32).to(torch.int64) << 32) | pixel
    pix = (b_idx * eh + v.reshape(-1).index_select(0, flat).to(torch.int64)) * ew
    pix += u.reshape(-1).index_select(0, flat).to(torch.int64)
    keys = torch.full((B * eh * ew,), _EMPTY_KEY, dtype=torch.int64, device=device)
    keys.scatter_reduce_(0, pix, key, reduce="amin")
    return keys.reshape(B, eh, ew)


def _gather(
    keys: torch.Tensor,
    source: _Source,
    dtype: torch.dtype,
    source_size: tuple[int, int],
    size: tuple[int, int],
    frame_of_view: torch.Tensor | None,
) -> WarpResult:
    """The warp's colour, depth and mask from the z-buffer's (B, h * w) keys of the region of `size` (h, w)."""
    H, W = source_size
    B = keys.shape[0]
    h, w = size
    valid = keys != _EMPTY_KEY
    depth_out = (keys >> 32).to(torch.int32).view(torch.float32)  # +inf where empty, by the choice of _EMPTY_KEY
    src_index = (keys & _LOW32).clamp_(max=H * W - 1)
    if frame_of_view is not None:
        src_index += frame_of_view[:, None] * (H * W)
    elif B > 1:
        src_index += torch.arange(B, device=keys.device)[:, None] * (H * W)
    src_index = src_index.reshape(-1)
    if dtype == torch.uint8:
        packed = source.colour.index_select(0, src_index) * valid.reshape(-1)
        out_rgb = packed.view(torch.uint8).reshape(-1, 4)[:, :3].contiguous()  # bytes as packed: any endianness
    else:
        out_rgb = torch.stack([row.index_select(0, src_index) for row in source.colour], -1)
        out_rgb *= valid.reshape(-1, 1)
    return WarpResult(rgb=out_rgb.reshape(B, h, w, 3), depth_m=depth_out.reshape(B, h, w), valid=valid.reshape(B, h, w))


def _min_depth(depth_m: torch.Tensor, caller_tensors: tuple[torch.Tensor, torch.Tensor]) -> float:
    """The smallest finite positive depth of the frames (inf when none), cached like the torch path's constants."""
    rgb_in, depth_in = caller_tensors
    key = (id(depth_in), depth_in._version, id(rgb_in), rgb_in._version)
    cached = _MIN_DEPTH_CACHE.get(key)
    if cached is not None and cached[0]() is rgb_in and cached[1]() is depth_in:
        _MIN_DEPTH_CACHE.move_to_end(key)
        return cached[2]
    z = depth_m.numpy()
    finite = z[(z > 0) & np.isfinite(z)]
    min_depth = float(finite.min()) if finite.size else float("inf")
    _MIN_DEPTH_CACHE[key] = (weakref.ref(rgb_in), weakref.ref(depth_in), min_depth)
    if len(_MIN_DEPTH_CACHE) > _MIN_DEPTH_CACHE_SIZE:
        _MIN_DEPTH_CACHE.popitem(last=False)
    return min_depth


class KernelWarp:
    """`forward_warp`'s CPU kernel path for one camera pair and region, with everything that does not depend on the
    frame or the pose (rays, the source window's corner rays, the region) computed once: a view synthesizer warps a
    frame per step into the same view, and at the policy's few thousand pixels the per-call preparation cost about as
    much as the compiled splat itself.

    :param K_src: (3, 3) source intrinsics. :param src_size: (H, W) of the source frames.
    :param K_dst: (3, 3) destination intrinsics. :param rendered: (ex0, ey0, ew, eh) the region rendered (the ROI
        plus the hole-filling margin). :param roi: (x0, y0, w, h) the region returned. :param fill_holes: fill cracks.
    :param partial: whether the rendered region is smaller than the destination image (then a source window).
    :param bands: horizontal bands the region is cut into, warped at the same time in numba's threads (1: one warp
        in the calling thread); the pixels are the same (`_band_regions`). A call may still warp it whole, in the
        calling thread (its `threads`).
    """

    def __init__(
        self,
        K_src: np.ndarray,
        src_size: tuple[int, int],
        K_dst: np.ndarray,
        rendered: tuple[int, int, int, int],
        roi: tuple[int, int, int, int],
        fill_holes: bool,
        partial: bool,
        bands: int = 1,
    ) -> None:
        self.K_src = np.array(K_src, dtype=np.float64)
        self.K_dst = np.array(K_dst, dtype=np.float64)
        self.src_size = H, W = int(src_size[0]), int(src_size[1])
        self.rendered = np.asarray(rendered, dtype=np.int64)
        self.roi = np.asarray(roi, dtype=np.int64)
        self.radius = _FILL_RADIUS_PX if fill_holes else 0
        self.partial = partial
        self.rays = _rays(H, W, torch.from_numpy(self.K_src)).numpy()
        self._band_rendered, self._band_roi = _band_regions(self.rendered, self.roi, self.radius, bands)
        regions = [self.rendered.tolist(), *self._band_rendered.tolist()]
        rays = [
            _window_rays(self.K_src.tobytes(), self.K_dst.tobytes(), (H, W), (ex0, ey0, ex0 + ew, ey0 + eh))
            for ex0, ey0, ew, eh in regions
        ]
        self._whole_rays, self._band_rays = rays[:1], rays[1:]
        self._whole = np.array([0, 0, W, H], dtype=np.int64)

    def __call__(
        self, rgb: np.ndarray, depth_m: np.ndarray, min_depth_m: float, T_dst_src: np.ndarray, threads: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame (rgb (H, W, 3), depth_m (H, W) float32, its smallest finite depth) warped to pose T_dst_src
        (4, 4): the region's (rgb (h, w, 3), depth (h, w) float32 +inf where empty, valid (h, w) bool) arrays.
        `threads` 1: warped whole in the calling thread; else (0: all bands) its bands at once in numba's threads."""
        with parallel_slot(len(self._band_roi) if threads == 0 else threads) as granted:
            return self._warp(rgb, depth_m, min_depth_m, T_dst_src, banded=granted > 1 and len(self._band_roi) > 1)

    def _warp(
        self, rgb: np.ndarray, depth_m: np.ndarray, min_depth_m: float, T_dst_src: np.ndarray, banded: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`__call__`'s warp, of the bands at the same time or of the whole region in the calling thread."""
        from drivesim.sim import warp_kernel  # numba compiles (or loads its cache) on first import

        H, W = self.src_size
        T = np.asarray(T_dst_src, dtype=np.float64).reshape(1, 4, 4)
        window_list = self._band_rays if banded else self._whole_rays
        partial = self.partial or banded  # each band's source window is narrower than the whole region's
        windows = np.empty((len(window_list), 4), dtype=np.int64)
        for b, window_rays in enumerate(window_list):
            windows[b] = self._whole
            if partial:  # only the source pixels that can land in the region: a rectangle of the source frame
                found = warp_kernel.source_window(float(min_depth_m), *window_rays, self.K_src, T, W, H)
                windows[b] = self._whole if found[0] < 0 else found
        # q = K_dst (R P + t finite): finite points move with the camera, points at infinity only turn.
        M = (self.K_dst @ T[:, :3, :3]).astype(np.float32)[0]
        c = (self.K_dst @ T[:, :3, 3:])[0, :, 0].astype(np.float32)
        h, w = int(self.roi[3]), int(self.roi[2])
        rgb_out = np.empty((h, w, 3), dtype=rgb.dtype)
        depth_out = np.empty((h, w), dtype=np.float32)
        valid = np.empty((h, w), dtype=bool)
        arrays = (self.rays, depth_m.reshape(H * W), rgb.reshape(H * W, 3), _NEAR_M, M, c)
        if not banded:
            warp_kernel.warp_region(
                *arrays, windows[0], W, self.rendered, self.roi, self.radius, rgb_out, depth_out, valid
            )  # fmt: skip
        else:
            warp_kernel.warp_bands(
                *arrays, windows, W, self._band_rendered, self._band_roi, self.radius, rgb_out, depth_out, valid
            )  # fmt: skip
        return rgb_out, depth_out, valid


def _band_regions(rendered: np.ndarray, roi: np.ndarray, radius: int, bands: int) -> tuple[np.ndarray, np.ndarray]:
    """(rendered (n, 4), roi (n, 4)) of `roi` cut into n = `bands` horizontal bands (at most one per row): each band
    renders its rows plus those its crack filling reads across a cut (radius + (radius - 1) + ... + 1 px: pass r reads
    r px of the results of pass r - 1), within the whole region's `rendered`, so that its pixels are exactly those
    of the whole region's warp."""
    x0, y0, w, h = (int(v) for v in roi)
    ex0, ey0, ew, eh = (int(v) for v in rendered)
    reach = radius * (radius + 1) // 2
    cuts = np.linspace(0, h, max(min(bands, h), 1) + 1).round().astype(int).tolist()
    band_rendered, band_roi = [], []
    for top, bottom in zip(cuts[:-1], cuts[1:], strict=True):
        r0 = ey0 if top == 0 else max(y0 + top - reach, ey0)
        r1 = ey0 + eh if bottom == h else min(y0 + bottom + reach, ey0 + eh)
        band_rendered.append((ex0, r0, ew, r1 - r0))
        band_roi.append((x0, y0 + top, w, bottom - top))
    return np.array(band_rendered, dtype=np.int64), np.array(band_roi, dtype=np.int64)


@functools.lru_cache(maxsize=16)
def _kernel_warp(
    K_src: bytes, src_size: tuple[int, int], K_dst: bytes, rendered: tuple, roi: tuple, fill_holes: bool, partial: bool
) -> KernelWarp:
    """A KernelWarp per camera pair and region (intrinsics as float64 bytes, so that they can key the cache)."""
    K_s = np.frombuffer(K_src, dtype=np.float64).reshape(3, 3)
    K_d = np.frombuffer(K_dst, dtype=np.float64).reshape(3, 3)
    return KernelWarp(K_s, src_size, K_d, rendered, roi, fill_holes, partial)


def _warp_with_kernel(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K_src: np.ndarray | torch.Tensor,
    T_dst_src: np.ndarray | torch.Tensor,
    K_dst: np.ndarray | torch.Tensor,
    rendered: tuple[int, int, int, int],
    roi: tuple[int, int, int, int],
    fill_holes: bool,
    caller_tensors: tuple[torch.Tensor, torch.Tensor],
    partial: bool,
) -> WarpResult:
    """forward_warp's CPU path for (B, H, W) frames: each frame through `KernelWarp` (splat, crack filling, colour
    gather), with no per-frame preparation but the smallest depth (for the source window).

    :param rendered: (ex0, ey0, ew, eh) the rendered region (the ROI plus the hole-filling margin).
    :param roi: (x0, y0, w, h) the region returned.
    :param partial: whether the rendered region is smaller than the destination image (then a source window).
    """
    B, H, W = depth_m.shape
    K_s = np.asarray(K_src.cpu().numpy() if isinstance(K_src, torch.Tensor) else K_src, dtype=np.float64)
    K_d = np.asarray(K_dst.cpu().numpy() if isinstance(K_dst, torch.Tensor) else K_dst, dtype=np.float64)
    T = np.asarray(T_dst_src.cpu().numpy() if isinstance(T_dst_src, torch.Tensor) else T_dst_src, dtype=np.float64)
    T = np.broadcast_to(T.reshape(-1, 4, 4), (B, 4, 4))
    warp = _kernel_warp(
        K_s.tobytes(), (H, W), K_d.tobytes(), tuple(int(v) for v in rendered), tuple(int(v) for v in roi),
        bool(fill_holes), bool(partial),
    )  # fmt: skip
    min_depth = _min_depth(depth_m, caller_tensors) if partial else float("inf")
    depth_src = depth_m.to(torch.float32).numpy()
    colour = rgb.numpy()
    x0, y0, w, h = roi
    depth_out = np.empty((B, h, w), dtype=np.float32)
    valid = np.empty((B, h, w), dtype=bool)
    rgb_out = np.empty((B, h, w, 3), dtype=colour.dtype)
    for b in range(B):
        rgb_out[b], depth_out[b], valid[b] = warp(colour[b], depth_src[b], min_depth, T[b])
    return WarpResult(rgb=torch.from_numpy(rgb_out), depth_m=torch.from_numpy(depth_out), valid=torch.from_numpy(valid))
