"""The learned harmonizer's training (`sim/models/harmonizer.onnx`, `benchmarks/bench_harmonizer.py`).

Training pairs come from the synthetic world, which knows the true look of a car in its scene: a library car is
placed at random ahead of a synthetic drive's frame, the simulator's view draws it (warp + insertion + lighting +
contact shadow, no harmonization, no camera look), and the synthetic world's own renderer draws the same car into
the same scene (its sun, sky and haze). The network sees the composite and the car's mask and predicts a colour
transform of the car's pixels: a 3 x 4 affine map from masked statistics and pooled convolution features, times a
per-pixel brightness gain from a small convolution head (both start at the identity), all but the map at half the
resolution. Its support is the car and a ring of `RING_PX` around it, so the simulator runs it on the car's box alone
(`LearnedHarmonizer`).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn.functional import avg_pool2d, interpolate, max_pool2d

from drivesim.bench.car_fidelity import world_from_drive
from drivesim.bench.fidelity import image_metrics, render_drive
from drivesim.sim.geometry import pose_2d, yaw_of
from drivesim.sim.harmonize import LEARNED_RING_PX as RING_PX
from drivesim.sim.harmonize import LEARNED_SCALE as SCALE
from drivesim.sim.harmonize import Harmonizer, LearnedHarmonizer, harmonize_view_uint8_
from drivesim.sim.vehicle_library import VehicleLibrary
from drivesim.sim.vehicles import sample_paint
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from drivesim.stages.synth.render import CellCulling

CAR_ID = 1000


def parse_seeds(text: str) -> list[int]:
    """'1-10' or '1,4,7' -> seeds."""
    if "-" in text:
        first, last = (int(v) for v in text.split("-"))
        return list(range(first, last + 1))
    return [int(v) for v in text.split(",")]


def make_pairs(seed: int, samples: int) -> dict[str, np.ndarray]:
    """`samples` (composite, sim mask, truth, true mask) views of library cars placed at random ahead of the synthetic
    drive of `seed`, at the policy's view size."""
    rng = np.random.default_rng(seed)
    drive = render_drive(seed, samples + 2, 320, 200)
    world = world_from_drive(drive, Path("."))
    view = ViewSynthesizer(world, ViewConfig(harmonization=False, camera_look=False))
    size = (view.config.out_width_px, view.config.out_height_px)
    scene = drive.world.meshes  # textures made once for all samples
    models = VehicleLibrary.procedural(count=8, seed=seed).models
    out: dict[str, list] = {"composite": [], "sim_mask": [], "truth": [], "true_mask": []}
    for i in range(1, samples + 1):
        model = models[int(rng.integers(len(models)))].repainted(sample_paint(rng))
        ahead_m, lateral_m = rng.uniform(6.0, 22.0), rng.uniform(-3.5, 3.5)
        T_world_car = drive.T_world_vehicle[i] @ pose_2d(ahead_m, lateral_m, rng.uniform(-0.25, 0.25))
        T_world_agent = drive.T_world_vehicle[i] @ pose_2d(0.0, rng.uniform(-1.0, 1.0), 0.0)
        car = [dataclasses.replace(m.transformed(T_world_car), object_id=CAR_ID) for m in model.full]
        synth = drive.world
        saved, synth._culling = synth._culling, CellCulling(scene + car)  # the car joins the scene for this render
        try:
            truth, _, ids = synth.render_full(T_world_agent @ drive.T_vehicle_camera, view.K_view, *size)
        finally:
            synth._culling = saved
        placement = CarPlacement(model, float(T_world_car[0, 3]), float(T_world_car[1, 3]), float(yaw_of(T_world_car)))
        agent = (np.array([i]), T_world_agent[0, 3:4], T_world_agent[1, 3:4], np.atleast_1d(yaw_of(T_world_agent)))
        drawn = view.render(*agent, [[placement]])
        if (drawn.car_mask[0] & (ids == CAR_ID)).sum() < 30:
            continue  # the car is out of view or nearly hidden
        for key, value in zip(out, (drawn.rgb[0], drawn.car_mask[0], truth, ids == CAR_ID), strict=True):
            out[key].append(np.asarray(value))
    return {key: np.stack(v) for key, v in out.items()}


