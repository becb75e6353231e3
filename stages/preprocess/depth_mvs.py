"""Plane-sweep multi-view stereo over neighbouring frames with known poses, fused with the ground-plane prior.

For each frame (the reference) and each neighbour frame (index offsets from the config), on grey images at a
reduced matching resolution:
1. sweep fronto-parallel depth planes spaced evenly in inverse depth, plus one extra per-pixel hypothesis: the
   ground-plane depth; back-project every reference pixel at each hypothesis, move it into the neighbour's camera with
   the relative pose, project with K and sample the neighbour with `grid_sample`;
2. score each hypothesis by zero-mean normalized cross-correlation (ZNCC) over a square window (box filters), cost
   (1 - ZNCC) / 2, with out-of-view samples costing the maximum;
3. aggregate over neighbours as the mean of the best k costs (a point occluded or out of view in some neighbours
   still matches in the others);
4. winner-take-all with parabolic sub-sample refinement in inverse depth;
5. fuse: keep the ground plane where it matches (textured, cost within a margin of the best); keep stereo where it is
   confident (good ZNCC, a distinct minimum, and enough parallax: near the focus of expansion of a forward drive a
   depth change barely moves a pixel); fill the rest from trusted pixels around (normalized convolution), give the
   sky (textureless, sky-coloured, touching the top) max_depth_m, carry evidence along image columns (vertical
   surfaces), and last fall back to the plane below the horizon and max_depth_m above it; nothing deeper than the
   ground plane;
6. upsample to the working resolution with a 4-tap joint bilateral filter guided by the full-resolution colour.

Frames stream through a small cache of matching-resolution grey images (the reference plus its neighbours), so
memory stays bounded whatever the drive's length.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import torch
import torch.nn.functional as nnf

from drivesim.sim.geometry import invert, scale_intrinsics
from drivesim.sim.warp import forward_warp
from drivesim.stages.preprocess.depth_plane import pixel_rays, plane_depth

if TYPE_CHECKING:
    from drivesim.stages.preprocess.config import DepthConfig, MvsConfig

_EPS_VAR = 1e-4  # grey levels are in [0, 1]; variance below ~(1 % grey)^2 means no texture to match
_RANGE_SIGMA = 12.0 / 255.0  # colour difference (0-1 scale) at which the upsampling weight falls to exp(-1/2)


def _box(x: torch.Tensor, size: int) -> torch.Tensor:
    """Mean over a size x size window, borders replicated; x is (B, C, H, W)."""
    if x.device.type == "cpu" and x.dtype == torch.float32:
        # OpenCV's box filter (running sums, SIMD) is about 10x faster on CPU than torch's cumsum along the width.
        planes = x.detach().contiguous().reshape(-1, *x.shape[-2:]).numpy()
        out = np.empty_like(planes)
        for k in range(planes.shape[0]):
            cv2.boxFilter(planes[k], -1, (size, size), dst=out[k], normalize=True, borderType=cv2.BORDER_REPLICATE)
        return torch.from_numpy(out).reshape(x.shape)
    # Elsewhere (CUDA): running sums (cumsum differences) cost the same for any window size.
    pad = size // 2
    y = nnf.pad(x, (pad + 1, pad, pad + 1, pad), mode="replicate")
    y = y.cumsum(-1)
    y = y[..., size:] - y[..., :-size]
    y = y.cumsum(-2)
    y = y[..., size:, :] - y[..., :-size, :]
    return y * (1.0 / (size * size))


class _FrameCache:
    """Matching-resolution images of the frames near the one being processed: grey (1, 1, h, w) and colour (h, w, 3)."""

    def __init__(self, frames: np.ndarray, width_px: int, height_px: int, device: torch.device) -> None:
        self.frames = frames
        self.size = (width_px, height_px)
        self.device = device
        self.grey: dict[int, torch.Tensor] = {}
        self.colour: dict[int, np.ndarray] = {}

    def get(self, index: int) -> torch.Tensor:
        """Grey image (1, 1, h, w) in [0, 1] of frame `index`."""
        if index not in self.grey:
            small = cv2.resize(np.asarray(self.frames[index]), self.size, interpolation=cv2.INTER_AREA)
            grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
            self.grey[index] = torch.from_numpy(grey)[None, None].to(self.device)
            self.colour[index] = small.astype(np.float32) / 255.0
        return self.grey[index]

    def keep_only(self, indices: set[int]) -> None:
        """Drop every cached frame not in `indices`."""
        for index in list(self.grey):
            if index not in indices:
                del self.grey[index]
                del self.colour[index]


def _window_stats(ref: torch.Tensor, patch_px: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Window mean and standard deviation of the reference image, each (1, 1, h, w)."""
    mean = _box(ref, patch_px)
    var = (_box(ref * ref, patch_px) - mean * mean).clamp_min(0.0)
    return mean, torch.sqrt(var)


