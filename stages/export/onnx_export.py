"""Write a policy module as one ONNX graph with metadata, check it against torch, and time it on one core."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.policy.onnx_runtime import (
    DIGEST_KEY,
    INPUT_NAMES,
    METADATA_FORMAT,
    METADATA_PREFIX,
    OUTPUT_NAMES,
    OnnxPolicy,
    metadata_digest,
)

# Batch size is dynamic: the car runs one episode, evaluation may step several at once.
DYNAMIC_AXES = {
    "image_u8": {0: "episodes"},
    "h": {1: "episodes"},
    "c": {1: "episodes"},
    "episode_start": {0: "episodes"},
    "action": {0: "episodes"},
    "h_out": {1: "episodes"},
    "c_out": {1: "episodes"},
}


def export_onnx(
    module: Any, observation_shape: tuple[int, int, int], metadata: Mapping[str, Any], path: Path, opset: int = 17
) -> None:
    """Write `module` (forward(image_u8, h, c, episode_start) -> (action, h, c)) to `path` as one checked ONNX graph.

    Uses torch's legacy (TorchScript) exporter: the dynamo path needs onnxscript and writes the weights beside the
    graph. `metadata` values are stored as JSON under `drivesim.<key>`, with `drivesim.digest` over them and the graph
    (checked by `OnnxPolicy` on load).
    """
    import onnx
    import torch

    layers, hidden = int(module.lstm_layers), int(module.hidden_size)
    args = (
        torch.zeros((1, *observation_shape), dtype=torch.uint8),
        torch.zeros(layers, 1, hidden),
        torch.zeros(layers, 1, hidden),
        torch.zeros(1),
    )
    module = module.eval()
    with torch.no_grad(), warnings.catch_warnings():
        # The legacy exporter warns that it is deprecated and that LSTMs with a batch other than 1 "can" fail; the
        # rollout check runs the graph with several episodes at once, which is what shows it does not.
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.filterwarnings("ignore", message="Exporting a model to ONNX with a batch_size other than 1")
        # nn.LSTM checks the state's shape in Python; traced as a constant, which is what it is for one graph.
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=list(INPUT_NAMES),
            output_names=list(OUTPUT_NAMES),
            dynamic_axes=DYNAMIC_AXES,
            opset_version=opset,
            dynamo=False,
        )
    model = onnx.load(str(path))
    meta = {"format": METADATA_FORMAT, **metadata, "lstm_layers": layers, "hidden_size": hidden}
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = METADATA_PREFIX + key, json.dumps(value)
    model.producer_name = "drivesim"
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_PREFIX + DIGEST_KEY, json.dumps(metadata_digest(model))
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))


def check_images(rng: np.random.Generator, steps: int, episodes: int, shape: tuple[int, int, int]) -> np.ndarray:
    """(steps, episodes, C, H, W) uint8 test images: a drifting smooth pattern plus noise, so features change."""
    c, h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    phase = rng.uniform(0, 2 * np.pi, size=(episodes, c, 1, 1)).astype(np.float32)
    out = np.empty((steps, episodes, c, h, w), np.uint8)
    for t in range(steps):
        base = 128 + 80 * np.sin(0.07 * xx + 0.05 * yy + phase + 0.1 * t)
        noise = rng.normal(0, 20, size=(episodes, c, h, w))
        out[t] = np.clip(base + noise, 0, 255).astype(np.uint8)
    return out


def compare_rollout(
    module: Any, onnx_policy: OnnxPolicy, images: np.ndarray, reset_step: int
) -> dict[str, float | int]:
    """Step torch and onnxruntime side by side over `images` (T, N, C, H, W); episode 0 restarts at `reset_step`.

    Returns the largest absolute differences of the actions and of the LSTM state over all steps, the state's relative
    to its magnitude (the cell state c is unbounded: a trained LSTM's reaches hundreds, where float32 rounding alone
    is 1e-5 absolute), and how far the actions moved (so that a check on a constant policy cannot pass unnoticed).
    """
    import torch

    steps, episodes = images.shape[:2]
    h_t, c_t = (torch.zeros(module.lstm_layers, episodes, module.hidden_size) for _ in range(2))
    state = onnx_policy.initial_state(episodes)
    max_action, max_state, max_state_rel = 0.0, 0.0, 0.0
    actions = []
    for t in range(steps):
        starts = np.zeros(episodes, np.float32)
        if t == 0:
            starts[:] = 1.0
        elif t == reset_step:
            starts[0] = 1.0
        with torch.no_grad():
            a_t, h_t, c_t = module(torch.from_numpy(images[t]), h_t, c_t, torch.from_numpy(starts))
        a_o, state = onnx_policy.predict(images[t], state, starts)
        max_action = max(max_action, float(np.max(np.abs(a_t.numpy() - a_o))))
        for ours, theirs in ((h_t.numpy(), state[0]), (c_t.numpy(), state[1])):
            diff = float(np.max(np.abs(ours - theirs)))
            max_state = max(max_state, diff)
            max_state_rel = max(max_state_rel, diff / max(1.0, float(np.max(np.abs(ours)))))
        actions.append(a_o)
    stacked = np.stack(actions)
    return {
        "steps": steps,
        "episodes": episodes,
        "reset_step": reset_step,
        "max_abs_diff_action": max_action,
        "max_abs_diff_state": max_state,
        "max_rel_diff_state": max_state_rel,
        "action_range": float(stacked.max() - stacked.min()),
    }


def time_steps(onnx_policy: OnnxPolicy, images: np.ndarray, warmup: int = 20) -> dict[str, float | int]:
    """Latency of one single-episode step (ms): median, 99th percentile and mean over `images` (T, C, H, W)."""
    state = onnx_policy.initial_state(1)
    start = np.ones(1, np.float32)
    for t in range(min(warmup, len(images))):
        _, state = onnx_policy.predict(images[t : t + 1], state, start)
        start = np.zeros(1, np.float32)
    times = []
    for t in range(len(images)):
        began = time.perf_counter()
        _, state = onnx_policy.predict(images[t : t + 1], state, start)
        times.append((time.perf_counter() - began) * 1e3)
    ms = np.asarray(times)
    return {
        "steps": len(times),
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "threads": 1,
    }
