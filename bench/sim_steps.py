"""Per-step timing of an env that says, for every timed step, whether another car was drawn in the ego's view.

A simulator figure involving another car is only honest when it says how many of its steps drew the car: a step whose
car is behind the ego or outside the region of interest skips the raster, composite and harmonization. The car-drawn
flag of a step comes from the rendered view's car mask (`ViewBatch.car_mask`: at least one pixel of an inserted car
survived the depth test), recorded by wrapping `ViewSynthesizer.render` for the duration of a measurement.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivesim.sim.simulator import TIMING_KEYS


@contextmanager
def recording_car_drawn() -> Iterator[list[np.ndarray]]:
    """While active, every `ViewSynthesizer.render` call appends to the yielded list a (B,) bool array: whether
    each of its views shows an inserted car (any pixel of its car mask). The cost is one `any` per call."""
    from drivesim.sim.view import ViewSynthesizer

    original = ViewSynthesizer.render
    calls: list[np.ndarray] = []

    def render(self: Any, *args: Any, **kwargs: Any) -> Any:
        batch = original(self, *args, **kwargs)
        calls.append(batch.car_mask.reshape(len(batch.car_mask), -1).any(axis=1))
        return batch

    ViewSynthesizer.render = render
    try:
        yield calls
    finally:
        ViewSynthesizer.render = original


@dataclass
class StepTimes:
    """Wall time and parts of every timed env step, and whether the other car was drawn in it.

    :param ms: (n,) ms per step (the env's `step`, resets not included). :param car_drawn: (n,) bool.
    :param part_ms: per simulator part (`TIMING_KEYS`), (n,) ms per step.
    """

    ms: np.ndarray
    car_drawn: np.ndarray
    part_ms: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def car_drawn_share(self) -> float:
        """Fraction of the timed steps that drew the car."""
        return float(self.car_drawn.mean()) if len(self.ms) else float("nan")

    def median_ms(self, car_drawn: bool | None = None) -> float:
        """Median ms per step over all steps (None), the car-drawn ones (True) or the others (False); NaN if none."""
        chosen = self.ms if car_drawn is None else self.ms[self.car_drawn == car_drawn]
        return float(np.median(chosen)) if len(chosen) else float("nan")

    def mean_part_ms(self, car_drawn: bool | None = None) -> dict[str, float]:
        """Mean ms per step of each part and of the rest ("other") over the chosen steps (as `median_ms`)."""
        chosen = np.ones(len(self.ms), bool) if car_drawn is None else self.car_drawn == car_drawn
        if not chosen.any():
            return {}
        parts = {k: float(v[chosen].mean()) for k, v in self.part_ms.items()}
        parts["other"] = float(self.ms[chosen].mean()) - sum(parts.values())
        parts["total"] = float(self.ms[chosen].mean())
        return parts

    def summary(self) -> dict[str, float]:
        """The figures a report needs, JSON-able."""
        return {
            "steps": len(self.ms),
            "car_drawn_steps": int(self.car_drawn.sum()),
            "car_drawn_share": self.car_drawn_share,
            "median_ms": self.median_ms(),
            "median_ms_car_drawn": self.median_ms(True),
            "median_ms_no_car": self.median_ms(False),
            "mean_ms": float(np.mean(self.ms)) if len(self.ms) else float("nan"),
        }


def make_env(task: str, world: str, meshes: str | None, mode: str, config: dict | None = None) -> Any:
    """One gymnasium env of `task` with torch on one thread (as every env process of training runs)."""
    import gymnasium
    import torch

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    torch.set_num_threads(1)
    return gymnasium.make(f"drivesim/{task.capitalize()}-v0", world=world, meshes=meshes, mode=mode, config=config)


def time_env_steps(env: Any, steps: int, seed: int, car_drawn_steps: int = 0, max_steps: int = 0) -> StepTimes:
    """Time `steps` expert steps of `env` one by one (resets not timed; episode k starts with seed + k). With
    `car_drawn_steps`, go on past `steps` until that many steps drew the car (at most `max_steps` in all)."""
    unwrapped = env.unwrapped
    env.reset(seed=seed)
    for _ in range(5):  # warm the caches (frames, packed meshes) before timing
        env.step(unwrapped.expert_action())
    env.reset(seed=seed)
    max_steps = max(max_steps, steps)
    times, drawn, parts = [], [], {k: [] for k in TIMING_KEYS}
    episode = 0
    with recording_car_drawn() as calls:
        while len(times) < max_steps and (len(times) < steps or sum(drawn) < car_drawn_steps):
            action = unwrapped.expert_action()
            before = unwrapped.timings_ms
            calls.clear()
            start = time.perf_counter()
            _, _, terminated, truncated, _ = env.step(action)
            times.append(1e3 * (time.perf_counter() - start))
            after = unwrapped.timings_ms
            drawn.append(bool(calls[-1][0]) if calls else False)
            for k in TIMING_KEYS:
                parts[k].append(after.get(k, 0.0) - before.get(k, 0.0))
            if terminated or truncated:
                episode += 1
                env.reset(seed=seed + episode)
    return StepTimes(np.array(times), np.array(drawn, bool), {k: np.array(v) for k, v in parts.items()})