def _sweep_costs(
    ref: torch.Tensor,
    ref_stats: tuple[torch.Tensor, torch.Tensor],
    neighbour: torch.Tensor,
    T_nbr_ref: np.ndarray,
    K: torch.Tensor,
    rays: torch.Tensor,
    hypotheses_m: torch.Tensor,
    patch_px: int,
) -> torch.Tensor:
    """(1 - ZNCC) / 2 of each reference pixel against `neighbour` at each depth hypothesis (P, h, w), shape (P, h, w);
    1 (the worst) where the hypothesis projects out of the neighbour's view."""
    n_hyp, h, w = hypotheses_m.shape
    # Project straight to grid_sample's [-1, 1] coordinates: p = d * (N K R ray) + N K t, with N the normalization.
    N = torch.tensor([[2.0 / (w - 1), 0.0, -1.0], [0.0, 2.0 / (h - 1), -1.0], [0.0, 0.0, 1.0]], dtype=K.dtype)
    NK = N.to(K.device) @ K
    R = torch.as_tensor(T_nbr_ref[:3, :3], dtype=rays.dtype, device=rays.device)
    t = torch.as_tensor(T_nbr_ref[:3, 3], dtype=rays.dtype, device=rays.device)
    a = rays @ (NK @ R).T  # (h, w, 3)
    b = NK @ t
    # In-place and fused operations throughout: this function is most of the sweep's time on CPU.
    pz = torch.addcmul(b[2], hypotheses_m, a[..., 2])
    in_front = pz > 0.05
    inv_pz = pz.masked_fill_(~in_front, 1.0).reciprocal_()
    gx = torch.addcmul(b[0], hypotheses_m, a[..., 0]).mul_(inv_pz)
    gy = torch.addcmul(b[1], hypotheses_m, a[..., 1]).mul_(inv_pz)
    grid = torch.stack([gx, gy], dim=-1)
    # The whole matching window must fall inside the neighbour's view.
    margin_x = 1.0 - (patch_px // 2) * 2.0 / (w - 1)
    margin_y = 1.0 - (patch_px // 2) * 2.0 / (h - 1)
    inside = in_front.logical_and_(gx.abs_() <= margin_x).logical_and_(gy.abs_() <= margin_y)
    warped = nnf.grid_sample(
        neighbour.expand(n_hyp, 1, h, w), grid, mode="bilinear", padding_mode="border", align_corners=True
    )
    mean_r, std_r = ref_stats
    mean_w = _box(warped, patch_px)
    var_w = torch.addcmul(_box(warped * warped, patch_px), mean_w, mean_w, value=-1.0).clamp_min_(0.0)
    cov = torch.addcmul(_box(warped.mul_(ref), patch_px), mean_r, mean_w, value=-1.0)
    zncc = cov.div_(var_w.sqrt_().mul_(std_r).add_(_EPS_VAR)).clamp_(-1.0, 1.0)[:, 0]
    return zncc.mul_(-0.5).add_(0.5).masked_fill_(~inside, 1.0)


def _parabolic_shift(cost: torch.Tensor, best: torch.Tensor, best_cost: torch.Tensor) -> torch.Tensor:
    """Sub-sample offset (in hypothesis steps, within +-0.5) of the minimum of a parabola through the winner of a cost
    volume (P, h, w) and its two neighbours; 0 at either end or where the curve is flat."""
    n = cost.shape[0]
    c_lo = cost.gather(0, (best - 1).clamp_min(0)[None])[0]
    c_hi = cost.gather(0, (best + 1).clamp_max(n - 1)[None])[0]
    curvature = c_lo - 2.0 * best_cost + c_hi
    interior = (best > 0) & (best < n - 1) & (curvature > 1e-6)
    return torch.where(interior, (c_lo - c_hi) / (2.0 * curvature.clamp_min(1e-6)), 0.0).clamp(-0.5, 0.5)


def _k_smallest_mean(costs: Iterable[torch.Tensor], k: int) -> torch.Tensor:
    """Element-wise mean of the k smallest of a stream of equally shaped cost volumes, kept by insertion (k small):
    no stacked (neighbours, P, h, w) tensor and no sort."""
    smallest: list[torch.Tensor] = []
    for cost in costs:
        for slot in range(len(smallest)):
            lower = torch.minimum(smallest[slot], cost)
            cost = torch.maximum(smallest[slot], cost)
            smallest[slot] = lower
        if len(smallest) < k:
            smallest.append(cost)
    total = smallest[0].clone()
    for extra in smallest[1:]:
        total += extra
    return total * (1.0 / len(smallest))


def _visible_best_k_mean(costs: torch.Tensor, k: int) -> torch.Tensor:
    """Mean of the k lowest costs over neighbours (Nn, P, h, w) -> (P, h, w), where a pixel that fewer than k
    neighbours see (out of view costs exactly 1, e.g. the outer side of a turn, which the frames ahead and behind look
    away from) takes the mean over the neighbours that do see it, instead of counting the others as mismatches."""
    ordered = torch.sort(costs, dim=0).values
    seen_by = (costs < 1.0).sum(dim=0).amax(dim=0)  # (h, w): neighbours seeing the pixel at some hypothesis
    k_eff = seen_by.clamp(1, k)
    sums = ordered[:k].cumsum(dim=0)  # (k, P, h, w)
    picked = sums.gather(0, (k_eff - 1)[None, None].expand(1, costs.shape[1], -1, -1))[0]
    return picked / k_eff.to(costs.dtype)


def guided_filter(guide: torch.Tensor, costs: torch.Tensor, radius_px: int, eps: float) -> torch.Tensor:
    """Edge-aware aggregation of a cost volume (P, h, w) guided by the grey reference (1, h, w): each hypothesis's
    cost slice is smoothed over a (2r+1)^2 window except across the reference's edges (He et al.'s guided filter, as
    in Hosni et al.'s cost-volume filtering). Hand-written with the box filter above: OpenCV's guided filter lives in
    the contrib build, which the project does not install."""
    size = 2 * radius_px + 1
    guide = guide[None]  # (1, 1, h, w)
    mean_i = _box(guide, size)
    var_i = (_box(guide * guide, size) - mean_i * mean_i).clamp_min(0.0)
    p = costs[:, None]  # (P, 1, h, w)
    stats = _box(torch.cat([p, p * guide], dim=1), size)
    mean_p, corr_ip = stats[:, 0:1], stats[:, 1:2]
    a = (corr_ip - mean_i * mean_p) / (var_i + eps)
    b = mean_p - a * mean_i
    ab = _box(torch.cat([a, b], dim=1), size)
    return (ab[:, 0:1] * guide + ab[:, 1:2])[:, 0]


def _parallax_px(
    depth_m: torch.Tensor, T_nbr_ref: np.ndarray, K: torch.Tensor, rays: torch.Tensor, ratio: float = 1.25
) -> torch.Tensor:
    """How far (pixels) each reference pixel moves in the neighbour when its depth changes by `ratio`."""
    R = torch.as_tensor(T_nbr_ref[:3, :3], dtype=rays.dtype, device=rays.device)
    t = torch.as_tensor(T_nbr_ref[:3, 3], dtype=rays.dtype, device=rays.device)
    rotated = rays @ R.T
    uv = []
    for d in (depth_m, depth_m * ratio):
        p = d[..., None] * rotated + t
        z = p[..., 2].clamp_min(0.05)
        uv.append(torch.stack([K[0, 0] * p[..., 0] / z, K[1, 1] * p[..., 1] / z], dim=-1))
    return torch.linalg.vector_norm(uv[0] - uv[1], dim=-1)


def _joint_bilateral_upsample(
    inv_depth_lo: np.ndarray, colour_lo: np.ndarray, colour_hi: np.ndarray, bilateral: bool
) -> np.ndarray:
    """Inverse depth at the high resolution of `colour_hi`: bilinear taps weighted by colour similarity."""
    h, w = inv_depth_lo.shape
    H, W = colour_hi.shape[:2]
    if not bilateral:
        return cv2.resize(inv_depth_lo, (W, H), interpolation=cv2.INTER_LINEAR)
    x = (np.arange(W, dtype=np.float32) + 0.5) * (w / W) - 0.5
    y = (np.arange(H, dtype=np.float32) + 0.5) * (h / H) - 0.5
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = np.clip(x - x0, 0.0, 1.0)[None, :]
    fy = np.clip(y - y0, 0.0, 1.0)[:, None]
    total = np.zeros((H, W), np.float32)
    weight_sum = np.zeros((H, W), np.float32)
    for ys, wy in ((y0, 1.0 - fy), (y1, fy)):
        for xs, wx in ((x0, 1.0 - fx), (x1, fx)):
            tap_colour = colour_lo[ys[:, None], xs[None, :]]
            diff2 = np.sum((tap_colour - colour_hi) ** 2, axis=-1)
            weight = (wy * wx) * np.exp(-diff2 / (2.0 * _RANGE_SIGMA**2)) + 1e-6 * (wy * wx)
            total += weight * inv_depth_lo[ys[:, None], xs[None, :]]
            weight_sum += weight
    return total / weight_sum


# Where each fused depth came from (counted for the summary).
_STEREO, _PLANE, _FILLED, _COLUMN, _FALLBACK_PLANE, _FAR = range(6)
_LABELS = ("stereo", "plane", "filled", "column", "fallback_plane", "far_fallback")


def sky_mask(texture_std: np.ndarray, colour: np.ndarray, below_horizon: np.ndarray, max_std: float) -> np.ndarray:
    """Pixels taken as sky: textureless (window deviation below `max_std`), sky-coloured (bright, blue at least as
    strong as red: clear or overcast), above the horizon, and connected to the top of the image through such pixels
    (a bare patch of facade is enclosed by texture, and a plain facade reaching the top is rarely blue). A mono
    camera's sky is never found (a white facade looks the same); it then takes the depth of what is below it."""
    skyish = (colour[..., 2] > colour[..., 0] + 0.04) & (colour.mean(axis=-1) > 0.35)
    candidate = ((texture_std < max_std) & skyish & ~below_horizon).astype(np.uint8)
    count, labels = cv2.connectedComponents(candidate, connectivity=4)
    top = np.unique(labels[0][candidate[0] > 0])
    return np.isin(labels, top) & (candidate > 0)


def _nearest_in_column(values: np.ndarray, known: np.ndarray, above_only: bool = False) -> np.ndarray:
    """For every pixel, the value of the nearest known pixel in its column (or the nearest above it); NaN if none."""
    h, w = values.shape
    rows = np.arange(h)[:, None].repeat(w, axis=1)
    above = np.maximum.accumulate(np.where(known, rows, -1), axis=0)  # nearest known row at or above
    if above_only:
        source = above
    else:
        below = np.minimum.accumulate(np.where(known, rows, h)[::-1], axis=0)[::-1]  # nearest known row at or below
        use_below = (below < h) & ((above < 0) | (below - rows < rows - above))
        source = np.where(use_below, below, above)
    picked = values[np.clip(source, 0, h - 1), np.arange(w)[None, :]]
    return np.where(source >= 0, picked, np.nan)


def _fuse(
    stereo_m: np.ndarray,
    use_stereo: np.ndarray,
    plane_ok: np.ndarray,
    plane_m: np.ndarray,
    sky: np.ndarray,
    far_m: float,
    fill_sigma_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Fused depth (h, w) and the source label of each pixel.

    Trusted stereo and agreeing plane pixels are kept. A pixel with neither takes, in order: the Gaussian-weighted
    mean inverse depth of the trusted pixels around it when they surround it densely enough (textureless patches and
    object rims); `far_m` if it is sky; the depth of the nearest trusted pixel in its column (a vertical surface -
    facade, car side, tree trunk - has one optical depth down an image column when the camera is nearly level);
    and last the plane below the horizon and `far_m` above it.
    """
    trusted = use_stereo | plane_ok
    depth = np.where(use_stereo, stereo_m, plane_m).astype(np.float32)
    labels = np.where(use_stereo, _STEREO, np.where(plane_ok, _PLANE, _FALLBACK_PLANE)).astype(np.int64)
    labels[~trusted & (plane_m >= far_m)] = _FAR
    if trusted.all() or not trusted.any():
        return depth, labels
    todo = ~trusted
    if fill_sigma_px > 0:
        weight = trusted.astype(np.float32)
        support = cv2.GaussianBlur(weight, (0, 0), fill_sigma_px)
        inv = cv2.GaussianBlur(weight / depth, (0, 0), fill_sigma_px)
        fill = todo & (support >= 0.25) & ~sky
        depth[fill] = np.clip(support[fill] / inv[fill], 0.0, far_m)
        labels[fill] = _FILLED
        todo &= ~fill
    depth[todo & sky] = far_m
    labels[todo & sky] = _FAR
    todo &= ~sky
    # Above the horizon: the nearest evidence up or down the column. Below it: the nearest stereo evidence above,
    # if nearer than the ground there (a vertical surface reaches down to where it stands; below that is ground).
    evidence = (labels == _STEREO) | (labels == _FILLED)
    above_horizon = plane_m >= far_m
    column = _nearest_in_column(depth, evidence | (trusted & ~above_horizon))
    take = todo & above_horizon & np.isfinite(column)
    over = _nearest_in_column(depth, evidence, above_only=True)
    take_below = todo & ~above_horizon & (over < plane_m)
    depth[take] = column[take]
    depth[take_below] = over[take_below]
    labels[take | take_below] = _COLUMN
    # Nothing visible lies below the ground: no depth beyond the ground plane's.
    return np.minimum(depth, plane_m), labels


def _plane_where_no_better(
    depth_m: np.ndarray,
    labels: np.ndarray,
    plane_m: np.ndarray,
    far_m: float,
    sweep_cost: torch.Tensor,
    plane_cost: torch.Tensor,
    inv_depths: torch.Tensor,
    margin: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel fusion with the road plane by photometric evidence: a guessed pixel below the horizon (filled from
    around, or from its column) takes the ground plane unless its guessed depth matches the neighbours better than
    the plane by more than `margin` in cost. Textureless road matches every depth equally badly, so it gets the
    plane (the prior), not the depth of whatever textured object lies next to it."""
    guessed = ((labels == _FILLED) | (labels == _COLUMN)) & (plane_m < far_m)
    if not guessed.any():
        return depth_m, labels
    inv = torch.from_numpy(1.0 / np.clip(depth_m, 1e-3, None)).to(sweep_cost.device)
    step = inv_depths[1] - inv_depths[0]
    index = ((inv - inv_depths[0]) / step).round().long().clamp(0, len(inv_depths) - 1)
    guessed_cost = sweep_cost.gather(0, index[None])[0]
    take = guessed & (plane_cost <= guessed_cost + margin).cpu().numpy()
    return np.where(take, plane_m, depth_m).astype(np.float32), np.where(take, _PLANE, labels)


def _stereo_evidence(
    i: int,
    nbrs: list[int],
    poses: np.ndarray,
    cache: _FrameCache,
    K_t: torch.Tensor,
    rays: torch.Tensor,
    hypotheses: torch.Tensor,
    inv_depths: torch.Tensor,
    below_horizon: torch.Tensor,
    far_m: float,
    m: MvsConfig,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sweep frame i against its neighbours: (stereo depth m, trusted stereo mask, trusted plane mask, window
    deviation of the grey image, aggregated sweep cost (P, h, w), plane cost), at matching resolution."""
    ref = cache.get(i)
    T_ref = poses[i]
    rel = [invert(poses[j]) @ T_ref for j in nbrs]
    stats = _window_stats(ref, m.patch_size_px)
    per_neighbour = (
        _sweep_costs(ref, stats, cache.get(j), T, K_t, rays, hypotheses, m.patch_size_px)
        for j, T in zip(nbrs, rel, strict=True)
    )
    k = min(m.best_k, len(nbrs))
    if m.visible_best_k:
        agg = _visible_best_k_mean(torch.stack(list(per_neighbour)), k)
    else:
        agg = _k_smallest_mean(per_neighbour, k)  # (P, h, w)
    if m.aggregation_radius_px > 0:
        agg = guided_filter(ref[0], agg, m.aggregation_radius_px, m.aggregation_eps)
    sweep_cost, plane_cost = agg[:-1], agg[-1]
    best_cost, best = sweep_cost.min(dim=0)
    step = inv_depths[1] - inv_depths[0]
    inv_lo, inv_hi = 1.0 / far_m, 1.0 / m.min_depth_m
    inv_best = (inv_depths[best] + _parabolic_shift(sweep_cost, best, best_cost) * step).clamp(inv_lo, inv_hi)
    stereo_m = 1.0 / inv_best
    # Distinctness: the best cost away from the winner's immediate neighbourhood.
    index = torch.arange(m.num_hypotheses, device=best.device)[:, None, None]
    away = (index - best[None]).abs() > 2
    second = torch.where(away, sweep_cost, torch.ones_like(sweep_cost)).min(dim=0).values
    # Parallax from the widest baseline on each side (the others have less).
    widest = {min(nbrs), max(nbrs)}
    parallax = (
        torch.stack([_parallax_px(stereo_m, T, K_t, rays) for j, T in zip(nbrs, rel, strict=True) if j in widest])
        .max(dim=0)
        .values
    )
    confident = (
        (1.0 - 2.0 * best_cost >= m.min_zncc)
        & (second - best_cost >= m.min_distinctness)
        & (parallax >= m.min_parallax_px)
        & (best > 0)  # the nearest plane winning means the true depth may be nearer still
    )
    plane_ok = (
        below_horizon
        & (plane_cost <= best_cost + m.plane_margin)
        & (1.0 - 2.0 * plane_cost >= m.min_zncc)  # textureless ground is a guess, not evidence
    )
    return stereo_m, confident & ~plane_ok, plane_ok, stats[1][0, 0], sweep_cost, plane_cost


class MvsEstimator:
    """Plane-sweep depth of any frame of a drive (the set-up shared by all frames is done once)."""

    def __init__(
        self,
        frames: np.ndarray,
        K: np.ndarray,
        T_world_camera: np.ndarray,
        T_vehicle_camera: np.ndarray,
        camera_height_m: float | None,
        cfg: DepthConfig,
    ) -> None:
        m = self.m = cfg.mvs
        self.frames = frames
        self.device = torch.device(
            "cuda" if m.device == "cuda" or (m.device == "auto" and torch.cuda.is_available()) else "cpu"
        )
        n, H, W = frames.shape[:3]
        w = self.w = min(W, m.matching_width_px)
        h = self.h = max(8, round(H * w / W))
        K_lo = scale_intrinsics(np.asarray(K, dtype=np.float64), w / W, h / H)
        self.K_t = torch.as_tensor(K_lo, dtype=torch.float32, device=self.device)
        self.rays = torch.as_tensor(pixel_rays(K_lo, w, h), dtype=torch.float32, device=self.device)
        self.far_m = far_m = cfg.max_depth_m
        self.plane_lo = plane_depth(K_lo, w, h, T_vehicle_camera, camera_height_m, far_m)
        plane_lo_t = torch.from_numpy(self.plane_lo).to(self.device)
        self.plane_hi = plane_depth(K, W, H, T_vehicle_camera, camera_height_m, far_m)
        self.below_horizon = plane_lo_t < far_m
        self.inv_depths = torch.linspace(1.0 / m.min_depth_m, 1.0 / far_m, m.num_hypotheses, device=self.device)
        sweep = (1.0 / self.inv_depths)[:, None, None].expand(-1, h, w)
        self.hypotheses = torch.cat([sweep, plane_lo_t[None]], dim=0)  # the last one is the ground plane
        self.poses = np.asarray(T_world_camera, dtype=np.float64)
        self.cache = _FrameCache(frames, w, h, self.device)

    def neighbours(self, i: int) -> list[int]:
        """The frames matched against frame i; near the ends an offset past the end takes the last frame there."""
        n = self.frames.shape[0]
        return sorted({min(max(i + o, 0), n - 1) for o in self.m.neighbour_offsets} - {i})

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Depth (m) of frame i at the working resolution, and the source label of each matching-resolution pixel."""
        m, far_m, plane_lo = self.m, self.far_m, self.plane_lo
        nbrs = self.neighbours(i)
        self.cache.keep_only({i, *nbrs})
        self.cache.get(i)  # also caches the reference's colour (sky mask, upsampling)
        if not nbrs:
            return self.plane_hi.copy(), np.where(plane_lo < far_m, _FALLBACK_PLANE, _FAR)
        with torch.no_grad():
            stereo_m, use_stereo, plane_ok, texture_std, sweep_cost, plane_cost = _stereo_evidence(
                i, nbrs, self.poses, self.cache, self.K_t, self.rays, self.hypotheses, self.inv_depths,
                self.below_horizon, far_m, m,
            )  # fmt: skip
        depth_np, labels = _fuse(
            stereo_m.cpu().numpy(),
            use_stereo.cpu().numpy(),
            plane_ok.cpu().numpy(),
            plane_lo,
            sky_mask(texture_std.cpu().numpy(), self.cache.colour[i], plane_lo < far_m, m.sky_max_std),
            far_m,
            m.fill_sigma_px,
        )
        if m.plane_prior_margin > 0:
            depth_np, labels = _plane_where_no_better(
                depth_np, labels, plane_lo, far_m, sweep_cost, plane_cost, self.inv_depths, m.plane_prior_margin
            )
        depth_np = cv2.medianBlur(depth_np.astype(np.float32), 3)  # removes isolated mismatches
        inv_hi = _joint_bilateral_upsample(
            1.0 / depth_np,
            self.cache.colour[i],
            np.asarray(self.frames[i], dtype=np.float32) / 255.0,
            m.upsample == "joint_bilateral",
        )
        # No lower clip at min_depth_m: the ground plane near the camera may be nearer than the sweep's range.
        return (1.0 / np.clip(inv_hi, 1.0 / far_m, None)).astype(np.float32), labels


def temporal_median(
    depth_m: dict[int, np.ndarray], i: int, K: np.ndarray, poses: np.ndarray, far_m: float
) -> np.ndarray:
    """Frame i's depth made consistent with its neighbours': every depth map in `depth_m` is forward-warped into
    frame i's camera (z-buffered) and each pixel takes the median inverse depth of the maps that land there, its own
    included, where at least three do. A mismatch that one frame makes and its neighbours do not is voted out."""
    own = depth_m[i]
    h, w = own.shape
    stack = [1.0 / np.clip(own, 1e-3, far_m)]
    blank = torch.zeros((h, w, 3), dtype=torch.uint8)
    T_i_world = invert(poses[i])
    for j, depth in depth_m.items():
        if j == i:
            continue
        finite = np.where(depth >= far_m, np.inf, depth).astype(np.float32)  # far: a point at infinity
        out = forward_warp(blank, torch.from_numpy(finite), K, T_i_world @ poses[j], K, w, h, use_kernel=True)
        warped = out.depth_m.numpy().reshape(h, w)
        valid = out.valid.numpy().reshape(h, w).astype(bool)
        stack.append(np.where(valid, 1.0 / np.clip(np.where(np.isfinite(warped), warped, far_m), 1e-3, far_m), np.nan))
    votes = np.stack(stack)
    inv = np.nanmedian(votes, axis=0)
    # A median of two is their mean: where fewer than three maps see the pixel, the frame's own estimate stays.
    inv = np.where(np.sum(np.isfinite(votes), axis=0) >= 3, inv, stack[0])
    return (1.0 / np.clip(inv, 1.0 / far_m, None)).astype(np.float32)


def mvs_frames(
    estimator: MvsEstimator, K: np.ndarray, start: int, stop: int
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Finished depth (m) of frames start..stop-1 in order, each as (frame index, depth, label counts of the frame's
    own estimate); the result of a frame depends only on the drive, not on `start` and `stop`.

    With `mvs.temporal_window` w > 0 the estimates of up to w frames beyond each end are made too (the temporal
    median of a frame needs them); at most 2 w + 1 estimates are held at once.
    """
    n = estimator.frames.shape[0]
    window = estimator.m.temporal_window
    far_m = estimator.far_m
    raw: dict[int, np.ndarray] = {}  # per-frame estimates not yet finished: at most 2 * window + 1
    counts: dict[int, np.ndarray] = {}
    first, end = max(0, start - window), min(n, stop + window)

    def finish(i: int) -> tuple[int, np.ndarray, np.ndarray]:
        near = {j: raw[j] for j in range(i - window, i + window + 1) if j in raw}
        depth_m = temporal_median(near, i, K, estimator.poses, far_m) if len(near) > 1 else raw[i]
        return i, depth_m, counts.pop(i)

    for k in range(first, end):
        raw[k], labels = estimator.frame(k)
        if start <= k < stop:
            counts[k] = np.bincount(labels.ravel(), minlength=len(_LABELS))
        if start <= k - window < stop:
            yield finish(k - window)
        raw.pop(k - 2 * window, None)
    for i in range(max(start, end - window), stop):
        yield finish(i)


def mvs_depth(
    frames: np.ndarray,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    T_vehicle_camera: np.ndarray,
    camera_height_m: float | None,
    cfg: DepthConfig,
    out: np.ndarray,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Fill `out` with plane-sweep stereo depth fused with the ground plane, then made consistent over
    `mvs.temporal_window` frames each side; returns the fusion fractions."""
    estimator = MvsEstimator(frames, K, T_world_camera, T_vehicle_camera, camera_height_m, cfg)
    counts = np.zeros(len(_LABELS), np.int64)
    for i, depth_m, frame_counts in mvs_frames(estimator, K, 0, frames.shape[0]):
        out[i] = depth_m
        counts += frame_counts
        if progress is not None:
            progress(1)
    return fusion_fractions(counts, frames.shape[0], estimator.w, estimator.h)


def fusion_fractions(counts: np.ndarray, frame_count: int, width_px: int, height_px: int) -> dict[str, Any]:
    """The matching resolution and the share of matching-resolution pixels each fusion source gave, from the label
    counts summed over `frame_count` frames."""
    total = max(1, frame_count * width_px * height_px)
    return {
        "matching_resolution_px": [width_px, height_px],
        **{f"{name}_fraction": round(float(c) / total, 4) for name, c in zip(_LABELS, counts, strict=True)},
    }
