"""The common driving environment: one ego agent (the policy) and, for follow and overtake, one front car.

Subclasses (`lane.py`, `follow.py`, `overtake.py`) set the task's start state, rewards and success; their class
docstrings describe spaces, rewards, start and end in one place. The step is split into `advance` (dynamics,
association, rewards) and `observation_from` (augmentation of a rendered view) so that `vector.py` can render many
episodes in one call.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from drivesim.sim.agents import Agent, LateralProfile, ReferencePath, pursue_profile
from drivesim.sim.dynamics import BicycleState, curvature_of_steering
from drivesim.sim.envs.augment import Augmentation
from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.rewards import collision_reward, comfort_reward, lane_reward, pass_reward
from drivesim.sim.envs.termination import termination_flags
from drivesim.sim.footprint import clearance_m, collision_overlap, footprint
from drivesim.sim.simulator import TIMING_KEYS, Simulator, make_view_synthesizer, render_requests
from drivesim.sim.world import World

DEFAULT_OTHER_SIZE_M = (4.5, 1.9)
NAN = float("nan")


def load_worlds(world: Any, min_length_m: float) -> list[World]:
    """World objects from a path, a World or a list of them; one-line errors for missing, old or short worlds."""
    items = list(world) if isinstance(world, list | tuple) else [world]
    if not items:
        raise ValueError("world: an empty list of worlds; give at least one world folder")
    worlds = []
    for item in items:
        w = item if isinstance(item, World) else World.load(Path(item))
        if w.path_length_m < min_length_m:
            raise ValueError(
                f"{w.root / 'world.json'}: path of {w.path_length_m:.0f} m is too short for this task "
                f"(needs {min_length_m:.0f} m: min_path_length_m + end_margin_m); record a longer drive"
            )
        worlds.append(w)
    return worlds


def load_vehicles(meshes: Any) -> Any:
    """The vehicle library from a `meshes/` folder, or the procedural one for None."""
    if meshes is not None and not Path(meshes).exists():
        raise FileNotFoundError(f"{meshes}: no such meshes folder; run `drivesim meshes build` or pass meshes=None")
    from drivesim.sim.vehicle_library import VehicleLibrary  # trimesh: only for tasks with other cars

    return VehicleLibrary.procedural() if meshes is None else VehicleLibrary.load(meshes)


def default_roi(width_px: int, height_px: int, config: EnvConfig) -> tuple[int, int, int, int]:
    """The largest region with the observation's aspect, centred across, at the bottom of the image."""
    aspect = config.out_width_px / config.out_height_px
    w, h = width_px, round(width_px / aspect)
    if h > height_px:
        w, h = round(height_px * aspect), height_px
    return ((width_px - w) // 2, height_px - h, w, h)


class DrivingEnv(gymnasium.Env):
    """Base of the drivesim tasks (see the subclasses for the task documentation)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    task = "lane"
    has_other = False

    def __init__(
        self,
        world: Any,
        meshes: Any = None,
        mode: str = "train",
        config: dict | EnvConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        if mode not in ("train", "eval"):
            raise ValueError(f"mode: {mode!r}; use 'train' or 'eval'")
        self.config = config if isinstance(config, EnvConfig) else EnvConfig(**(config or {}))
        self.mode = mode
        self.render_mode = render_mode
        c = self.config
        self.worlds = load_worlds(world, c.min_path_length_m + c.end_margin_m)
        self.vehicles = load_vehicles(meshes) if self.has_other else None
        self.collision_threshold = c.collision_overlap_train if mode == "train" else c.collision_overlap_eval
        self._timings = dict.fromkeys(TIMING_KEYS, 0.0)
        self._renderers: dict[int, Any] = {}
        self.observation_space = spaces.Box(0, 255, (3, c.out_height_px, c.out_width_px), np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.step_count = 0
        self.sim: Simulator | None = None
        self._last_rgb: np.ndarray | None = None

    # --- timings -------------------------------------------------------------------------------------------------
    @property
    def timings_ms(self) -> dict[str, float]:
        """Cumulative ms per part since `reset_timings()`."""
        return dict(self._timings)

    def reset_timings(self) -> None:
        """Zero the timings and the step count."""
        for key in self._timings:
            self._timings[key] = 0.0
        self.step_count = 0

    # --- episode start -------------------------------------------------------------------------------------------
    def _renderer(self, world_index: int) -> Any:
        if world_index not in self._renderers:
            c, world = self.config, self.worlds[world_index]
            roi = c.roi_px if c.roi_px is not None else default_roi(world.width_px, world.height_px, c)
            self._renderers[world_index] = make_view_synthesizer(world, roi, c.out_width_px, c.out_height_px)
        return self._renderers[world_index]

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """A new episode; the same seed gives the same episode and observation."""
        self.reset_state(seed)
        info = self._info(reset=True)
        return self.observation_from(self._render_one()), info

    def reset_state(self, seed: int | None) -> None:
        """Draw the episode's start state (no rendering)."""
        super().reset(seed=seed)
        c, rng = self.config, self.np_random
        self._seed = seed
        self._world_index = int(rng.integers(len(self.worlds)))
        world = self.worlds[self._world_index]
        sim = Simulator(world, self._renderer(self._world_index), c.wheelbase_m, c.max_steering_rate_radps, c.dt_s)
        sim.timings_ms = self._timings
        self.sim = sim
        ref = sim.reference
        start_arc = float(rng.uniform(ref.start_m, ref.end_m - c.min_path_length_m - c.end_margin_m))
        ego_speed, other_speed = self._speeds(rng)
        lat0 = float(rng.uniform(-c.initial_lateral_m, c.initial_lateral_m))
        yaw0 = float(rng.uniform(-c.initial_yaw_rad, c.initial_yaw_rad))
        x, y, yaw = ref.pose(start_arc, lat0)
        ego = Agent(BicycleState(x, y, yaw + yaw0, 0.0, ego_speed), c.ego_length_m, c.ego_width_m, ego_speed)
        ego.arc_m, ego.lateral_m = start_arc, lat0
        sim.agents, sim.models = [ego], [None]
        self._gap_m = NAN
        self._other_lateral_m = NAN
        if self.has_other:
            model = self.vehicles.sample(rng) if self.vehicles is not None else None
            size = DEFAULT_OTHER_SIZE_M if model is None else (model.length_m, model.width_m)
            gap = float(rng.uniform(*c.front_distance_m))
            side = 1.0 if rng.uniform() < 0.5 else -1.0
            lateral = side * float(rng.uniform(*c.front_lateral_m))
            profile = self._other_profile(rng, start_arc + gap, lateral, ref)
            ox, oy, oyaw = ref.pose(start_arc + gap, lateral)
            other = Agent(BicycleState(ox, oy, oyaw, 0.0, other_speed), size[0], size[1], other_speed, profile)
            other.arc_m, other.lateral_m = start_arc + gap, lateral
            sim.agents.append(other)
            sim.models.append(model)
            self._gap_m, self._other_lateral_m = gap, lateral
        sim.associate()
        for agent in sim.agents:
            agent.frame_index = int(np.argmin(np.abs(ref.arc_m - agent.arc_m)))
        self._assoc = self._associate()
        self._u_steer = 0.0
        self._t = 0
        self._succeeded = False
        self._episode = {
            "seed": seed,
            "world": str(world.root),
            "start_frame": int(sim.agents[0].frame_index),
            "ego_speed_mps": ego_speed,
            "other_speed_mps": other_speed if self.has_other else NAN,
            "initial_lateral_m": (self._other_lateral_m - lat0) if self.has_other else lat0,
            "road_curvature_1pm": ref.mean_abs_curvature(start_arc, c.min_path_length_m),
            "ego_length_m": c.ego_length_m,
            "ego_width_m": c.ego_width_m,
            "other_length_m": sim.agents[1].length_m if self.has_other else NAN,
            "other_width_m": sim.agents[1].width_m if self.has_other else NAN,
        }
        aug_on = c.augment and self.mode == "train"
        self._augmentation = (
            Augmentation.sample(rng, c.gamma, c.brightness, c.contrast, c.saturation) if aug_on else Augmentation()
        )
        self._measure()

    def _speeds(self, rng: np.random.Generator) -> tuple[float, float]:
        return float(rng.uniform(*self.config.ego_speed_mps)), NAN

    def _other_profile(
        self, rng: np.random.Generator, arc_m: float, lateral_m: float, ref: ReferencePath
    ) -> LateralProfile:
        return LateralProfile.constant(lateral_m)

    # --- one step ------------------------------------------------------------------------------------------------
    def _associate(self) -> tuple[np.ndarray, ...]:
        index, q_lat, q_long, q_rot = self.sim.associate()
        arc = self.sim.reference.arc_m
        for i, agent in enumerate(self.sim.agents):
            agent.arc_m = float(arc[index[i]] + q_long[i])
            agent.lateral_m = float(q_lat[i])
        return index, q_lat, q_long, q_rot

    def advance(self, action: np.ndarray) -> tuple[float, bool, bool, dict]:
        """Dynamics, association, rewards and terminations for one action (no rendering)."""
        c, sim = self.config, self.sim
        a = float(np.clip(np.asarray(action, dtype=np.float32).reshape(-1)[0], -1.0, 1.0))
        curvatures = [a * c.max_curvature_1pm]
        if self.has_other:
            other = sim.agents[1]
            curvatures.append(pursue_profile(other, sim.reference, other.arc_m, c.pursuit_gain, c.pursuit_lookahead_m))
        rates = sim.step(curvatures)
        self._assoc = self._associate()
        start = time.perf_counter()
        steering_accel = (rates[0] - self._u_steer) / c.dt_s
        self._u_steer = rates[0]
        self._t += 1
        self.step_count += 1
        self._measure()
        m = self._m
        terms = {
            "lane": c.weight_lane * lane_reward(self._lane_error(), c.max_lateral_m),
            "pass": c.weight_pass * pass_reward(m["pass_margin_m"], c.pass_distance_m)
            if self.task == "overtake"
            else 0.0,
            "collision": c.weight_collision * collision_reward(m["dilated_overlap"]),
            "comfort": c.weight_comfort * comfort_reward(steering_accel),
        }
        arc_left = min(sim.reference.end_m - ag.arc_m for ag in sim.agents)
        flags = termination_flags(
            m["q_lat_m"], m["q_rot_rad"], m["overlap_frac"], self.collision_threshold, arc_left,
            c.max_lateral_m, c.max_rotation_rad, c.end_margin_m,
        )  # fmt: skip
        intervention = flags["off_lane"] or flags["over_rotation"] or flags["collision"]
        succeeded_now = self._success(intervention)
        self._succeeded |= succeeded_now
        end_on_success = self.mode == "eval" or c.end_on_success_in_training
        terminated = any(flags.values()) or (self.task == "overtake" and succeeded_now and end_on_success)
        truncated = (not terminated) and self._t >= c.episode_steps
        flags["time_limit"] = truncated
        if self.task == "overtake" and end_on_success:
            success = succeeded_now
        elif self.task == "overtake":  # a training episode that went on after the pass: no intervention since
            success = self._succeeded and (terminated or truncated) and not intervention
        else:
            success = (terminated or truncated) and not intervention
        info = self._info(reset=False)
        info["rewards"] = terms
        info["termination"] = flags
        info["success"] = bool(success)
        self._timings["rewards"] += 1e3 * (time.perf_counter() - start)
        return float(sum(terms.values())), bool(terminated), bool(truncated), info

    def _lane_error(self) -> float:
        return self._m["q_lat_m"]

    def _success(self, intervention: bool) -> bool:
        return False

    def _measure(self) -> None:
        """The state figures of `info["state"]` for the current step."""
        c, sim = self.config, self.sim
        ego = sim.agents[0]
        index, q_lat, q_long, q_rot = self._assoc
        s = ego.state
        m = {
            "t_s": self._t * c.dt_s,
            "ego_x_m": s.x_m,
            "ego_y_m": s.y_m,
            "ego_yaw_rad": s.yaw_rad,
            "ego_speed_mps": s.speed_mps,
            "q_lat_m": float(q_lat[0]),
            "q_long_m": float(q_long[0]),
            "q_rot_rad": float(q_rot[0]),
            "frame_index": float(index[0]),
            "arc_length_m": ego.arc_m,
            "road_curvature_1pm": sim.reference.curvature(ego.arc_m),
            "steering_curvature_1pm": curvature_of_steering(s.steering_rad, c.wheelbase_m),
            "other_x_m": NAN, "other_y_m": NAN, "other_yaw_rad": NAN, "other_speed_mps": NAN,
            "other_rel_x_m": NAN, "other_rel_y_m": NAN,
            "clearance_m": math.inf, "overlap_frac": 0.0, "pass_margin_m": NAN, "tracking_error_m": NAN,
            "dilated_overlap": 0.0,
        }  # fmt: skip
        if self.has_other:
            other = sim.agents[1]
            o = other.state
            dx, dy = o.x_m - s.x_m, o.y_m - s.y_m
            cy, sy = math.cos(s.yaw_rad), math.sin(s.yaw_rad)
            m.update(other_x_m=o.x_m, other_y_m=o.y_m, other_yaw_rad=o.yaw_rad, other_speed_mps=o.speed_mps)
            m["other_rel_x_m"] = cy * dx + sy * dy
            m["other_rel_y_m"] = -sy * dx + cy * dy
            m["pass_margin_m"] = ego.distance_m - other.distance_m - self._gap_m
            centre = math.hypot(dx, dy)
            if centre > c.far_clearance_m:
                m["clearance_m"] = centre - 0.5 * (
                    math.hypot(ego.length_m, ego.width_m) + math.hypot(other.length_m, other.width_m)
                )
            else:
                ego_pose, other_pose = (s.x_m, s.y_m, s.yaw_rad), (o.x_m, o.y_m, o.yaw_rad)
                ego_size, other_size = (ego.length_m, ego.width_m), (other.length_m, other.width_m)
                m["clearance_m"] = clearance = clearance_m(
                    footprint(*ego_pose, *ego_size), footprint(*other_pose, *other_size)
                )
                # The dilated ego reaches at most 0.5 m further than the ego: beyond that no overlap to compute.
                if clearance < 0.6:
                    m["overlap_frac"] = collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=False)
                    m["dilated_overlap"] = collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=True)
            if self.task == "follow":
                m["tracking_error_m"] = ego.lateral_m - other.profile(ego.arc_m)
        self._m = m

    def _info(self, reset: bool) -> dict:
        state = {k: float(v) for k, v in self._m.items() if k != "dilated_overlap"}
        info: dict[str, Any] = {"state": state}
        if reset:
            info["episode"] = dict(self._episode)
        return info

    # --- observation ---------------------------------------------------------------------------------------------
    def view_request(self) -> tuple:
        """(frame_index, x, y, yaw, cars) of the ego's view now."""
        return self.sim.view_request(0)

    def _render_one(self) -> np.ndarray:
        return render_requests(self.sim.renderer, [self.view_request()], self._timings)[0]

    def observation_from(self, rgb: np.ndarray) -> np.ndarray:
        """The observation (3, h, w) uint8 from the ego's rendered (h, w, 3) view."""
        self._last_rgb = rgb
        return np.ascontiguousarray(self._augmentation.apply(rgb).transpose(2, 0, 1))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One step of dt_s: the action is the normalized steering curvature in [-1, 1]."""
        reward, terminated, truncated, info = self.advance(action)
        return self.observation_from(self._render_one()), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The ego's last view (h, w, 3) uint8, without augmentation."""
        return self._last_rgb

    def expert_action(self) -> np.ndarray:
        """The privileged expert's action for the current state, (1,) float32."""
        from drivesim.sim.envs.expert import expert_action

        return expert_action(self)
