"""The camera's own look on inserted cars: edges blended with the background, the frame's blur and its grain.

A rasterized car is point-sampled: its edges step from car to background within one pixel and its faces are
noiseless, while every recorded pixel integrates light over its area through the lens and carries sensor noise. After
compositing (and harmonization), `apply_camera_look_` makes the car's pixels look taken by the same camera:

1. blur: the car and a one-pixel band around it are replaced by the composited view blurred with a Gaussian of the
   frame's own blur (`frame_blur_sigma`), at least `EDGE_SIGMA_PX`: its edge pixels become blends of car and
   background (a post-filter anti-aliasing), its faces as soft as the recorded surfaces;
2. grain: the car's pixels get zero-mean noise of the frame's own pixel-level variation (`frame_noise_sigma`), the
   same on every channel (a gray camera's car stays gray), from a fixed noise tile (so a view is a pure function of
   its inputs). At the recording's size that variation is mostly sensor noise. In frames reduced to a world's size
   the block mean removes most of the noise, and what is left is mostly fine texture, which a flat car lacks just
   as much.

The estimates are made once per recorded frame (`look_of_frame`); applying them costs a few OpenCV calls over the
car's box.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "EDGE_SIGMA_PX", "CameraLook", "apply_camera_look_", "frame_blur_sigma", "frame_noise_sigma", "look_of_frame",
    "look_of_frames",
]  # fmt: skip

EDGE_SIGMA_PX = 0.5
"""Least blur (Gaussian sigma, px) applied to an inserted car: about a pixel's own area, so its edges blend."""
MAX_BLUR_SIGMA_PX = 3.0  # a frame blurrier than this is clamped (the estimate is unreliable there)
_SOBEL_SIGMA_PX = 0.72  # the blur a Sobel gradient adds to an edge by itself (measured on synthetic step edges)
_REBLUR_SIGMA_PX = 1.0
_EDGE_PERCENTILE = 99.0  # the strongest gradients, the centres of the frame's sharpest edges
_NOISE_TILE_PX = 128
_NOISE_TILE = np.random.default_rng(0).standard_normal((_NOISE_TILE_PX, _NOISE_TILE_PX)).astype(np.float32)
# Immerkaer's noise-estimation mask: zero on any linear ramp, its response to white noise has 6 sigma.
_NOISE_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)


@dataclass(frozen=True)
class CameraLook:
    """What the camera does to a pixel: `blur_sigma_px` (Gaussian sigma of its blur, px) and `noise_sigma`
    (standard deviation of its noise, grey levels of 255)."""

    blur_sigma_px: float = EDGE_SIGMA_PX
    noise_sigma: float = 0.0


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    return image


def frame_noise_sigma(image: np.ndarray) -> float:
    """The pixel-level variation of a uint8 frame (h, w[, 3]) in grey levels (its noise, plus texture finer than a
    few pixels): the median absolute response of Immerkaer's Laplacian-difference mask (blind to flat and linear
    shading) over 6 sigma, robust to the frame's edges."""
    response = cv2.filter2D(_gray(image).astype(np.float32), -1, _NOISE_MASK)[1:-1, 1:-1]
    return float(np.median(np.abs(response)) / (0.6745 * 6.0))


def frame_blur_sigma(image: np.ndarray) -> float:
    """The blur of a uint8 frame (h, w[, 3]) as a Gaussian sigma (px), from its sharpest edges: blurring a step edge
    of sigma s by r lowers its peak gradient by s / sqrt(s^2 + r^2), so the ratio R of the peak gradients before and
    after a re-blur gives s = r / sqrt(R^2 - 1); the gradient operator's own blur is taken off. In [0, 3]."""
    gray = _gray(image).astype(np.float32)

    def gradient(x: np.ndarray) -> np.ndarray:
        return cv2.magnitude(cv2.Sobel(x, cv2.CV_32F, 1, 0), cv2.Sobel(x, cv2.CV_32F, 0, 1))

    sharp = gradient(gray)
    reblurred = gradient(cv2.GaussianBlur(gray, (0, 0), _REBLUR_SIGMA_PX))
    edges = sharp >= max(np.percentile(sharp, _EDGE_PERCENTILE), 1e-3)
    ratio = float(sharp[edges].sum() / max(reblurred[edges].sum(), 1e-6))
    if ratio <= 1.0:
        return MAX_BLUR_SIGMA_PX
    apparent = _REBLUR_SIGMA_PX / np.sqrt(ratio * ratio - 1.0)
    return float(np.clip(np.sqrt(max(apparent**2 - _SOBEL_SIGMA_PX**2, 0.0)), 0.0, MAX_BLUR_SIGMA_PX))


