"""Episode-level augmentation of the uint8 observation: photometric (gamma, brightness, contrast, saturation, and
whole episodes in grey: a grey camera, as every KITTI drive is, seen by a policy trained on colour worlds), and in
image space (`ViewJitter`: camera pitch, blur, sensor noise, erased rectangles)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass
class Augmentation:
    """One episode's draw; `apply` maps (..., 3) uint8 images."""

    gamma: float = 1.0
    brightness: float = 0.0
    contrast: float = 1.0
    saturation: float = 1.0

    @classmethod
    def sample(
        cls,
        rng: np.random.Generator,
        gamma,  # noqa: ANN001
        brightness,  # noqa: ANN001
        contrast,  # noqa: ANN001
        saturation,  # noqa: ANN001
        grey_probability: float = 0.0,
    ) -> Augmentation:
        """A draw from the given (low, high) ranges; with probability `grey_probability` the episode is grey
        (saturation 0). The grey draw is made only when that probability is above 0, so the draws of a config
        without it stay as they were."""
        draw = cls(*(float(rng.uniform(*r)) for r in (gamma, brightness, contrast, saturation)))
        if grey_probability > 0.0 and rng.uniform() < grey_probability:
            draw = cls(draw.gamma, draw.brightness, draw.contrast, 0.0)
        return draw

    def __post_init__(self) -> None:
        # Gamma, brightness and contrast act per channel value: one 256-entry table, applied by indexing.
        v = np.arange(256, dtype=np.float32) / 255.0
        v = v**self.gamma + self.brightness
        v = (v - 0.5) * self.contrast + 0.5
        self._lut = np.clip(np.rint(v * 255.0), 0, 255).astype(np.uint8)
        # new = grey + s (c - grey) = (1 - s) luma . rgb + s c, as a 3 x 3 matrix acting on (r, g, b)
        luma = np.array([0.299, 0.587, 0.114])
        self._saturation_matrix = (1.0 - self.saturation) * np.tile(luma, (3, 1)) + self.saturation * np.eye(3)

    @property
    def identity(self) -> bool:
        """True when it changes nothing."""
        return self.gamma == 1.0 and self.brightness == 0.0 and self.contrast == 1.0 and self.saturation == 1.0

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """The augmented image (same shape, uint8): the table, then the saturation, a linear map of each pixel
        toward its grey value (ITU-R 601 luma), rounded and saturated to 0-255 (OpenCV's vectorized LUT and
        transform: a few microseconds for the policy's image)."""
        if self.identity:
            return rgb
        pixels = np.ascontiguousarray(rgb).reshape(-1, 1, 3)
        out = cv2.LUT(pixels, self._lut)
        if self.saturation != 1.0:
            out = cv2.transform(out, self._saturation_matrix)
        return out.reshape(rgb.shape)


NOISE_SHIFT_PX = 16
"""A noisy episode draws its noise once, a field this many pixels larger than the image each way, and adds a window
of it at a random offset at each step: fresh-looking noise every step for the cost of an addition (drawing
10^4-10^5 normal numbers per step took 0.3-0.5 ms, more than the rest of a lane step's observation)."""