class HarmonizerNet(nn.Module):
    """(B, 4, h, w) RGB in [0, 1] + mask (h, w even) -> (B, 3, h, w): the car's pixels through a predicted affine
    colour map and a per-pixel gain; the rest unchanged. Everything but applying the colour map runs at half the
    resolution (`LEARNED_SCALE`), which cuts the convolutions' cost fourfold."""

    def __init__(self, width: int = 8) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(5, width, 3, padding=1), nn.ReLU(), nn.Conv2d(width, width, 3, padding=1), nn.ReLU()
        )
        self.affine = nn.Sequential(nn.Linear(2 * (3 + width) + 6, 64), nn.ReLU(), nn.Linear(64, 12))
        self.gain = nn.Conv2d(width, 1, 3, padding=1)
        for layer in (self.affine[-1], self.gain):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def head(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 4, h, w) -> the colour map's 12 parameters (B, 12: 3 x 3 added to the identity, then the offset) and
        the brightness gain at half resolution (B, 1, h / 2, w / 2), in [-1, 1] (1 + gain multiplies the colour)."""
        small = avg_pool2d(x, SCALE)
        rgb_s, mask_s = small[:, :3], small[:, 3:4]
        r = RING_PX // SCALE
        ring_s = max_pool2d(mask_s, 2 * r + 1, stride=1, padding=r) - mask_s
        feats = self.features(torch.cat([rgb_s, mask_s, ring_s], dim=1))
        # The car's and the ring's weighted means of colour and features and their colour spreads, as two matrix
        # products (few graph nodes: the simulator runs this once per view).
        weights = torch.cat([mask_s, ring_s], dim=1).flatten(2)  # (B, 2, n)
        count = weights.sum(dim=2, keepdim=True).clamp_min(1.0)  # (B, 2, 1)
        mean = weights @ torch.cat([rgb_s, feats], dim=1).flatten(2).transpose(1, 2) / count  # (B, 2, 3 + width)
        square = weights @ (rgb_s * rgb_s).flatten(2).transpose(1, 2) / count  # (B, 2, 3)
        spread = (square - mean[:, :, :3] ** 2).clamp_min(0.0).add(1e-6).sqrt()
        params = self.affine(torch.cat([mean.flatten(1), spread.flatten(1)], dim=1))
        return params, torch.tanh(self.gain(feats))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rgb, mask = x[:, :3], x[:, 3:4]
        params, gain = self.head(x)
        matrix = torch.eye(3, device=x.device)[None] + params[:, :9].reshape(-1, 3, 3)
        mapped = torch.einsum("bij,bjhw->bihw", matrix, rgb) + params[:, 9:12, None, None]
        mapped = mapped * (1.0 + interpolate(gain, scale_factor=SCALE, mode="bilinear", align_corners=False))
        return mask * mapped.clamp(0.0, 1.0) + (1.0 - mask) * rgb


def as_input(composite: np.ndarray, mask: np.ndarray) -> torch.Tensor:
    """uint8 views (B, h, w, 3) and masks (B, h, w) -> the model's (B, 4, h, w) input."""
    rgb = torch.from_numpy(composite).permute(0, 3, 1, 2).float() / 255.0
    return torch.cat([rgb, torch.from_numpy(mask)[:, None].float()], dim=1)


def train(pairs: dict[str, np.ndarray], steps: int, seed: int) -> HarmonizerNet:
    """Fit the model to the true look over the pixels that both masks cover (mean squared error)."""
    torch.manual_seed(seed)
    model = HarmonizerNet()
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    x = as_input(pairs["composite"], pairs["sim_mask"])
    target = torch.from_numpy(pairs["truth"]).permute(0, 3, 1, 2).float() / 255.0
    both = torch.from_numpy(pairs["sim_mask"] & pairs["true_mask"])[:, None].float()
    rng = np.random.default_rng(seed)
    for step in range(steps):
        ids = torch.from_numpy(rng.choice(len(x), size=min(32, len(x)), replace=False))
        out = model(x[ids])
        loss = (((out - target[ids]) ** 2) * both[ids]).sum() / (3 * both[ids].sum()).clamp_min(1.0)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step % 100 == 0 or step == steps - 1:
            print(f"step {step}: loss {loss.item():.5f}", flush=True)
    return model.eval()