def look_of_frame(image: np.ndarray, scale: float = 1.0) -> CameraLook:
    """The camera look of a recorded uint8 frame, for a view drawn at `scale` view pixels per frame pixel (blur
    scales with it; the noise of a pixel does not)."""
    return CameraLook(blur_sigma_px=frame_blur_sigma(image) * scale, noise_sigma=frame_noise_sigma(image))


def look_of_frames(frames: np.ndarray, factor: int = 1, scale: float = 1.0, samples: int = 8) -> CameraLook:
    """The camera look of a drive's uint8 frames (N, h, w, 3): the median blur and noise of `samples` frames spread
    over the drive, each first reduced by the integer `factor` (block mean, as the views' warp reads them), the blur
    given at `scale` view pixels per reduced frame pixel. A camera's look is its own, not a frame's."""
    n = len(frames)
    if n == 0:
        return CameraLook()
    blur, noise = [], []
    for i in np.unique(np.linspace(0, n - 1, samples).round().astype(int)):
        image = _gray(np.asarray(frames[i]))
        if factor > 1:
            h, w = image.shape[0] - image.shape[0] % factor, image.shape[1] - image.shape[1] % factor
            image = cv2.resize(image[:h, :w], (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        blur.append(frame_blur_sigma(image))
        noise.append(frame_noise_sigma(image))
    return CameraLook(blur_sigma_px=float(np.median(blur)) * scale, noise_sigma=float(np.median(noise)))


def apply_camera_look_(rgb: np.ndarray, mask: np.ndarray, look: CameraLook) -> None:
    """Blur and grain, in place, the inserted car of a uint8 view `rgb` (h, w, 3) where `mask` (h, w) bool (module
    docstring): the car and a one-pixel band around it take the blurred view, the car's pixels the frame's noise."""
    left, top, width, height = cv2.boundingRect(mask.view(np.uint8))
    if width == 0:
        return
    sigma = max(float(look.blur_sigma_px), EDGE_SIGMA_PX)
    reach = int(np.ceil(3.0 * sigma))  # the blur's kernel radius: pixels this far out feed the band
    h, w = mask.shape
    y0, y1 = max(top - reach - 1, 0), min(top + height + reach + 1, h)
    x0, x1 = max(left - reach - 1, 0), min(left + width + reach + 1, w)
    box = rgb[y0:y1, x0:x1]
    car = np.ascontiguousarray(mask[y0:y1, x0:x1]).view(np.uint8)
    band = cv2.dilate(car, np.ones((3, 3), np.uint8))
    blurred = cv2.GaussianBlur(box, (2 * reach + 1, 2 * reach + 1), sigma)
    cv2.copyTo(blurred, band, box)
    if look.noise_sigma <= 0.0:
        return
    bh, bw = box.shape[:2]
    up, down = _noise(y0, x0, bh, bw, float(look.noise_sigma))
    cv2.add(box, up, dst=box, mask=car)  # saturating uint8 arithmetic under the car only, in place
    cv2.subtract(box, down, dst=box, mask=car)


def _noise(y0: int, x0: int, h: int, w: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(h, w, 3) uint8 noise of standard deviation `sigma` as its positive and negative parts, equal on the three
    channels, cut from the noise tile at an offset given by the box's corner (tiled where the box is larger)."""
    tiles = _scaled_tiles(sigma)
    span = tiles[0].shape[0]
    oy, ox = y0 % _NOISE_TILE_PX, x0 % _NOISE_TILE_PX
    if oy + h <= span and ox + w <= tiles[0].shape[1]:
        return tiles[0][oy : oy + h, ox : ox + w], tiles[1][oy : oy + h, ox : ox + w]
    reps = (-(-(oy + h) // span), -(-(ox + w) // span), 1)
    return tuple(np.tile(t, reps)[oy : oy + h, ox : ox + w] for t in tiles)  # type: ignore[return-value]


@functools.lru_cache(maxsize=8)
def _scaled_tiles(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The noise tile scaled to `sigma`, rounded, repeated 2 x 2 (so any box up to the tile's size is one slice), as
    (positive part, negative part) (2T, 2T, 3) uint8: made once per look."""
    noise = np.rint(np.tile(_NOISE_TILE, (2, 2)) * sigma).clip(-255, 255)
    return tuple(
        np.ascontiguousarray(np.repeat(part.astype(np.uint8)[..., None], 3, axis=-1))
        for part in (np.maximum(noise, 0), np.maximum(-noise, 0))
    )  # type: ignore[return-value]
