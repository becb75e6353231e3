"""Simulator speed (issue 8 figures): env steps/s per task with one process and with one env per core, ms per step
split into the simulator's parts (the envs' `timings_ms`), and the view synthesizer alone, one view per call against
several views in one batched call.

Actions come from each env's privileged expert (what a policy's forward pass would cost is not the simulator's).
"""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drivesim.bench.machine import machine_line, report_header, usable_cores
from drivesim.bench.sim_steps import make_env, recording_car_drawn, time_env_steps
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
    """One task's speed: steps/s in one process and summed over one process per core, ms per step by part.

    For a task with another car, steps split by whether the car was drawn in the ego's view (`sim_steps.py`):
    `car_drawn_share` of the timed steps drew it; `car_drawn_steps_per_s` is 1000 / the median ms of those steps
    (one process; `car_drawn_steps_per_s_all_cores` sums it over the processes) and `ms_per_step_car_drawn` their
    mean ms per part. Tasks without another car leave them NaN / empty.
    """

    task: str
    steps_per_s: float
    steps_per_s_all_cores: float
    processes: int
    ms_per_step: dict[str, float]
    batched_steps_per_s: float = float("nan")
    batched_envs: int = 0
    car_drawn_share: float = float("nan")
    car_drawn_steps: int = 0
    median_ms_car_drawn: float = float("nan")
    car_drawn_steps_per_s: float = float("nan")
    car_drawn_steps_per_s_all_cores: float = float("nan")
    ms_per_step_car_drawn: dict[str, float] = field(default_factory=dict)
    batched_car_drawn_share: float = float("nan")


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


def _env_loop(task: str, world: str, meshes: str | None, steps: int, seed: int) -> dict:
    """The figures of `steps` expert steps of one env (`sim_steps.StepTimes`, resets not timed): the summary, and the
    mean ms per part over all steps and over the car-drawn ones."""
    name, mode = _task_mode(task)
    times = time_env_steps(make_env(name, world, meshes, mode), steps, seed)
    return {
        "summary": times.summary(),
        "parts": times.mean_part_ms(),
        "parts_car_drawn": times.mean_part_ms(True),
    }


def _env_loop_star(args: tuple) -> dict:
    return _env_loop(*args)


