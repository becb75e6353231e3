"""The common driving environment: one ego agent (the policy) and, for follow and overtake, one front car.

Subclasses (`lane.py`, `follow.py`, `overtake.py`, `cutin.py`, listed in `registry.py`) own their task through the
hooks of `DrivingEnv` (its default config, start state of the other car, reward terms, success and whether it ends
the episode, per-task measurements, evaluation scenarios, the expert's target offset); the base never asks which task
it is. Their class docstrings
describe spaces, rewards, start and end in one place. The step is split into `advance` (dynamics,
association, rewards) and `observation_from` (augmentation of a rendered view) so that `vector.py` can render many
episodes in one call.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, ClassVar

import cv2
import gymnasium
import numpy as np
from gymnasium import spaces

from drivesim.sim.agents import Agent, LateralProfile, ReferencePath, pursue_profile
from drivesim.sim.dynamics import BicycleState, curvature_of_steering, steering_for_curvature
from drivesim.sim.envs.augment import Augmentation, ViewJitter
from drivesim.sim.envs.config import TASK_ONLY_KEYS, EnvConfig
from drivesim.sim.envs.rewards import collision_reward, comfort_reward, lane_reward
from drivesim.sim.envs.roi import roi_for
from drivesim.sim.envs.termination import termination_flags
from drivesim.sim.footprint import collision_overlap, pose_clearance_m
from drivesim.sim.simulator import TIMING_KEYS, Simulator, make_view_synthesizer, render_requests
from drivesim.sim.world import World

DEFAULT_OTHER_SIZE_M = (4.5, 1.9)
MEMORY_SCALE_M = (10.0, 3.0)
"""`memory_target`'s units: the other car's forward and left offsets from the ego are given in these metres."""
MEMORY_CLIP = 3.0
"""`memory_target` is clipped to +-this (a car far ahead or behind weighs no more than one 30 m away)."""
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
                f"(needs {min_length_m:.0f} m: min_path_length_m + end_margin_m); record a longer drive or set the "
                "env's min_path_length_m lower"
            )
        worlds.append(w)
    return worlds


def load_vehicles(meshes: Any) -> Any:
    """The vehicle library from a `meshes/` folder, or the procedural one for None."""
    if meshes is not None and not Path(meshes).exists():
        raise FileNotFoundError(f"{meshes}: no such meshes folder; run `drivesim meshes build` or pass meshes=None")
    from drivesim.sim.vehicle_library import VehicleLibrary  # trimesh: only for tasks with other cars

    return VehicleLibrary.procedural() if meshes is None else VehicleLibrary.load(meshes)


class DrivingEnv(gymnasium.Env):
    """Base of the drivesim tasks (see the subclasses for the task documentation).

    `config`: an `EnvConfig` is taken whole; a dict (or None) gives its keys over the task's `default_config()`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    task = "lane"
    _mirrored = False  # this episode seen mirrored (EnvConfig.mirror_probability); drawn at each reset
    _jitter = ViewJitter()  # this episode's pitch, blur and noise (EnvConfig.pitch_jitter_deg, ...); drawn at reset
    has_other = False
    task_keys: ClassVar[tuple[str, ...]] = ()
    """The keys of `config.TASK_ONLY_KEYS` this task reads (`config_keys`)."""

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
        self.config = config if isinstance(config, EnvConfig) else self.config_with(config or {})
        self.mode = mode
        self.render_mode = render_mode
        c = self.config
        self.worlds = load_worlds(world, c.min_path_length_m + c.end_margin_m)
        self._check_front_car_fits()
        self._rois = [roi_for(w, c) for w in self.worlds]  # a camera too small for the view is refused here
        self.vehicles = load_vehicles(meshes) if self.has_other else None
        self.collision_threshold = c.collision_overlap_train if mode == "train" else c.collision_overlap_eval
        self._timings = dict.fromkeys(TIMING_KEYS, 0.0)
        self._renderers: dict[int, Any] = {}
        self.observation_space = spaces.Box(0, 255, c.observation_shape, np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.step_count = 0
        self.sim: Simulator | None = None
        self._last_rgb: np.ndarray | None = None

    # --- the task's config ---------------------------------------------------------------------------------------
    @classmethod
    def default_config(cls) -> EnvConfig:
        """The task's env config as it is trained; a task extends its base's (`model_copy(update=...)`)."""
        return EnvConfig()

    @classmethod
    def config_with(cls, overrides: dict[str, Any]) -> EnvConfig:
        """The task's `default_config()` with `overrides` (keys of `EnvConfig`) on top, validated."""
        return EnvConfig.model_validate({**cls.default_config().model_dump(), **overrides})

    @classmethod
    def config_keys(cls) -> tuple[str, ...]:
        """The `EnvConfig` keys this task reads: every task's, and its own of `TASK_ONLY_KEYS`."""
        return tuple(k for k in EnvConfig.model_fields if k not in TASK_ONLY_KEYS or k in cls.task_keys)

    @classmethod
    def scenarios(cls) -> tuple[dict[str, dict[str, Any]], ...]:
        """Named evaluation scenarios as env settings, in groups whose members exclude each other (choose at most one
        per group: `drivesim eval --scenario`); () for a task without scenarios."""
        return ()

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

    def _check_front_car_fits(self) -> None:
        """Refuse a front car placed past the road an episode is sure to have: such an episode ends at its first step
        with end_of_data (every agent must stay end_margin_m from the end of the recording), which no figure shows."""
        c = self.config
        ahead_m = self._farthest_start_ahead_m()
        if ahead_m is not None and ahead_m > c.min_path_length_m:
            raise ValueError(
                f"front_distance_m up to {ahead_m:g} m puts the front car past the "
                f"{c.min_path_length_m:g} m of road an episode is sure to have ahead (min_path_length_m): such "
                "episodes end at their first step; give front_distance_m within min_path_length_m"
            )

    # --- episode start -------------------------------------------------------------------------------------------
    def roi_px_of(self, world_index: int = 0) -> tuple[int, int, int, int]:
        """(x0, y0, w, h) of world `world_index`'s sim image that the policy sees (`roi.py`)."""
        return self._rois[world_index]

    def _renderer(self, world_index: int) -> Any:
        if world_index not in self._renderers:
            c, world = self.config, self.worlds[world_index]
            roi = self.roi_px_of(world_index)
            self._renderers[world_index] = make_view_synthesizer(
                world, roi, c.observation_width_px, c.observation_height_px, device=c.render_device,
                render_threads=c.render_threads, harmonizer=c.harmonizer,
            )  # fmt: skip
        return self._renderers[world_index]

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """A new episode; the same seed gives the same episode and observation."""
        self.reset_state(seed)
        info = self._info(reset=True)
        return self.observation_from(self._render_one()), info

    def _road_steering_rad(self, arc_m: float) -> float:
        """The steering angle that follows the road's curve at `arc_m` (within the steering limit): every car starts
        steering with the road, as the recorded car was, so that a start in a bend is not a start off the road."""
        c = self.config
        curvature_1pm = float(np.clip(self.sim.reference.curvature(arc_m), -c.max_curvature_1pm, c.max_curvature_1pm))
        return steering_for_curvature(curvature_1pm, c.wheelbase_m)

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
        ego_state = BicycleState(x, y, yaw + yaw0, self._road_steering_rad(start_arc), ego_speed)
        ego = Agent(ego_state, c.ego_length_m, c.ego_width_m, ego_speed)
        ego.arc_m, ego.lateral_m = start_arc, lat0
        sim.agents, sim.models = [ego], [None]
        self._gap_m = NAN
        self._other_lateral_m = NAN
        if self.has_other:
            model = self.vehicles.sample(rng) if self.vehicles is not None else None
            size = DEFAULT_OTHER_SIZE_M if model is None else (model.length_m, model.width_m)
            arc, lateral, profile = self._place_other(rng, start_arc, ref, ego_speed, other_speed)
            ox, oy, oyaw = ref.pose(arc, profile(arc))
            other_state = BicycleState(ox, oy, oyaw, self._road_steering_rad(arc), other_speed)
            other = Agent(other_state, size[0], size[1], other_speed, profile)
            other.arc_m, other.lateral_m = arc, profile(arc)
            sim.agents.append(other)
            sim.models.append(model)
            self._gap_m, self._other_lateral_m = arc - start_arc, lateral
        sim.associate()
        for agent in sim.agents:
            agent.frame_index = int(np.argmin(np.abs(ref.arc_m - agent.arc_m)))
        self._assoc = self._associate()
        self._u_steer = 0.0
        self._t = 0
        self._succeeded = False
        # Only quantities the task has: NaN for an absent one would make equal infos compare unequal (NaN != NaN).
        self._episode = {
            "seed": seed,
            "world": str(world.root),
            "start_frame": int(sim.agents[0].frame_index),
            "ego_speed_mps": ego_speed,
            "initial_lateral_m": (self._other_lateral_m - lat0) if self.has_other else lat0,
            "road_curvature_1pm": ref.mean_abs_curvature(start_arc, c.min_path_length_m),
            "ego_length_m": c.ego_length_m,
            "ego_width_m": c.ego_width_m,
        }
        if self.has_other:
            other = sim.agents[1]
            self._episode.update(
                other_speed_mps=other_speed,
                other_lateral_m=self._other_lateral_m,
                other_length_m=other.length_m,
                other_width_m=other.width_m,
            )
        aug_on = c.augment and self.mode == "train"
        self._augmentation = (
            Augmentation.sample(rng, c.gamma, c.brightness, c.contrast, c.saturation, c.grey_probability)
            if aug_on
            else Augmentation()
        )
        # drawn only when asked for, so that the draws of a config without mirroring stay as they were
        self._mirrored = bool(aug_on and c.mirror_probability > 0.0 and rng.uniform() < c.mirror_probability)
        self._jitter = self._sample_jitter(rng) if aug_on else ViewJitter()
        self._measure()

    def _sample_jitter(self, rng: np.random.Generator) -> ViewJitter:
        """The episode's pitch, blur, noise and erased rectangles (`ViewJitter`); nothing is drawn when all are off,
        so the draws of a config without them stay as they were."""
        c = self.config
        if (
            c.pitch_jitter_deg == 0.0
            and max(c.blur_sigma_px) == 0.0
            and max(c.noise_std) == 0.0
            and c.cutout_count[1] == 0
        ):
            return ViewJitter()
        world = self.worlds[self._world_index]
        focal_rows_px = float(world.K[1, 1]) * c.observation_height_px / self.roi_px_of(self._world_index)[3]
        return ViewJitter.sample(
            rng, c.pitch_jitter_deg, focal_rows_px, c.blur_sigma_px, c.noise_std, c.cutout_count, c.cutout_size
        )

    # --- task hooks (a task subclass overrides what it needs; the base never asks which task it is) -----------
    def _farthest_start_ahead_m(self) -> float | None:
        """How far ahead of the ego the other car may start at most, metres (`_place_other`'s front_distance_m);
        None: no other car, or one that does not start ahead."""
        return self.config.front_distance_m[1] if self.has_other else None

    def _speeds(self, rng: np.random.Generator) -> tuple[float, float]:
        """(ego, other) speeds of a new episode from ego_speed_mps and other_speed_mps, m/s (NaN: no other car)."""
        c = self.config
        ego = float(rng.uniform(*c.ego_speed_mps))
        return ego, float(rng.uniform(*c.other_speed_mps)) if self.has_other else NAN

    def _place_other(
        self,
        rng: np.random.Generator,
        ego_arc_m: float,
        ref: ReferencePath,
        ego_speed_mps: float,
        other_speed_mps: float,
    ) -> tuple[float, float, LateralProfile]:
        """(arc_m, lateral_m, profile) of the other car at the start: by default a front car front_distance_m
        ahead, front_lateral_m to the side front_side says (drawn for "either"), keeping its offset
        (`_other_profile`)."""
        c = self.config
        arc = ego_arc_m + float(rng.uniform(*c.front_distance_m))
        side = 1.0 if rng.uniform() < 0.5 else -1.0  # drawn in every case: the same seed, the same other draws
        side = {"left": 1.0, "right": -1.0}.get(c.front_side, side)
        lateral = side * float(rng.uniform(*c.front_lateral_m))
        return arc, lateral, self._other_profile(rng, arc, lateral, ref)

    def _other_profile(
        self, rng: np.random.Generator, arc_m: float, lateral_m: float, ref: ReferencePath
    ) -> LateralProfile:
        """The other car's lateral offset along the road (m, + = left) from its start."""
        return LateralProfile.constant(lateral_m)

    def _reward_terms(self, steering_accel_radps2: float) -> dict[str, float]:
        """The weighted reward terms by name (their sum is the reward): lane, collision and comfort; a task adds its
        own (overtake's pass)."""
        c, m = self.config, self._m
        return {
            "lane": c.weight_lane * lane_reward(self._lane_error(), c.max_lateral_m),
            "collision": c.weight_collision * collision_reward(m["dilated_overlap"]),
            "comfort": c.weight_comfort * comfort_reward(steering_accel_radps2),
        }

    def _lane_error(self) -> float:
        """The lateral error R_lane penalizes, m (the lane centre's by default)."""
        return self._m["q_lat_m"]

    def _success_now(self, intervention: bool) -> bool:
        """Whether the task's goal is reached at this step (tasks whose success is the time limit: never)."""
        return False

    def _ends_at_success(self) -> bool:
        """Whether reaching the goal ends the episode (tasks whose success is the time limit: no)."""
        return False

    def _episode_success(self, ended: bool, intervention: bool, succeeded_now: bool) -> bool:
        """info["success"]: by default, the episode ended without an intervention."""
        return ended and not intervention

    def _task_measurements(self) -> dict[str, float]:
        """Figures of `info["state"]` that only this task has (e.g. the pass margin of overtake)."""
        return {}

    def expert_target_offset(self) -> float:
        """The lateral offset (m, + = left of the lane centre) the privileged expert steers to now."""
        return 0.0

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
        a = -a if self._mirrored else a  # the policy steers in the mirrored picture it sees
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
        terms = self._reward_terms(steering_accel)
        arc_left = min(sim.reference.end_m - ag.arc_m for ag in sim.agents)
        flags = termination_flags(
            m["q_lat_m"], m["q_rot_rad"], m["overlap_frac"], self.collision_threshold, arc_left,
            c.max_lateral_m, c.max_rotation_rad, c.end_margin_m,
        )  # fmt: skip
        intervention = flags["off_lane"] or flags["over_rotation"] or flags["collision"]
        succeeded_now = self._success_now(intervention)
        self._succeeded |= succeeded_now
        terminated = any(flags.values()) or (succeeded_now and self._ends_at_success())
        truncated = (not terminated) and self._t >= c.episode_steps
        flags["time_limit"] = truncated
        success = self._episode_success(terminated or truncated, intervention, succeeded_now)
        info = self._info(reset=False)
        info["rewards"] = terms
        info["termination"] = flags
        info["success"] = bool(success)
        self._timings["rewards"] += 1e3 * (time.perf_counter() - start)
        return float(sum(terms.values())), bool(terminated), bool(truncated), info

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
            "clearance_m": math.inf, "overlap_frac": 0.0, "dilated_overlap": 0.0,
        }  # fmt: skip
        if self.has_other:
            other = sim.agents[1]
            o = other.state
            dx, dy = o.x_m - s.x_m, o.y_m - s.y_m
            cy, sy = math.cos(s.yaw_rad), math.sin(s.yaw_rad)
            m.update(other_x_m=o.x_m, other_y_m=o.y_m, other_yaw_rad=o.yaw_rad, other_speed_mps=o.speed_mps)
            m["other_rel_x_m"] = cy * dx + sy * dy
            m["other_rel_y_m"] = -sy * dx + cy * dy
            centre = math.hypot(dx, dy)
            if centre > c.far_clearance_m:
                m["clearance_m"] = centre - 0.5 * (
                    math.hypot(ego.length_m, ego.width_m) + math.hypot(other.length_m, other.width_m)
                )
            else:
                ego_pose, other_pose = (s.x_m, s.y_m, s.yaw_rad), (o.x_m, o.y_m, o.yaw_rad)
                ego_size, other_size = (ego.length_m, ego.width_m), (other.length_m, other.width_m)
                m["clearance_m"] = clearance = pose_clearance_m(ego_pose, ego_size, other_pose, other_size)
                # The dilated ego reaches at most 0.5 m further than the ego: beyond that no overlap to compute.
                if clearance < 0.6:
                    m["overlap_frac"] = collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=False)
                    m["dilated_overlap"] = collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=True)
        self._m = m
        m.update(self._task_measurements())

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
        view = self._jitter.apply(self._augmentation.apply(rgb))
        view = view[:, ::-1] if self._mirrored else view
        if not (view.flags.c_contiguous and view.ndim == 3 and view.shape[2] == 3):
            return np.ascontiguousarray(view.transpose(2, 0, 1))
        # Channels first by OpenCV's split into the rows of one array: 4 us at 160 x 64, numpy's strided copy 16 us.
        chw = np.empty((3, *view.shape[:2]), dtype=view.dtype)
        cv2.split(view, [chw[0], chw[1], chw[2]])
        return chw

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One step of dt_s: the action is the normalized steering curvature in [-1, 1]."""
        reward, terminated, truncated, info = self.advance(action)
        return self.observation_from(self._render_one()), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The ego's last view (h, w, 3) uint8, without augmentation."""
        return self._last_rgb

    def place_ego(self, arc_m: float, lateral_m: float, heading_rad: float = 0.0) -> np.ndarray:
        """Move the ego, within the current episode, to `lateral_m` left of the path at arc length `arc_m` with its
        heading `heading_rad` off the road's (counter-clockwise +), and return its observation there; the state
        (`lane_position`, `info["state"]`) follows. For diagnostics and probes; the episode's clock is unchanged."""
        ref, ego = self.sim.reference, self.sim.agents[0]
        x, y, yaw = ref.pose(arc_m, lateral_m)
        ego.state = BicycleState(x, y, yaw + heading_rad, 0.0, ego.state.speed_mps)
        ego.frame_index = int(np.argmin(np.abs(ref.arc_m - arc_m)))
        self._assoc = self._associate()
        self._measure()
        return self.observation_from(self._render_one())

    def lane_position(self) -> np.ndarray:
        """The ego's lateral offset from the lane centre (m, + = left) and its heading relative to the lane (rad) now,
        as the policy's picture shows them (mirrored with a mirrored episode): (2,) float32."""
        sign = -1.0 if self._mirrored else 1.0
        return np.array([sign * self._m["q_lat_m"], sign * self._m["q_rot_rad"]], dtype=np.float32)

    def memory_target(self) -> np.ndarray:
        """Where the other car is from the ego, as the policy's picture shows it (mirrored with a mirrored episode):
        (forward / MEMORY_SCALE_M[0], left / MEMORY_SCALE_M[1]) in the ego's frame, clipped to +-MEMORY_CLIP, (2,)
        float32; zeros without another car. Privileged: a training target, never an input."""
        if not self.has_other:
            return np.zeros(2, dtype=np.float32)
        ego, other = self.sim.agents[0].state, self.sim.agents[1].state
        dx, dy = other.x_m - ego.x_m, other.y_m - ego.y_m
        cos, sin = math.cos(ego.yaw_rad), math.sin(ego.yaw_rad)
        forward_m, left_m = cos * dx + sin * dy, -sin * dx + cos * dy
        left_m = -left_m if self._mirrored else left_m
        scaled = np.array([forward_m / MEMORY_SCALE_M[0], left_m / MEMORY_SCALE_M[1]], dtype=np.float32)
        return np.clip(scaled, -MEMORY_CLIP, MEMORY_CLIP)

    def expert_action(self) -> np.ndarray:
        """The privileged expert's action for the current state, (1,) float32 (it steers to
        `expert_target_offset()`)."""
        from drivesim.sim.envs.expert import expert_action

        action = expert_action(self)
        return -action if self._mirrored else action
