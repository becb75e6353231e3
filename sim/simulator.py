"""The multi-agent simulator without gymnasium: every agent stepped, associated with a recorded frame and viewed.

Each step: (1) agents' bicycle states advance (`sim/dynamics.py`), (2) each agent is associated with its closest
recorded frame (`World.closest_frames`), (3) the requested agents' views are synthesized in one batched call
(`sim/view.py::ViewSynthesizer`) with every other car inserted. Time per part accumulates in `timings_ms`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from drivesim.sim.agents import Agent, ReferencePath
from drivesim.sim.dynamics import rk3_step, steering_for_curvature, steering_rate_command
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from drivesim.sim.world import World

TIMING_KEYS = ("dynamics", "association", "warp", "raster", "composite", "lighting", "harmonize", "rewards")


def make_view_synthesizer(
    world: World,
    roi_px: tuple[int, int, int, int],
    out_width_px: int,
    out_height_px: int,
    device: str = "cpu",
    **view_options: Any,
) -> ViewSynthesizer:
    """The world's view synthesizer for a region of interest resized to the policy's observation size, rendering on
    torch `device`."""
    config = ViewConfig(roi_px=tuple(roi_px), out_width_px=out_width_px, out_height_px=out_height_px, **view_options)
    return ViewSynthesizer(world, config, device=device)


class Simulator:
    """Agents in one world: `step` advances them, `associate` finds their frames, `views` renders their cameras.

    :param world: the loaded world. :param renderer: an object with ViewSynthesizer's `render`.
    :param wheelbase_m: L of every agent. :param max_steering_rate_radps: the steering-rate limit.
    :param dt_s: the step.
    """

    def __init__(
        self, world: World, renderer: Any, wheelbase_m: float, max_steering_rate_radps: float, dt_s: float
    ) -> None:
        self.world = world
        self.reference = ReferencePath(world.path)
        self.renderer = renderer
        self.wheelbase_m = wheelbase_m
        self.max_steering_rate_radps = max_steering_rate_radps
        self.dt_s = dt_s
        self.agents: list[Agent] = []
        self.models: list[Any] = []
        self.timings_ms = dict.fromkeys(TIMING_KEYS, 0.0)

    def reset_timings(self) -> None:
        """Zero the cumulative timings."""
        self.timings_ms = dict.fromkeys(TIMING_KEYS, 0.0)

    def step_agent(self, agent: Agent, curvature_1pm: float) -> float:
        """Advance one agent by dt toward the commanded curvature at its set speed; returns u_δ (rad/s)."""
        target = steering_for_curvature(curvature_1pm, self.wheelbase_m)
        u_steer = steering_rate_command(agent.state.steering_rad, target, self.max_steering_rate_radps, self.dt_s)
        u_accel = (agent.target_speed_mps - agent.state.speed_mps) / self.dt_s
        before_x, before_y = agent.state.x_m, agent.state.y_m
        agent.state = rk3_step(agent.state, u_steer, u_accel, self.dt_s, self.wheelbase_m)
        agent.distance_m += math.hypot(agent.state.x_m - before_x, agent.state.y_m - before_y)
        return u_steer

    def step(self, curvatures_1pm: list[float]) -> list[float]:
        """Advance every agent with its commanded curvature; returns each one's u_δ."""
        start = time.perf_counter()
        rates = [self.step_agent(a, k) for a, k in zip(self.agents, curvatures_1pm, strict=True)]
        self.timings_ms["dynamics"] += 1e3 * (time.perf_counter() - start)
        return rates

    def associate(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every agent's closest recorded frame and (q_lat, q_long, q_rot); updates `agent.frame_index`."""
        start = time.perf_counter()
        x = np.array([a.state.x_m for a in self.agents])
        y = np.array([a.state.y_m for a in self.agents])
        yaw = np.array([a.state.yaw_rad for a in self.agents])
        near = np.array([a.frame_index for a in self.agents])
        index, q_lat, q_long, q_rot = self.world.closest_frames(x, y, yaw, near_index=near)
        for agent, i in zip(self.agents, index, strict=True):
            agent.frame_index = int(i)
        self.timings_ms["association"] += 1e3 * (time.perf_counter() - start)
        return index, q_lat, q_long, q_rot

    def placements(self, viewer: int) -> list[Any]:
        """Every other agent as a CarPlacement for the viewer's camera (empty without vehicle models)."""
        if not self.models:
            return []
        return [
            CarPlacement(model=self.models[j], x_m=a.state.x_m, y_m=a.state.y_m, yaw_rad=a.state.yaw_rad)
            for j, a in enumerate(self.agents)
            if j != viewer and self.models[j] is not None
        ]

    def view_request(self, viewer: int = 0) -> tuple[int, float, float, float, list[Any]]:
        """What `views` needs for one agent: frame index, pose and the cars it sees."""
        a = self.agents[viewer]
        return a.frame_index, a.state.x_m, a.state.y_m, a.state.yaw_rad, self.placements(viewer)

    def views(self, viewers: list[int] | None = None) -> np.ndarray:
        """The viewers' (default: all agents') camera views, (B, h, w, 3) uint8, in one batched render."""
        viewers = list(range(len(self.agents))) if viewers is None else viewers
        return render_requests(self.renderer, [self.view_request(v) for v in viewers], self.timings_ms)


def render_requests(renderer: Any, requests: list[tuple], timings_ms: dict[str, float]) -> np.ndarray:
    """One batched render of (frame_index, x, y, yaw, cars) requests; adds its part timings to `timings_ms`."""
    batch = renderer.render(
        np.array([r[0] for r in requests], dtype=np.int64),
        np.array([r[1] for r in requests]),
        np.array([r[2] for r in requests]),
        np.array([r[3] for r in requests]),
        [r[4] for r in requests],
    )
    for key, value in batch.timings_ms.items():
        timings_ms[key] = timings_ms.get(key, 0.0) + float(value)
    return batch.rgb