@dataclass
class ViewJitter:
    """One episode's image-space draw, applied after `Augmentation`: a camera pitch shown as the vertical shift of
    the image it makes, a Gaussian blur, rectangles erased at random places, and sensor noise; the rectangles and
    the noise change at every call (their own generator, so the episode's other draws do not depend on how many
    steps it ran)."""

    shift_rows: float = 0.0
    blur_sigma_px: float = 0.0
    noise_std: float = 0.0
    cutout_count: tuple[int, int] = (0, 0)
    """Range (low, high, both included) of the number of rectangles erased at each call."""
    cutout_size: tuple[float, float] = (0.1, 0.4)
    """Range of each erased rectangle's width and height, fractions of the image's."""
    noise_rng: np.random.Generator | None = field(default=None, compare=False, repr=False)
    _noise_field: np.ndarray | None = field(default=None, init=False, compare=False, repr=False)

    @classmethod
    def sample(
        cls,
        rng: np.random.Generator,
        pitch_deg: float,
        focal_rows_px: float,
        blur_sigma_px: tuple[float, float],
        noise_std: tuple[float, float],
        cutout_count: tuple[int, int],
        cutout_size: tuple[float, float],
    ) -> ViewJitter:
        """A pitch in +-`pitch_deg` (as rows at the image's vertical focal length `focal_rows_px`: a small pitch
        moves the whole image by about f tan(pitch)), a blur and a noise level from their (low, high) ranges; the
        cutout ranges are kept as given (the rectangles are drawn at each call)."""
        pitch_rad = np.radians(float(rng.uniform(-pitch_deg, pitch_deg)))
        return cls(
            shift_rows=float(focal_rows_px * np.tan(pitch_rad)),
            blur_sigma_px=float(rng.uniform(*blur_sigma_px)),
            noise_std=float(rng.uniform(*noise_std)),
            cutout_count=cutout_count,
            cutout_size=cutout_size,
            noise_rng=np.random.default_rng(int(rng.integers(2**63))),
        )

    @property
    def identity(self) -> bool:
        """True when it changes nothing."""
        return (
            self.shift_rows == 0.0 and self.blur_sigma_px == 0.0 and self.noise_std == 0.0 and self.cutout_count[1] == 0
        )

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """The (h, w, 3) uint8 image shifted down by `shift_rows` (sub-pixel, edge rows repeated), blurred, with
        `cutout_count` rectangles erased (each to one random colour), and with Gaussian noise of `noise_std` x 255
        added (a new window of the episode's noise field at each call), rounded and saturated to 0-255."""
        if self.identity:
            return rgb
        out = np.ascontiguousarray(rgb)
        if self.shift_rows != 0.0:
            shift = np.float32([[1.0, 0.0, 0.0], [0.0, 1.0, self.shift_rows]])
            out = cv2.warpAffine(out, shift, (out.shape[1], out.shape[0]), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        if self.blur_sigma_px > 0.0:
            out = cv2.GaussianBlur(out, (0, 0), self.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
        if self.cutout_count[1] > 0:
            out = self._erase_rectangles(out)
        if self.noise_std > 0.0:
            out = self._add_noise(out)
        return out

    def _erase_rectangles(self, image: np.ndarray) -> np.ndarray:
        """A copy of `image` with a drawn number of rectangles, each of a drawn size and place, set to one random
        colour each (random erasing, as RAD's cutout-colour: a policy that must drive with any part of its view
        hidden cannot lean on one region's scenery)."""
        if self.noise_rng is None:
            self.noise_rng = np.random.default_rng()
        rng, (h, w) = self.noise_rng, image.shape[:2]
        out = image.copy()
        for _ in range(int(rng.integers(self.cutout_count[0], self.cutout_count[1] + 1))):
            rect_h = max(1, round(h * rng.uniform(*self.cutout_size)))
            rect_w = max(1, round(w * rng.uniform(*self.cutout_size)))
            top, left = int(rng.integers(0, h - rect_h + 1)), int(rng.integers(0, w - rect_w + 1))
            out[top : top + rect_h, left : left + rect_w] = rng.integers(0, 256, size=out.shape[2:], dtype=np.uint8)
        return out

    def _add_noise(self, image: np.ndarray) -> np.ndarray:
        """`image` plus a window of the episode's noise field (drawn at the first call, see NOISE_SHIFT_PX) at a
        random offset, saturated to 0-255."""
        if self.noise_rng is None:
            self.noise_rng = np.random.default_rng()
        h, w = image.shape[:2]
        if self._noise_field is None or self._noise_field.shape[:2] != (h + NOISE_SHIFT_PX, w + NOISE_SHIFT_PX):
            size = (h + NOISE_SHIFT_PX, w + NOISE_SHIFT_PX, *image.shape[2:])
            noise = self.noise_rng.standard_normal(size, dtype=np.float32) * (self.noise_std * 255.0)
            self._noise_field = np.rint(noise).astype(np.int16)
        dy, dx = self.noise_rng.integers(0, NOISE_SHIFT_PX + 1, size=2)
        window = self._noise_field[dy : dy + h, dx : dx + w]
        return np.clip(image.astype(np.int16) + window, 0, 255).astype(np.uint8)