def _batched_loop(task: str, world: str, meshes: str | None, steps: int, n_envs: int, seed: int) -> tuple[float, float]:
    """(env steps/s, share of the views that drew the other car) of `n_envs` episodes stepped together in one process
    (one batched render per step)."""
    import torch

    from drivesim.sim.envs.vector import BatchedVecEnv

    torch.set_num_threads(1)
    name, mode = _task_mode(task)
    venv = BatchedVecEnv(name, n_envs, world, meshes, mode, None, seed)
    venv.reset()
    actions = np.zeros((n_envs, 1), dtype=np.float32)
    for _ in range(3):
        venv.step(actions)
    rounds = max(steps // n_envs, 1)
    with recording_car_drawn() as calls:
        start = time.perf_counter()
        for _ in range(rounds):
            actions = np.stack([e.expert_action() for e in venv.envs])
            venv.step(actions)
        seconds = time.perf_counter() - start
    drawn = np.concatenate(calls) if calls else np.zeros(0, bool)
    return rounds * n_envs / seconds, float(drawn.mean()) if len(drawn) else float("nan")


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
        one = _env_loop(task, world, meshes, steps, seed=0)
        with ctx.Pool(processes) as pool:
            runs = pool.map(_env_loop_star, [(task, world, meshes, steps, 1000 * (i + 1)) for i in range(processes)])
        summary = one["summary"]
        ms = {part: one["parts"].get(part, 0.0) for part in (*PARTS, "other", "total")}
        speed = TaskSpeed(
            task, 1e3 / summary["mean_ms"], sum(1e3 / r["summary"]["mean_ms"] for r in runs), processes, ms
        )
        if _task_has_other(task):
            speed.car_drawn_share = summary["car_drawn_share"]
            speed.car_drawn_steps = summary["car_drawn_steps"]
            speed.median_ms_car_drawn = summary["median_ms_car_drawn"]
            speed.car_drawn_steps_per_s = 1e3 / summary["median_ms_car_drawn"]
            speed.car_drawn_steps_per_s_all_cores = sum(1e3 / r["summary"]["median_ms_car_drawn"] for r in runs)
            speed.ms_per_step_car_drawn = one["parts_car_drawn"]
        if batched_envs > 1:
            speed.batched_steps_per_s, share = _batched_loop(task, world, meshes, steps, batched_envs, seed=0)
            speed.batched_envs = batched_envs
            speed.batched_car_drawn_share = share if _task_has_other(task) else float("nan")
        result.tasks.append(speed)
    return result


def _task_has_other(task: str) -> bool:
    """Whether a task's episodes have another car."""
    from drivesim.sim.envs.registry import task_spec

    return bool(task_spec(_task_mode(task)[0]).env_class().has_other)


def sim_speed_markdown(result: SimSpeedResult, command: str) -> str:
    """The results as a markdown report."""
    lines = [
        *report_header("Simulator speed", result.machine),
        f"- world: `{result.world}`, {result.steps} expert steps per measurement, default observation; step times "
        "exclude resets",
        f"- command: `{command}`",
        "",
        "| task | steps/s, 1 process | steps/s, 1 env per core | batched envs in 1 process: steps/s |",
        "|---|---:|---:|---:|",
    ]
    for t in result.tasks:
        batched = f"{t.batched_steps_per_s:.0f} ({t.batched_envs} envs)" if t.batched_envs else "-"
        if t.batched_envs and t.batched_car_drawn_share == t.batched_car_drawn_share:
            batched += f", car drawn in {100 * t.batched_car_drawn_share:.0f} % of the views"
        lines.append(f"| {t.task} | {t.steps_per_s:.0f} | {t.steps_per_s_all_cores:.0f} ({t.processes}) | {batched} |")
    lines += [
        "",
        "steps/s = 1000 / mean ms per step over all timed steps, with or without the other car in view. overtake: "
        "training episodes (they drive on after the pass, the other car behind and out of view); overtake:eval: "
        "evaluation episodes (they end at the pass).",
        "",
        "With the other car drawn (a step counts when at least one pixel of the car survives the depth test in the "
        "ego's view; steps/s = 1000 / the median ms of those steps):",
        "",
        "| task | car drawn in (share of timed steps) | car-drawn steps | median ms, car drawn | steps/s, car drawn, "
        "1 process | steps/s, car drawn, 1 env per core |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for t in result.tasks:
        if t.car_drawn_steps or t.car_drawn_share == t.car_drawn_share:
            lines.append(
                f"| {t.task} | {100 * t.car_drawn_share:.0f} % | {t.car_drawn_steps} | {t.median_ms_car_drawn:.2f} | "
                f"{t.car_drawn_steps_per_s:.0f} | {t.car_drawn_steps_per_s_all_cores:.0f} ({t.processes}) |"
            )
    columns = (*PARTS, "other", "total")
    lines += ["", "Mean ms per step, one process (all timed steps; car drawn: only those):", ""]
    lines += ["| task | " + " | ".join(columns) + " |", "|---|" + "---:|" * len(columns)]
    for t in result.tasks:
        lines.append(f"| {t.task} | " + " | ".join(f"{t.ms_per_step.get(p, 0.0):.2f}" for p in columns) + " |")
        if t.ms_per_step_car_drawn:
            cells = " | ".join(f"{t.ms_per_step_car_drawn.get(p, 0.0):.2f}" for p in columns)
            lines.append(f"| {t.task}, car drawn | {cells} |")
    lines += ["", "View synthesizer alone (one library car 10 m ahead):", ""]
    lines += [f"- {k}: {v:.2f}" for k, v in result.view_ms.items()]
    return "\n".join(lines) + "\n"
