"""Forward warp of an RGB-D frame into another camera: the image-based view synthesis of the paper (eq. 2).

Each source pixel p with depth z is back-projected (z K_src^-1 p), moved by T_dst_src, projected with K_dst and
splatted to its nearest destination pixel; a z-buffer keeps the nearest point per pixel through `scatter_reduce(amin)`
of a packed int64 key (float32 depth bits << 32 | source pixel index: positive float bits sort like the floats).
Pixels with infinite depth (sky) are warped as points at infinity (rotation only), so the sky is not a hole.
Small cracks (1-2 px, with warped pixels on both sides along a row, column or diagonal) are filled with the nearest
surface around them; larger disocclusions stay empty (`valid` False).

Only the requested region of interest of the destination image is rendered: source pixels landing outside it (plus a
2 px margin that hole filling reads) are dropped before the scatter, so the cost scales with what the policy sees.
Conventions: pixel centres at integer coordinates (see geometry.scale_intrinsics), depth = z along the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["WarpResult", "forward_warp"]

_EMPTY_KEY = torch.iinfo(torch.int64).max
_LOW32 = 0xFFFFFFFF
_FILL_RADIUS_PX = 2
_NEAR_M = 1e-3
_GRID_CACHE: dict[tuple[int, int, str], torch.Tensor] = {}


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


def _pixel_grid(height_px: int, width_px: int, device: torch.device) -> torch.Tensor:
    """(3, H*W) homogeneous pixel centres [u, v, 1], cached per size and device."""
    key = (height_px, width_px, str(device))
    grid = _GRID_CACHE.get(key)
    if grid is None:
        v, u = torch.meshgrid(
            torch.arange(height_px, dtype=torch.float32, device=device),
            torch.arange(width_px, dtype=torch.float32, device=device),
            indexing="ij",
        )
        grid = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(height_px * width_px, device=device)])
        _GRID_CACHE[key] = grid
    return grid


def _as_tensor(x: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64), device=device)


def _min_filter(keys: torch.Tensor, radius: int) -> torch.Tensor:
    """Separable (2r+1)^2 minimum of a (B, h, w) int64 image (outside the image counts as empty)."""
    out = keys.clone()
    for d in range(1, radius + 1):
        out[:, :, d:] = torch.minimum(out[:, :, d:], keys[:, :, :-d])
        out[:, :, :-d] = torch.minimum(out[:, :, :-d], keys[:, :, d:])
    rows = out.clone()
    for d in range(1, radius + 1):
        out[:, d:, :] = torch.minimum(out[:, d:, :], rows[:, :-d, :])
        out[:, :-d, :] = torch.minimum(out[:, :-d, :], rows[:, d:, :])
    return out


def _shifted(valid: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """valid[y + dy, x + dx] (False outside)."""
    B, h, w = valid.shape
    out = torch.zeros_like(valid)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[:, yd, xd] = valid[:, ys, xs]
    return out


def _fill_cracks(keys: torch.Tensor, radius: int = _FILL_RADIUS_PX) -> torch.Tensor:
    """Fill empty pixels that have warped pixels on both sides along a row, column or diagonal, within 1 px first
    (from the nearest surface in the 3x3 neighbourhood), then within `radius` px for the cracks still open."""
    for r in range(1, radius + 1):
        valid = keys != _EMPTY_KEY
        enclosed = torch.zeros_like(valid)
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            side_a = _shifted(valid, r * dy, r * dx)
            side_b = _shifted(valid, -r * dy, -r * dx)
            for d in range(1, r):
                side_a |= _shifted(valid, d * dy, d * dx)
                side_b |= _shifted(valid, -d * dy, -d * dx)
            enclosed |= side_a & side_b
        keys = torch.where(enclosed & ~valid, _min_filter(keys, r), keys)
    return keys


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
    :returns: WarpResult of size (B, h, w) of the region.
    """
    squeeze = depth_m.dim() == 2
    if squeeze:
        rgb, depth_m = rgb[None], depth_m[None]
    device = depth_m.device
    B, H, W = depth_m.shape
    T = _as_tensor(T_dst_src, device)
    if T.dim() == 2:
        T = T[None].expand(B, 4, 4)
    if T.shape != (B, 4, 4):
        raise ValueError(f"T_dst_src must be (4, 4) or ({B}, 4, 4), got {tuple(T.shape)}")
    x0, y0, w, h = roi if roi is not None else (0, 0, out_width_px, out_height_px)
    margin = _FILL_RADIUS_PX if fill_holes else 0
    # Rendered region: the ROI plus the margin hole filling reads, clipped to the full destination image.
    ex0, ey0 = max(x0 - margin, 0), max(y0 - margin, 0)
    ex1, ey1 = min(x0 + w + margin, out_width_px), min(y0 + h + margin, out_height_px)
    ew, eh = ex1 - ex0, ey1 - ey0

    K_s = _as_tensor(K_src, device)
    K_d = _as_tensor(K_dst, device)
    # q = K_dst (R z K_src^-1 p + t) = z (A p) + K_dst t, with A = K_dst R K_src^-1 folding the cached rays.
    A = (K_d @ T[:, :3, :3] @ torch.linalg.inv(K_s)).to(torch.float32)
    c = (K_d @ T[:, :3, 3:]).to(torch.float32)  # (B, 3, 1)
    q = A @ _pixel_grid(H, W, device)  # (B, 3, HW)
    z = depth_m.reshape(B, 1, H * W).to(torch.float32)
    finite = torch.isfinite(z)
    q = q * torch.where(finite, z, 1.0) + c * finite
    qz = q[:, 2]
    in_front = torch.where(finite[:, 0], (qz > _NEAR_M) & (z[:, 0] > 0), qz > 0)
    qz_safe = torch.where(in_front, qz, 1.0)
    u = torch.floor(q[:, 0] / qz_safe + 0.5) - ex0
    v = torch.floor(q[:, 1] / qz_safe + 0.5) - ey0
    inside = in_front & (u >= 0) & (u < ew) & (v >= 0) & (v < eh)
    b_idx, src = inside.nonzero(as_tuple=True)
    depth = torch.where(finite[:, 0], qz, torch.inf)[b_idx, src]
    key = (depth.view(torch.int32).to(torch.int64) << 32) | src
    pix = (b_idx * eh + v[b_idx, src].to(torch.int64)) * ew + u[b_idx, src].to(torch.int64)
    keys = torch.full((B * eh * ew,), _EMPTY_KEY, dtype=torch.int64, device=device)
    keys.scatter_reduce_(0, pix, key, reduce="amin")
    keys = keys.reshape(B, eh, ew)
    if fill_holes:
        keys = _fill_cracks(keys)
    keys = keys[:, y0 - ey0 : y0 - ey0 + h, x0 - ex0 : x0 - ex0 + w]

    valid = keys != _EMPTY_KEY
    safe = torch.where(valid, keys, 0)
    src_index = safe & _LOW32
    depth_out = torch.where(valid, (safe >> 32).to(torch.int32).view(torch.float32), torch.inf)
    flat = (torch.arange(B, device=device)[:, None, None] * (H * W) + src_index).reshape(-1)
    out_rgb = rgb.reshape(B * H * W, 3)[flat].reshape(B, h, w, 3)
    out_rgb = torch.where(valid[..., None], out_rgb, torch.zeros((), dtype=out_rgb.dtype, device=device))
    result = WarpResult(rgb=out_rgb, depth_m=depth_out, valid=valid)
    if squeeze:
        result = WarpResult(rgb=out_rgb[0], depth_m=depth_out[0], valid=valid[0])
    return result
