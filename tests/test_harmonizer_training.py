"""The learned harmonizer's training (`bench/harmonizer_training.py`): pairs of the simulator's composite and the
synthetic world's true look, a fit that brings the car closer to the truth, and an ONNX export onnxruntime runs on
the car's box as torch does on the whole view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from drivesim.bench import harmonizer_training as ht


def _masked_mse(model: torch.nn.Module, pairs: dict[str, np.ndarray]) -> float:
    x = ht.as_input(pairs["composite"], pairs["sim_mask"])
    target = torch.from_numpy(pairs["truth"]).permute(0, 3, 1, 2).float() / 255.0
    both = torch.from_numpy(pairs["sim_mask"] & pairs["true_mask"])[:, None].float()
    with torch.no_grad():
        return float((((model(x) - target) ** 2) * both).sum() / (3 * both.sum()))


def test_pairs_training_and_export(tmp_path: Path) -> None:
    pairs = ht.make_pairs(seed=1, samples=6)
    n = len(pairs["composite"])
    assert n >= 4, "most placements put the car in view"
    assert pairs["composite"].shape == pairs["truth"].shape == (n, 64, 160, 3)
    overlap = (pairs["sim_mask"] & pairs["true_mask"]).sum(axis=(1, 2))
    union = (pairs["sim_mask"] | pairs["true_mask"]).sum(axis=(1, 2))
    assert (overlap >= 30).all() and (overlap / union).mean() > 0.8  # the simulator draws the car where it is
    identity = ht.HarmonizerNet().eval()  # its last layers start at zero: the identity on the car
    model = ht.train(pairs, steps=60, seed=0)
    assert _masked_mse(model, pairs) < 0.8 * _masked_mse(identity, pairs)
    difference = ht.export_onnx(model, tmp_path / "h.onnx", pairs["composite"][:2], pairs["sim_mask"][:2])
    assert difference <= 1  # grey levels: onnxruntime on the car's box as torch on the whole view


def test_seed_lists() -> None:
    assert ht.parse_seeds("3-5") == [3, 4, 5] and ht.parse_seeds("1,7") == [1, 7]
