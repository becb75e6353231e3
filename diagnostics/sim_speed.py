"""Simulator speed (issue 8 figures): env steps/s per task with one process and with one env per core, ms per step
split into the simulator's parts (the envs' `timings_ms`), and the view synthesizer alone, one view per call against
several views in one batched call.

Actions come from each env's privileged expert (what a policy's forward pass would cost is not the simulator's).
"""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivesim.diagnostics.machine import machine_line, usable_cores
from drivesim.sim.envs.registry import TASK_NAMES

# "overtake:eval": evaluation episodes, which end at the pass, so the other car is in view at nearly every step; a
# training episode drives on after the pass with the car behind, out of view (cheaper steps).
TASKS = (*TASK_NAMES, "overtake:eval")


def _task_mode(task: str) -> tuple[str, str]:
    """("overtake", "eval") from "overtake:eval"; the mode is "train" when none is given."""
    name, _, mode = task.partition(":")
    return name, mode or "train"


PARTS = ("dynamics", "association", "warp", "raster", "composite", "lighting", "harmonize", "rewards")


@dataclass
class TaskSpeed:
    """One task's speed: steps/s in one process and summed over one process per core, ms per step by part."""

    task: str
    steps_per_s: float
    steps_per_s_all_cores: float
    processes: int
    ms_per_step: dict[str, float]
    batched_steps_per_s: float = float("nan")
    batched_envs: int = 0


@dataclass
class SimSpeedResult:
    """Everything `drivesim bench sim` reports."""

    machine: str
    world: str
    steps: int
    tasks: list[TaskSpeed] = field(default_factory=list)
    view_ms: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        """Plain JSON-able dict."""
        return asdict(self)


def _env_loop(task: str, world: str, meshes: str | None, steps: int, seed: int) -> tuple[float, dict[str, float], int]:
    """(seconds, cumulative timings_ms, steps) of `steps` expert steps of one env, resets included."""
    import gymnasium
    import torch

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    torch.set_num_threads(1)
    name, mode = _task_mode(task)
    env = gymnasium.make(f"drivesim/{name.capitalize()}-v0", world=world, meshes=meshes, mode=mode)
    env.reset(seed=seed)
    env.unwrapped.expert_action()
    for _ in range(5):  # warm the caches (frames, packed meshes) before timing
        env.step(env.unwrapped.expert_action())
    env.reset(seed=seed)
    env.unwrapped.reset_timings()
    episode = 0
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.unwrapped.expert_action())
        if terminated or truncated:
            episode += 1
            env.reset(seed=seed + episode)
    seconds = time.perf_counter() - start
    return seconds, dict(env.unwrapped.timings_ms), int(env.unwrapped.step_count)


def _env_loop_star(args: tuple) -> tuple[float, dict[str, float], int]:
    return _env_loop(*args)


