"""The simulator's observations on two versions of a world, compared: what a storage change does to what the policy
sees."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def expert_observations(world: Path, task: str, steps: int) -> list[np.ndarray]:
    """The image observations of `steps` expert steps of `task` on `world` (episode k from seed k), flattened."""
    from drivesim.bench.sim_steps import make_env

    env = make_env(task, str(world), None, "train")
    unwrapped = env.unwrapped
    env.reset(seed=0)
    images, episode = [], 0
    while len(images) < steps:
        obs, _, terminated, truncated, _ = env.step(unwrapped.expert_action())
        parts = obs.values() if isinstance(obs, dict) else [obs]
        images.append(np.concatenate([np.asarray(p).ravel() for p in parts if np.asarray(p).dtype == np.uint8]))
        if terminated or truncated:
            episode += 1
            env.reset(seed=episode)
    env.close()
    return images


def observation_difference(reference: Path, world: Path, task: str, steps: int) -> dict[str, Any]:
    """How the observations of the same expert steps of `task` differ between two worlds: PSNR (dB), the share of
    pixels that differ, mean and max absolute difference (grey levels), steps whose images are identical."""
    a = np.stack(expert_observations(reference, task, steps)).astype(np.float64)
    b = np.stack(expert_observations(world, task, steps)).astype(np.float64)
    diff = np.abs(a - b)
    mse = float(np.mean(diff**2))
    return {
        "task": task,
        "steps": steps,
        "psnr_db": float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse),
        "pixels_differing": float(np.mean(diff > 0)),
        "mean_abs_diff": float(diff.mean()),
        "max_abs_diff": float(diff.max()),
        "steps_identical": int(np.sum(diff.reshape(len(diff), -1).max(axis=1) == 0)),
    }
