"""The synth world's per-pixel pass as one compiled loop (numba): texture, shading, aerial haze and uint8 output.

`sim.raster.Rasterizer` resolves textured scenes through a chain of whole-image torch operations (gathers of 24
attribute rows, bilinear texture fetches, Blinn–Phong, then the haze blend and the uint8 conversion in
`SynthWorld.render_full`): on one core that was about 100 ms of a 960x600 frame. This loop evaluates the same
float32 formulas per covered pixel of the z-buffer that `sim.raster_kernel.depth_test` fills: perspective-correct
barycentrics from the set-up table, the interpolated attributes, the bilinear (clamp-to-edge) texture lookup of
`raster._sample_bilinear`, the shading of `sim/shading.py`, then `rgb + haze (horizon - rgb)` with
`haze = 1 - exp(-depth / haze distance)`, clamped and rounded to uint8.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from drivesim.sim.raster_kernel import normalized, pixel_barycentrics


@njit(cache=True, nogil=True, inline="always")
def _texel(texels: np.ndarray, index: int, c: int) -> float:
    """Channel c (0 r, 1 g, 2 b) in [0, 255] of a packed RGB8 texel (r in the low byte)."""
    return np.float32((texels[index] >> (8 * c)) & 0xFF)


@njit(cache=True, nogil=True, inline="always")
def _lerp(a: float, b: float, w: float) -> float:
    """torch.lerp's formula (exact at both ends)."""
    return a + w * (b - a) if w < np.float32(0.5) else b - (b - a) * (np.float32(1.0) - w)


@njit(cache=True, nogil=True)
def _sample(texels: np.ndarray, info: np.ndarray, tex: int, u: float, v: float) -> tuple[float, float, float]:
    """Bilinear lookup with clamp-to-edge of texture `tex` at (u, v): rgb in [0, 1] (`raster._sample_bilinear`)."""
    f32 = np.float32
    offset, tw, th = info[0, tex], info[1, tex], info[2, tex]
    x = u * f32(tw) - f32(0.5)
    y = v * f32(th) - f32(0.5)
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx, fy = x - x0, y - y0
    ix, iy = int(x0), int(y0)
    xa, xb = min(max(ix, 0), tw - 1), min(max(ix + 1, 0), tw - 1)
    ya = offset + min(max(iy, 0), th - 1) * tw
    yb = offset + min(max(iy + 1, 0), th - 1) * tw
    r = g = b = f32(0.0)
    for c in range(3):
        top = _lerp(_texel(texels, ya + xa, c), _texel(texels, ya + xb, c), fx)
        bottom = _lerp(_texel(texels, yb + xa, c), _texel(texels, yb + xb, c), fx)
        value = _lerp(top, bottom, fy) * f32(1.0 / 255.0)
        if c == 0:
            r = value
        elif c == 1:
            g = value
        else:
            b = value
    return r, g, b


@njit(cache=True, nogil=True, inline="always")
def _camera_normal(
    attributes: np.ndarray, s: int, b0: float, b1: float, b2: float, R_cam_world: np.ndarray
) -> tuple[float, float, float]:
    """Scene triangle s's normal interpolated at barycentrics (b0, b1, b2), in the camera frame, unit length."""
    nw0 = attributes[0, s] * b0 + attributes[8, s] * b1 + attributes[16, s] * b2
    nw1 = attributes[1, s] * b0 + attributes[9, s] * b1 + attributes[17, s] * b2
    nw2 = attributes[2, s] * b0 + attributes[10, s] * b1 + attributes[18, s] * b2
    return normalized(
        R_cam_world[0, 0] * nw0 + R_cam_world[0, 1] * nw1 + R_cam_world[0, 2] * nw2,
        R_cam_world[1, 0] * nw0 + R_cam_world[1, 1] * nw1 + R_cam_world[1, 2] * nw2,
        R_cam_world[2, 0] * nw0 + R_cam_world[2, 1] * nw1 + R_cam_world[2, 2] * nw2,
    )


@njit(cache=True, nogil=True, inline="always")
def _to_viewer(K_inv: np.ndarray, fx: float, fy: float) -> tuple[float, float, float]:
    """The unit direction from pixel (fx, fy)'s surface point back to the camera, in the camera frame."""
    return normalized(
        -(K_inv[0, 0] * fx + K_inv[0, 1] * fy + K_inv[0, 2]),
        -(K_inv[1, 0] * fx + K_inv[1, 1] * fy + K_inv[1, 2]),
        -(K_inv[2, 0] * fx + K_inv[2, 1] * fy + K_inv[2, 2]),
    )


