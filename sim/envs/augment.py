"""Episode-level photometric augmentation of the uint8 observation: gamma, brightness, contrast, saturation, and
whole episodes in grey (a grey camera, as every KITTI drive is, seen by a policy trained on colour worlds)."""

from __future__ import annotations

from dataclasses import dataclass

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