def _batched_loop(task: str, world: str, meshes: str | None, steps: int, n_envs: int, seed: int) -> float:
    """Env steps/s of `n_envs` episodes stepped together in one process (one batched render per step)."""
    import torch

    from drivesim.sim.envs.vector import BatchedVecEnv

    torch.set_num_threads(1)
    name, mode = _task_mode(task)
    venv = BatchedVecEnv(name, n_envs, world, meshes, mode, None, seed)
    venv.reset()
    actions = np.zeros((n_envs, 1), dtype=np.float32)
    for _ in range(3):
        venv.step(actions)
    start = time.perf_counter()
    rounds = max(steps // n_envs, 1)
    for _ in range(rounds):
        actions = np.stack([e.expert_action() for e in venv.envs])
        venv.step(actions)
    return rounds * n_envs / (time.perf_counter() - start)


def view_speed(world_path: str, repeats: int = 60, batch: int = 8) -> dict[str, float]:
    """ms per view of the view synthesizer alone with one library car 10 m ahead: one view per call, and `batch`
    views (different frames and offsets) in one call."""
    import torch

    from drivesim.sim.vehicle_library import VehicleLibrary
    from drivesim.sim.view import CarPlacement, ViewSynthesizer
    from drivesim.sim.world import World

    torch.set_num_threads(1)
    world = World.load(world_path)
    vs = ViewSynthesizer(world)
    model = VehicleLibrary.procedural(count=2, seed=0).models[0]
    n = world.frame_count
    frames = np.linspace(0, n - 1 - max(n // 10, 1), batch).astype(int)
    x, y, yaw = (world.path[k][frames].copy() for k in ("x_m", "y_m", "yaw_rad"))
    y += np.linspace(-0.5, 0.5, batch)
    cars = [
        [CarPlacement(model, xi + 10 * np.cos(a), yi + 10 * np.sin(a), a)] for xi, yi, a in zip(x, y, yaw, strict=True)
    ]
    for b in range(batch):  # warm the caches
        vs.render(frames[b : b + 1], x[b : b + 1], y[b : b + 1], yaw[b : b + 1], cars[b : b + 1])
    start = time.perf_counter()
    for r in range(repeats):
        b = r % batch
        vs.render(frames[b : b + 1], x[b : b + 1], y[b : b + 1], yaw[b : b + 1], cars[b : b + 1])
    one = 1e3 * (time.perf_counter() - start) / repeats
    start = time.perf_counter()
    rounds = max(repeats // batch, 1)
    for _ in range(rounds):
        vs.render(frames, x, y, yaw, cars)
    batched = 1e3 * (time.perf_counter() - start) / (rounds * batch)
    return {"one_view_per_call_ms": one, f"batch_{batch}_per_view_ms": batched}


def run_sim_speed(
    world: Path | str,
    meshes: Path | str | None = None,
    tasks: tuple[str, ...] = TASKS,
    steps: int = 300,
    processes: int | None = None,
    batched_envs: int = 8,
) -> SimSpeedResult:
    """Measure the simulator on `world` (module docstring); `processes` defaults to the usable cores."""
    world, meshes = str(world), (None if meshes is None else str(meshes))
    processes = processes or usable_cores()
    result = SimSpeedResult(machine=machine_line(), world=world, steps=steps)
    result.view_ms = view_speed(world)
    ctx = multiprocessing.get_context("spawn")
    for task in tasks:
        seconds, timings, count = _env_loop(task, world, meshes, steps, seed=0)
        with ctx.Pool(processes) as pool:
            runs = pool.map(_env_loop_star, [(task, world, meshes, steps, 1000 * (i + 1)) for i in range(processes)])
        all_cores = sum(c / s for s, _, c in runs)
        ms = {part: timings.get(part, 0.0) / max(count, 1) for part in PARTS}
        ms["total"] = 1e3 * seconds / max(count, 1)
        ms["other"] = ms["total"] - sum(ms[p] for p in PARTS)
        speed = TaskSpeed(task, count / seconds, all_cores, processes, ms)
        if batched_envs > 1:
            speed.batched_steps_per_s = _batched_loop(task, world, meshes, steps, batched_envs, seed=0)
            speed.batched_envs = batched_envs
        result.tasks.append(speed)
    return result


def sim_speed_markdown(result: SimSpeedResult, command: str) -> str:
    """The results as a markdown report."""
    lines = [
        "# Simulator speed",
        "",
        f"- machine: {result.machine}",
        f"- date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"- world: `{result.world}`, {result.steps} expert steps per measurement, default observation",
        f"- command: `{command}`",
        "",
        "| task | steps/s, 1 process | steps/s, 1 env per core | batched envs in 1 process: steps/s |",
        "|---|---:|---:|---:|",
    ]
    for t in result.tasks:
        batched = f"{t.batched_steps_per_s:.0f} ({t.batched_envs} envs)" if t.batched_envs else "-"
        lines.append(f"| {t.task} | {t.steps_per_s:.0f} | {t.steps_per_s_all_cores:.0f} ({t.processes}) | {batched} |")
    lines += [
        "",
        "overtake: training episodes (they drive on after the pass, the other car behind and out of view); "
        "overtake:eval: evaluation episodes (they end at the pass: the car is in view at nearly every step).",
    ]
    lines += ["", "ms per step, one process:", "", "| task | " + " | ".join((*PARTS, "other", "total")) + " |"]
    lines.append("|---|" + "---:|" * (len(PARTS) + 2))
    for t in result.tasks:
        cells = " | ".join(f"{t.ms_per_step[p]:.2f}" for p in (*PARTS, "other", "total"))
        lines.append(f"| {t.task} | {cells} |")
    lines += ["", "View synthesizer alone (one library car 10 m ahead):", ""]
    lines += [f"- {k}: {v:.2f}" for k, v in result.view_ms.items()]
    return "\n".join(lines) + "\n"