@njit(cache=True, nogil=True)
def shade_world(
    depth: np.ndarray,
    winner: np.ndarray,
    table: np.ndarray,
    source: np.ndarray,
    attributes: np.ndarray,
    material: np.ndarray,
    object_ids: np.ndarray,
    texture_index: np.ndarray,
    texels: np.ndarray,
    texture_info: np.ndarray,
    R_cam_world: np.ndarray,
    K_inv: np.ndarray,
    light: np.ndarray,
    haze_distance_m: float,
    horizon_rgb: np.ndarray,
    width_px: int,
    rgb_out: np.ndarray,
    id_out: np.ndarray,
) -> int:
    """Colour (H*W, 3) uint8 and object ids (H*W,) int32 of every covered pixel of the z-buffer (depth (H*W,)
    float32, winner (H*W,) int64 candidate or -1); uncovered pixels get id -1 and their colour is left for the sky.
    Returns the number of uncovered pixels.

    table (13, n) the set-up table (`raster_kernel.setup`), source (n,) each candidate's scene triangle; attributes
    (24, T), material (7, T), object_ids (T,), texture_index (T,) (-1 untextured), texels (N,) int32 and texture_info
    (3, X) the packed scene's tables (`raster.PackedScene`); R_cam_world (3, 3); K_inv (3, 3); light (9,) ambient,
    unit light direction (camera frame), light colour; horizon_rgb (3,) the haze colour.
    """
    f32 = np.float32
    inv_haze = f32(1.0) / f32(haze_distance_m)
    l0, l1, l2 = -light[3], -light[4], -light[5]
    uncovered = 0
    for p in range(winner.shape[0]):
        t = winner[p]
        if t < 0:
            id_out[p] = -1
            uncovered += 1
            continue
        x, y = p % width_px, p // width_px
        b0, b1, b2 = pixel_barycentrics(table, t, x, y)
        s = source[t]
        n0, n1, n2 = _camera_normal(attributes, s, b0, b1, b2, R_cam_world)
        v0, v1, v2 = _to_viewer(K_inv, f32(x), f32(y))
        if n0 * v0 + n1 * v1 + n2 * v2 < 0:  # two-sided: the normal turned towards the viewer
            n0, n1, n2 = -n0, -n1, -n2
        h0, h1, h2 = normalized(v0 + l0, v1 + l1, v2 + l2)
        n_dot_l = max(n0 * l0 + n1 * l1 + n2 * l2, f32(0.0))
        n_dot_h = max(n0 * h0 + n1 * h1 + n2 * h2, f32(0.0))
        metalness, roughness, unlit = material[4, s], material[5, s], material[6, s]
        exponent = f32(1.0) + material[3, s] * (f32(1.0) - roughness) ** 2
        highlight = n_dot_h**exponent if n_dot_l > 0 else f32(0.0)
        diffuse_weight = f32(1.0) - metalness
        tr = tg = tb = f32(1.0)
        if texture_index[s] >= 0:
            u = attributes[6, s] * b0 + attributes[14, s] * b1 + attributes[22, s] * b2
            v = attributes[7, s] * b0 + attributes[15, s] * b1 + attributes[23, s] * b2
            tr, tg, tb = _sample(texels, texture_info, texture_index[s], u, v)
        haze = -np.expm1(-depth[p] * inv_haze)
        for c in range(3):
            base = attributes[3 + c, s] * b0 + attributes[11 + c, s] * b1 + attributes[19 + c, s] * b2
            base *= tr if c == 0 else (tg if c == 1 else tb)
            f0 = diffuse_weight * material[c, s] + metalness * base
            lit = light[c] * base + light[6 + c] * (f0 * highlight + diffuse_weight * base * n_dot_l)
            value = min(max(lit + unlit * (base - lit), f32(0.0)), f32(1.0))
            value = min(max(value + haze * (horizon_rgb[c] - value), f32(0.0)), f32(1.0))
            rgb_out[p, c] = np.uint8(value * f32(255.0) + f32(0.5))
        id_out[p] = object_ids[s]
    return uncovered


@njit(cache=True, nogil=True)
def paint_sky(
    winner: np.ndarray,
    K_inv: np.ndarray,
    R_world_camera: np.ndarray,
    clouds: np.ndarray,
    sky: np.ndarray,
    width_px: int,
    rgb_out: np.ndarray,
) -> None:
    """Colour (H*W, 3) uint8 of the uncovered pixels (winner -1): a blue gradient from the hazy horizon to the
    zenith, clouds on a layer above fading out toward the horizon, hazy ground below the horizon.

    clouds (N, N) cloud opacity on a periodic tile; sky (12,) float32: zenith rgb, horizon rgb, cloud rgb, cloud
    height (m), cloud tile size (m), two unused.
    """
    f32 = np.float32
    n = clouds.shape[0]
    height, tile = sky[9], sky[10]
    for p in range(winner.shape[0]):
        if winner[p] >= 0:
            continue
        fx, fy = f32(p % width_px), f32(p // width_px)
        r0 = K_inv[0, 0] * fx + K_inv[0, 1] * fy + K_inv[0, 2]
        r1 = K_inv[1, 0] * fx + K_inv[1, 1] * fy + K_inv[1, 2]
        r2 = K_inv[2, 0] * fx + K_inv[2, 1] * fy + K_inv[2, 2]
        d0, d1, d2 = normalized(
            R_world_camera[0, 0] * r0 + R_world_camera[0, 1] * r1 + R_world_camera[0, 2] * r2,
            R_world_camera[1, 0] * r0 + R_world_camera[1, 1] * r1 + R_world_camera[1, 2] * r2,
            R_world_camera[2, 0] * r0 + R_world_camera[2, 1] * r1 + R_world_camera[2, 2] * r2,
        )
        cover = f32(0.0)
        if d2 > f32(0.01):
            i = int(np.floor(d0 * (height / d2) / tile * f32(n))) % n
            j = int(np.floor(d1 * (height / d2) / tile * f32(n))) % n
            cover = clouds[j, i] * min(max((d2 - f32(0.03)) * f32(4.0), f32(0.0)), f32(1.0))
        t = min(max(d2, f32(0.0)), f32(1.0)) ** f32(0.6)
        for c in range(3):
            value = sky[3 + c] * (f32(1.0) - t) + sky[c] * t
            value = value * (f32(1.0) - cover) + sky[6 + c] * cover
            if d2 < 0:
                value = sky[3 + c] * f32(0.85)
            rgb_out[p, c] = np.uint8(value * f32(255.0) + f32(0.5))