class HeadGraph(nn.Module):
    """The graph drivesim ships: one uint8 view or box (h, w, 3) and its car mask (h, w) uint8 -> the colour map's
    parameters (12,) and the half-resolution gain (h / 2, w / 2) of `HarmonizerNet.head`; applying them to the car's
    pixels is a few OpenCV calls in the simulator (`LearnedHarmonizer`), cheaper than the same in the graph."""

    def __init__(self, net: HarmonizerNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, view: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rgb = view.permute(2, 0, 1).to(torch.float32) * (1.0 / 255.0)
        params, gain = self.net.head(torch.cat([rgb, mask.to(torch.float32)[None]], dim=0)[None])
        return params[0], gain[0, 0]


def export_onnx(model: HarmonizerNet, path: Path, views: np.ndarray, masks: np.ndarray) -> int:
    """Write the model as the shipped ONNX graph (`HeadGraph`, any even size) and return the largest difference in
    grey levels between the simulator's path (onnxruntime on the car's box, then OpenCV) and the torch model on the
    whole uint8 `views` (B, h, w, 3) under `masks` (B, h, w)."""
    graph = HeadGraph(model.eval())
    sample = (torch.from_numpy(views[0]), torch.from_numpy(masks[0].astype(np.uint8)))
    torch.onnx.export(
        graph, sample, str(path), input_names=["view", "mask"], output_names=["params", "gain"], opset_version=17,
        dynamic_axes={"view": {0: "h", 1: "w"}, "mask": {0: "h", 1: "w"}, "gain": {0: "h2", 1: "w2"}}, dynamo=False,
    )  # fmt: skip
    runtime = LearnedHarmonizer(path)
    largest = 0
    for view, mask in zip(views, masks, strict=True):
        with torch.no_grad():
            out = model(as_input(view[None], mask[None]))[0].permute(1, 2, 0)
        expected = (out * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).numpy()
        got = view.copy()
        runtime.harmonize_view_uint8_(got, mask)
        largest = max(largest, int(np.abs(got.astype(int) - expected.astype(int)).max()))
    return largest


def harmonized(harmonizer: Harmonizer | None, view: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A harmonized copy of one uint8 view, as the simulator's CPU path makes it (None: the view unchanged)."""
    out = view.copy()
    if harmonizer is not None:
        harmonize_view_uint8_(harmonizer, out, mask)
    return out


def car_scores(pairs: dict[str, np.ndarray], harmonizers: dict[str, Harmonizer | None]) -> dict[str, dict[str, float]]:
    """Mean car PSNR / SSIM over the true car mask, per harmonizer (None: no harmonization)."""
    scores = {}
    for name, harmonizer in harmonizers.items():
        rows = []
        for i in range(len(pairs["composite"])):
            view = harmonized(harmonizer, pairs["composite"][i], pairs["sim_mask"][i])
            rows.append(image_metrics(view, pairs["truth"][i], pairs["true_mask"][i]))
        scores[name] = {key: float(np.mean([r[key] for r in rows])) for key in ("psnr_db", "ssim")}
    return scores


def figure(pairs: dict[str, np.ndarray], harmonizers: dict[str, Harmonizer | None], path: Path, count: int = 6) -> None:
    """Rows of test views around the car (each crop scaled to 96 x 64, then the grid 2x, no smoothing): the true
    look, then each harmonizer's."""
    rows = []
    for i in np.linspace(0, len(pairs["composite"]) - 1, count).round().astype(int):
        ys, xs = np.nonzero(pairs["true_mask"][i])
        y0, y1 = max(int(ys.min()) - 6, 0), int(ys.max()) + 7
        x0, x1 = max(int(xs.min()) - 10, 0), int(xs.max()) + 11
        cells = [pairs["truth"][i]]
        cells += [harmonized(h, pairs["composite"][i], pairs["sim_mask"][i]) for h in harmonizers.values()]
        crops = [cv2.resize(c[y0:y1, x0:x1], (96, 64), interpolation=cv2.INTER_NEAREST) for c in cells]
        rows.append(np.hstack([np.pad(c, ((2, 2), (2, 2), (0, 0)), constant_values=255) for c in crops]))
    grid = np.vstack(rows)
    labels = np.full((18, grid.shape[1], 3), 255, np.uint8)
    for k, name in enumerate(("truth", *harmonizers)):
        cv2.putText(labels, name, (k * 100 + 4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    grid = cv2.resize(np.vstack([labels, grid]), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))


def pairs_for(seeds: list[int], samples: int, cache: Path) -> dict[str, np.ndarray]:
    """The pairs of `seeds`, made once and kept in `cache`."""
    parts = []
    for seed in seeds:
        path = cache / f"pairs_{seed}_{samples}.npz"
        if not path.is_file():
            started = time.perf_counter()
            np.savez_compressed(path, **make_pairs(seed, samples))
            print(f"seed {seed}: pairs in {time.perf_counter() - started:.0f} s", flush=True)
        parts.append(dict(np.load(path)))
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
