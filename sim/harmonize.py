"""Image harmonization of inserted cars (DESIGN §4 step 5): make a rendered car look like it belongs in the frame.

A harmonizer takes a batch of composited views and the mask of the inserted car and returns the adjusted views; only
pixels under the mask may change. The default is statistical (per-channel colour statistics of the car moved toward
those of its surroundings, Reinhard-style transfer). `LearnedHarmonizer` runs a small network trained on the synthetic
world's true look of inserted cars (`models/harmonizer.onnx`, made by `benchmarks/bench_harmonizer.py`); any other
learned model (the paper used iDIH, whose weights are not available offline) plugs in as an ONNX graph through
`OnnxHarmonizer`.

Why not a library call: scikit-image's `exposure.match_histograms` matches whole images without masks and fully
(a red car would become road-grey); what is needed here is a partial, masked, batched transfer of mean and spread
toward a ring around the car, which is a few torch operations (batched), or OpenCV's masked dilation, mean / standard
deviation and colour transform on one uint8 view in place (the simulator's CPU path).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import torch
from torch.nn.functional import max_pool2d

__all__ = [
    "HARMONIZERS",
    "Harmonizer",
    "LearnedHarmonizer",
    "OnnxHarmonizer",
    "StatisticalHarmonizer",
    "harmonize_view_uint8_",
    "make_harmonizer",
]

HARMONIZERS = ("statistical", "learned")
LEARNED_MODEL = Path(__file__).resolve().parent / "models" / "harmonizer.onnx"
LEARNED_RING_PX = 6
"""Width of the ring of surrounding pixels the learned network pools around the car."""
LEARNED_SCALE = 2
"""The learned network reads the view at 1 / LEARNED_SCALE of its resolution (an odd side is padded)."""
# The ring plus the reach of the two feature convolutions pooled over it (3x3 each, at half resolution) plus one
# half-resolution pixel of grid alignment; the gain head reaches less far.
_LEARNED_MARGIN_PX = LEARNED_RING_PX + LEARNED_SCALE * 2 + LEARNED_SCALE


class Harmonizer(Protocol):
    """Harmonizes inserted objects: `(rgb (B, h, w, 3) float [0, 1], mask (B, h, w) bool) -> rgb` of the same shape;
    pixels outside the mask are returned unchanged."""

    def __call__(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor: ...


class StatisticalHarmonizer:
    """Moves the car's per-channel mean and standard deviation toward those of a ring of surrounding pixels.

    :param strength: 0 = no change, 1 = the car takes the surroundings' statistics fully. Partial by default: the
        car keeps its own paint colour but takes on the scene's exposure and colour cast.
    :param ring_px: width of the ring of surrounding pixels (outside the mask) the target statistics come from.
    :param max_gain: bound on the per-channel contrast gain (std ratio), so a flat background cannot erase the car.
    """

    def __init__(self, strength: float = 0.4, ring_px: int = 6, max_gain: float = 1.5):
        self.strength = float(strength)
        self.ring_px = int(ring_px)
        self.max_gain = float(max_gain)

    def __call__(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Harmonized copy of `rgb` (B, h, w, 3) float [0, 1] under `mask` (B, h, w) bool."""
        rows = mask.any(dim=2).any(dim=0).nonzero()
        cols = mask.any(dim=1).any(dim=0).nonzero()
        if rows.numel() == 0:
            return rgb
        # Only the box around all masks (plus the ring) matters: the rest of the images is left as it is.
        r = self.ring_px
        y0, y1 = max(int(rows[0]) - r, 0), int(rows[-1]) + r + 1
        x0, x1 = max(int(cols[0]) - r, 0), int(cols[-1]) + r + 1
        out = rgb.clone()
        out[:, y0:y1, x0:x1] = self._harmonize(rgb[:, y0:y1, x0:x1], mask[:, y0:y1, x0:x1])
        return out

    def harmonize_view_uint8_(self, rgb: np.ndarray, mask: np.ndarray) -> None:
        """The same transfer on one view, in place: `rgb` (h, w, 3) uint8 changes under `mask` (h, w) bool.

        The CPU path of the simulator: OpenCV's masked dilation and mean / standard deviation over the car's box do
        in tens of microseconds what the batched torch path does in about half a millisecond of per-call costs."""
        left, top, width, height = cv2.boundingRect(mask.view(np.uint8))  # the car's box: one pass, no copies
        if width == 0:
            return
        r = self.ring_px
        y0, y1 = max(top - r, 0), top + height + r
        x0, x1 = max(left - r, 0), left + width + r
        box = rgb[y0:y1, x0:x1]
        car = mask[y0:y1, x0:x1].view(np.uint8)
        ring = cv2.dilate(car, np.ones((2 * r + 1, 2 * r + 1), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        ring -= car
        if not ring.any():
            return
        car_mean, car_std = (v[:, 0] / 255.0 for v in cv2.meanStdDev(box, mask=car))
        ring_mean, ring_std = (v[:, 0] / 255.0 for v in cv2.meanStdDev(box, mask=ring))
        # As in the torch path: spreads floored at 1e-4 (a flat car or ring), the gain bounded.
        ratio = np.maximum(ring_std, 1e-4) / np.maximum(car_std, 1e-4)
        gain = np.clip(ratio, 1.0 / self.max_gain, self.max_gain)
        gain = 1.0 + self.strength * (gain - 1.0)
        target_mean = car_mean + self.strength * (ring_mean - car_mean)
        # (p - car_mean) * gain + target_mean per channel, on 0-255 values: one affine colour transform, which
        # OpenCV rounds and saturates to uint8 as the torch path's clamp and rounding do; copied under the mask.
        affine = np.zeros((3, 4))
        affine[:, :3] = np.diag(gain)
        affine[:, 3] = 255.0 * (target_mean - car_mean * gain)
        cv2.copyTo(cv2.transform(box, affine), car, box)

    def _harmonize(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(rgb.dtype)[:, None]  # (B, 1, h, w)
        k, r = 2 * self.ring_px + 1, self.ring_px
        dilated = max_pool2d(max_pool2d(m, (1, k), stride=1, padding=(0, r)), (k, 1), stride=1, padding=(r, 0))
        ring = (dilated - m)[:, 0]  # (B, h, w) 1 in the ring (a square structuring element)
        m = m[:, 0]

        def stats(weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            n = weight.sum(dim=(1, 2))  # (B,)
            w = weight[..., None]
            mean = (rgb * w).sum(dim=(1, 2)) / n.clamp_min(1.0)[:, None]
            var = ((rgb - mean[:, None, None]) ** 2 * w).sum(dim=(1, 2)) / n.clamp_min(1.0)[:, None]
            return mean, var.clamp_min(1e-8).sqrt(), n

        car_mean, car_std, car_n = stats(m)
        ring_mean, ring_std, ring_n = stats(ring)
        gain = (ring_std / car_std).clamp(1.0 / self.max_gain, self.max_gain)
        gain = 1.0 + self.strength * (gain - 1.0)
        target_mean = car_mean + self.strength * (ring_mean - car_mean)
        usable = ((car_n > 0) & (ring_n > 0)).to(rgb.dtype)[:, None]  # (B, 1): views without a car stay as they are
        gain = 1.0 + usable * (gain - 1.0)
        target_mean = car_mean + usable * (target_mean - car_mean)
        adjusted = (rgb - car_mean[:, None, None]) * gain[:, None, None] + target_mean[:, None, None]
        return torch.where(mask[..., None], adjusted.clamp_(0.0, 1.0), rgb)


def _cpu_session(path: Path):
    """A one-thread, sequential onnxruntime session of the graph at `path` (one line's error when it is missing or
    unusable): small graphs called once per view gain nothing from threads but their hand-offs."""
    import onnxruntime

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such harmonization model")
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
    try:
        return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own exception types for unreadable graphs
        raise ValueError(f"{path}: not a usable ONNX model ({str(error).splitlines()[0]})") from None


class OnnxHarmonizer:
    """A learned harmonization model run with onnxruntime.

    The graph takes either one input (B, 4, h, w) float32 (RGB in [0, 1] and the mask as a fourth channel, the iDIH
    layout) or two inputs, image (B, 3, h, w) and mask (B, 1, h, w), in that order, and returns (B, 3, h, w) float32
    RGB in [0, 1]. Its output is used under the mask only.

    :param path: the .onnx file (FileNotFoundError / ValueError with one line when missing or unusable).
    """

    def __init__(self, path: Path | str):
        self.session = _cpu_session(Path(path))
        self.input_names = [i.name for i in self.session.get_inputs()]
        if len(self.input_names) not in (1, 2):
            raise ValueError(
                f"{path}: a harmonization model takes 1 or 2 inputs, this one takes {len(self.input_names)}"
            )

    def __call__(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Harmonized copy of `rgb` (B, h, w, 3) float [0, 1] under `mask` (B, h, w) bool."""
        image = rgb.permute(0, 3, 1, 2).to(torch.float32).cpu().numpy()
        m = mask[:, None].to(torch.float32).cpu().numpy()
        if len(self.input_names) == 1:
            feeds = {self.input_names[0]: np.ascontiguousarray(np.concatenate([image, m], axis=1))}
        else:
            feeds = {self.input_names[0]: np.ascontiguousarray(image), self.input_names[1]: m}
        out = self.session.run(None, feeds)[0]
        if out.shape != image.shape:
            raise ValueError(f"the harmonization model returned {out.shape}, expected {image.shape}")
        harmonized = torch.from_numpy(np.clip(out, 0.0, 1.0)).permute(0, 2, 3, 1).to(rgb.device, rgb.dtype)
        return torch.where(mask[..., None], harmonized, rgb)


def harmonize_view_uint8_(harmonizer: Harmonizer, rgb: np.ndarray, mask: np.ndarray) -> None:
    """Harmonize one uint8 view `rgb` (h, w, 3) under `mask` (h, w) bool in place, with any harmonizer: its own
    in-place uint8 path where it has one, else its float batch call (rounded back to uint8)."""
    in_place = getattr(harmonizer, "harmonize_view_uint8_", None)
    if in_place is not None:
        in_place(rgb, mask)
        return
    view = torch.from_numpy(rgb)[None]
    car = torch.from_numpy(mask)[None]
    harmonized = harmonizer(view.to(torch.float32) / 255.0, car)
    out = torch.where(car[..., None], (harmonized * 255.0 + 0.5).clamp_(0, 255).to(torch.uint8), view)
    rgb[...] = out[0].numpy()


class LearnedHarmonizer:
    """The learned harmonizer (`LEARNED_MODEL`). Its graph, run with onnxruntime, reads one uint8 view or box
    (h, w, 3) and the car's mask (h, w) uint8, h and w even, and returns a 3 x 4 colour map's parameters and a
    half-resolution brightness gain; OpenCV applies them to the car's pixels. On a view it runs on the car's box and
    the ring around it only (the network reads nothing farther), which gives what the whole view gives.

    :param path: the .onnx file (the one shipped with drivesim by default).
    """

    def __init__(self, path: Path | str = LEARNED_MODEL):
        self.session = _cpu_session(Path(path))
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if [i.type for i in inputs] != ["tensor(uint8)", "tensor(uint8)"] or len(outputs) != 2:
            raise ValueError(
                f"{path}: the learned harmonizer reads a uint8 view (h, w, 3) and mask (h, w) and returns a colour "
                "map's parameters and a gain"
            )
        self.input_names = [i.name for i in inputs]

    def __call__(self, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Harmonized copy of `rgb` (B, h, w, 3) float [0, 1] under `mask` (B, h, w) bool (rounded to uint8 first)."""
        views = (rgb.detach().cpu() * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
        for view, car in zip(views, mask.cpu().numpy(), strict=True):
            if car.any():
                cv2.copyTo(self._harmonized(view, car), car.view(np.uint8), view)
        harmonized = torch.from_numpy(views).to(rgb.device, rgb.dtype) / 255.0
        return torch.where(mask[..., None], harmonized, rgb)

    def harmonize_view_uint8_(self, rgb: np.ndarray, mask: np.ndarray) -> None:
        """The same on one view, in place: `rgb` (h, w, 3) uint8 changes under `mask` (h, w) bool."""
        left, top, width, height = cv2.boundingRect(mask.view(np.uint8))
        if width == 0:
            return
        m, s = _LEARNED_MARGIN_PX, LEARNED_SCALE
        # The box starts on the network's half-resolution grid of the whole view, so both give the same result.
        y0, x0 = max(top - m, 0) // s * s, max(left - m, 0) // s * s
        y1 = min(y0 + -(-(top + height + m - y0) // s) * s, mask.shape[0])
        x1 = min(x0 + -(-(left + width + m - x0) // s) * s, mask.shape[1])
        box, car = rgb[y0:y1, x0:x1], mask[y0:y1, x0:x1].view(np.uint8)
        cv2.copyTo(self._harmonized(box, car), car, box)

    def _harmonized(self, view: np.ndarray, car: np.ndarray) -> np.ndarray:
        """The car's harmonized colours over a whole uint8 view or box (h, w, 3) (used under the car's mask only)."""
        h, w = car.shape
        s = LEARNED_SCALE
        view_in, car_in = np.ascontiguousarray(view), np.ascontiguousarray(car).view(np.uint8)
        if h % s or w % s:  # the network halves the view: an odd side gets a dark, car-free row or column
            view_in = np.pad(view_in, ((0, -h % s), (0, -w % s), (0, 0)))
            car_in = np.pad(car_in, ((0, -h % s), (0, -w % s)))
        params, gain = self.session.run(None, {self.input_names[0]: view_in, self.input_names[1]: car_in})
        colour_map = np.empty((3, 4), np.float32)  # on 0-255 values
        colour_map[:, :3] = params[:9].reshape(3, 3) + np.eye(3, dtype=np.float32)
        colour_map[:, 3] = 255.0 * params[9:12]
        mapped = cv2.transform(view_in.astype(np.float32), colour_map)
        mapped *= 1.0 + cv2.resize(gain, (car_in.shape[1], car_in.shape[0]), interpolation=cv2.INTER_LINEAR)[..., None]
        np.clip(mapped, 0.0, 255.0, out=mapped)
        mapped += 0.5
        return mapped[:h, :w].astype(np.uint8)


@functools.cache
def _learned() -> LearnedHarmonizer:
    return LearnedHarmonizer()


def make_harmonizer(name: str) -> Harmonizer:
    """The harmonizer called `name` (`HARMONIZERS`); the learned one's session is made once per process."""
    if name == "statistical":
        return StatisticalHarmonizer()
    if name == "learned":
        return _learned()
    raise ValueError(f"harmonizer {name!r}: choose one of {', '.join(HARMONIZERS)}")
