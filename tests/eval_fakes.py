"""Hand-made trajectories and a small fake driving env for the evaluation tests (no world, no renderer).

The fake env has the same spaces and `info` keys as drivesim's envs (INTERFACES §3) on a straight road along x
(lane centre y = 0, one recorded frame per metre), so the rollout, its workers and the report can be tested before
(and independently of) the real simulator.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

from drivesim.sim.footprint import footprint
from drivesim.stages.evaluate.metrics import EpisodeRecord

EGO_SIZE_M = (4.5, 1.8)
OTHER_SIZE_M = (4.5, 1.8)


def pass_record(
    lateral_m: float,
    seed: int = 0,
    ramp_m: float = 12.0,
    stop_at_overlap: bool = True,
    limits: dict[str, float] | None = None,
) -> EpisodeRecord:
    """An overtake on a straight road: the front car drives along y = 0 at 5 m/s from 25 m ahead; the ego at 9 m/s
    moves over to y = `lateral_m` by a cosine ramp over `ramp_m` metres (done 8 m behind the front car), stays there
    while passing, and comes back after it is 8 m ahead. Yaw follows the path's slope. Ends at the first overlap
    when `stop_at_overlap` (as the env would), else after 120 steps of 0.1 s.
    """
    dt = 0.1
    ego_x0, other_x0, ego_v, other_v = 0.0, 25.0, 9.0, 5.0
    rows = []
    overlap_seen = False
    for i in range(121):
        t = i * dt
        ex, ox = ego_x0 + ego_v * t, other_x0 + other_v * t
        gap = ex - ox  # ego ahead of the front car by gap (centres)
        ey, slope = _ramp(gap, lateral_m, ramp_m)
        eyaw = math.atan2(slope * (ego_v - other_v), ego_v)  # dy/dt = dy/dgap * (v_e - v_f); dx/dt = v_e
        rows.append((t, ex, ey, eyaw, ox, 0.0, 0.0))
        ego = footprint(ex, ey, eyaw, *EGO_SIZE_M)
        other = footprint(ox, 0.0, 0.0, *OTHER_SIZE_M)
        if stop_at_overlap and ego.intersection(other).area > 0:
            overlap_seen = True
            break
    traj = _trajectory(np.array(rows))
    termination = {"off_lane": False, "over_rotation": False, "collision": overlap_seen, "end_of_data": False}
    termination["time_limit"] = not overlap_seen
    return EpisodeRecord(
        seed=seed,
        task="overtake",
        episode=_episode_info(seed, lateral_m=0.0),
        trajectory=traj,
        termination=termination,
        success=not overlap_seen,
        limits=limits or {},
    )


def lane_departure_record(seed: int = 0, drift_mps: float = 0.6, limit_m: float = 2.0) -> EpisodeRecord:
    """The ego drifts left at `drift_mps` with no car near until |q_lat| > `limit_m` (the env ends it: off_lane)."""
    dt, v = 0.1, 8.0
    rows = []
    yaw = math.atan2(drift_mps, v)
    for i in range(200):
        t = i * dt
        y = drift_mps * t
        rows.append((t, v * t, y, yaw))
        if y > limit_m:
            break
    a = np.array(rows)
    far_ahead = np.column_stack([a[:, 1] + 60.0, np.zeros((len(a), 2))])  # never near
    traj = _trajectory(np.column_stack([a, far_ahead]))
    termination = {"off_lane": True, "over_rotation": False, "collision": False, "end_of_data": False}
    return EpisodeRecord(seed, "overtake", _episode_info(seed, 1.5), traj, termination, success=False)


def _trajectory(a: np.ndarray) -> dict[str, np.ndarray]:
    """An episode's trajectory on a straight road along x from rows (t, ego x, y, yaw, other x, y, yaw): the lane
    centre is y = 0, one recorded frame per metre."""
    n = len(a)
    return {
        "t_s": a[:, 0],
        "ego_x_m": a[:, 1],
        "ego_y_m": a[:, 2],
        "ego_yaw_rad": a[:, 3],
        "q_lat_m": a[:, 2],
        "q_rot_rad": a[:, 3],
        "frame_index": np.floor(a[:, 1]),
        "arc_length_m": a[:, 1],
        "road_curvature_1pm": np.zeros(n),
        "other_x_m": a[:, 4],
        "other_y_m": a[:, 5],
        "other_yaw_rad": a[:, 6],
        "tracking_error_m": np.full(n, np.nan),
        "action": np.zeros(n),
    }


def _ramp(gap_m: float, lateral_m: float, ramp_m: float) -> tuple[float, float]:
    """Lateral offset and its slope d(offset)/d(gap) along the pass: out before gap -8 m, back after gap +8 m."""
    start_out, start_back = -8.0 - ramp_m, 8.0
    if gap_m <= start_out or gap_m >= start_back + ramp_m:
        return 0.0, 0.0
    if gap_m < start_out + ramp_m:
        u = (gap_m - start_out) / ramp_m
        return 0.5 * lateral_m * (1 - math.cos(math.pi * u)), 0.5 * lateral_m * math.pi / ramp_m * math.sin(math.pi * u)
    if gap_m <= start_back:
        return lateral_m, 0.0
    u = (gap_m - start_back) / ramp_m
    return 0.5 * lateral_m * (1 + math.cos(math.pi * u)), -0.5 * lateral_m * math.pi / ramp_m * math.sin(math.pi * u)


def _episode_info(seed: int, lateral_m: float, curvature: float = 0.0, other_speed: float = 5.0) -> dict[str, Any]:
    return {
        "seed": seed,
        "world": "fake",
        "start_frame": 0,
        "ego_speed_mps": 9.0,
        "other_speed_mps": other_speed,
        "initial_lateral_m": lateral_m,
        "road_curvature_1pm": curvature,
        "ego_length_m": EGO_SIZE_M[0],
        "ego_width_m": EGO_SIZE_M[1],
        "other_length_m": OTHER_SIZE_M[0],
        "other_width_m": OTHER_SIZE_M[1],
    }


class FakeDrivingEnv(gymnasium.Env):
    """A straight-road two-car env with drivesim's spaces and info keys (INTERFACES §3), for the eval tests.

    The ego (kinematic, steering = curvature) starts at x = 0 behind a front car 6-15 m ahead shifted 1-2 m
    laterally (random side); the front car drives straight. Ends on overlap > 0 (eval), |q_lat| > 2.5 m,
    |q_rot| > 0.5 rad, the end of the 200 m of "data", or 120 steps. `expert_action()` steers around the front car.
    """

    metadata = {"render_modes": []}
    DT_S = 0.1
    MAX_CURVATURE_1PM = 0.15
    MAX_LATERAL_M = 2.5
    MAX_ROTATION_RAD = 0.5
    STEPS = 120
    ROAD_LENGTH_M = 200.0

    def __init__(
        self, world: Any = None, meshes: Any = None, mode: str = "eval", config: Any = None, task: str = "overtake"
    ):
        self.task = task
        self.world = world
        if world is not None and str(world).endswith("too-short"):
            raise ValueError(f"{world}: the world has 10 frames; the {task} task needs at least 100")
        self.observation_space = gymnasium.spaces.Box(0, 255, (3, 64, 160), np.uint8)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.step_count = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        self.ego = np.array([0.0, 0.0, 0.0])
        self.ego_v = float(rng.uniform(8.0, 10.0))
        side = 1.0 if rng.random() < 0.5 else -1.0
        self.other = np.array([float(rng.uniform(6.0, 15.0)), side * float(rng.uniform(1.0, 2.0)), 0.0])
        self.other_v = float(rng.uniform(3.0, 6.0)) if self.task == "overtake" else self.ego_v
        self.curvature = float(rng.uniform(0.0, 0.02))
        self.t = 0.0
        self.steps = 0
        self.travel = [0.0, 0.0]
        self.episode = {
            "seed": seed,
            "world": str(self.world),
            "start_frame": 0,
            "ego_speed_mps": self.ego_v,
            "other_speed_mps": self.other_v,
            "initial_lateral_m": float(self.other[1]),
            "road_curvature_1pm": self.curvature,
            "ego_length_m": EGO_SIZE_M[0],
            "ego_width_m": EGO_SIZE_M[1],
            "other_length_m": OTHER_SIZE_M[0],
            "other_width_m": OTHER_SIZE_M[1],
        }
        info = {"state": self._state(), "episode": dict(self.episode)}
        return self._obs(), info

    def _state(self) -> dict[str, float]:
        ex, ey, eyaw = self.ego
        ox, oy, oyaw = self.other
        ego_poly = footprint(ex, ey, eyaw, *EGO_SIZE_M)
        other_poly = footprint(ox, oy, oyaw, *OTHER_SIZE_M)
        return {
            "t_s": self.t,
            "ego_x_m": ex,
            "ego_y_m": ey,
            "ego_yaw_rad": eyaw,
            "ego_speed_mps": self.ego_v,
            "q_lat_m": ey,
            "q_long_m": 0.0,
            "q_rot_rad": eyaw,
            "frame_index": float(min(int(ex), int(self.ROAD_LENGTH_M) - 1)),
            "arc_length_m": ex,
            "road_curvature_1pm": self.curvature,
            "steering_curvature_1pm": 0.0,
            "other_x_m": ox,
            "other_y_m": oy,
            "other_yaw_rad": oyaw,
            "other_speed_mps": self.other_v,
            "other_rel_x_m": ox - ex,
            "other_rel_y_m": oy - ey,
            "clearance_m": float(ego_poly.distance(other_poly)),
            "overlap_frac": float(ego_poly.intersection(other_poly).area / ego_poly.area),
            "pass_margin_m": self.travel[0] - self.travel[1],
            "tracking_error_m": float(abs(ey - oy)) if self.task == "follow" else float("nan"),
        }

    def _obs(self) -> np.ndarray:
        img = np.full((3, 64, 160), 40, np.uint8)
        rel_x, rel_y = self.other[0] - self.ego[0], self.other[1] - self.ego[1]
        if rel_x > 0:
            col = int(np.clip(80 - rel_y * 40 / max(rel_x, 1.0), 0, 159))
            img[0, 20:44, max(col - 8, 0) : col + 8] = 220
        img[1, 50:, :] = np.uint8(np.clip(100 + self.ego[1] * 30, 0, 255))
        return img

    def expert_action(self) -> np.ndarray:
        """Steer to a lateral target: beside the front car (2.6 m away) while near it, else the lane centre."""
        ex, ey, eyaw = self.ego
        ox, oy, _ = self.other
        gap = ex - ox
        target = 0.0
        if self.task == "overtake" and -18.0 < gap < 7.0:
            target = oy - 2.6 if oy > 0 else oy + 2.6
        lookahead = max(self.ego_v, 1.0)
        heading_err = math.atan2(target - ey, lookahead * 1.2) - eyaw
        curvature = 2.0 * math.sin(heading_err) / lookahead
        return np.array([np.clip(curvature / self.MAX_CURVATURE_1PM, -1, 1)], np.float32)

    def step(self, action):
        a = float(np.clip(np.asarray(action, dtype=float).reshape(-1)[0], -1, 1))
        kappa = a * self.MAX_CURVATURE_1PM
        ex, ey, eyaw = self.ego
        eyaw += kappa * self.ego_v * self.DT_S
        ex += self.ego_v * math.cos(eyaw) * self.DT_S
        ey += self.ego_v * math.sin(eyaw) * self.DT_S
        self.ego = np.array([ex, ey, eyaw])
        self.other[0] += self.other_v * self.DT_S
        self.travel[0] += self.ego_v * self.DT_S
        self.travel[1] += self.other_v * self.DT_S
        self.t += self.DT_S
        self.steps += 1
        self.step_count += 1
        state = self._state()
        termination = {
            "off_lane": abs(state["q_lat_m"]) > self.MAX_LATERAL_M,
            "over_rotation": abs(state["q_rot_rad"]) > self.MAX_ROTATION_RAD,
            "collision": state["overlap_frac"] > 0.0,
            "end_of_data": ex >= self.ROAD_LENGTH_M - 1,
        }
        terminated = any(termination.values())
        truncated = not terminated and self.steps >= self.STEPS
        termination["time_limit"] = truncated
        intervention = termination["off_lane"] or termination["over_rotation"] or termination["collision"]
        if self.task == "overtake":
            success = ex > self.other[0] + 5.0 and abs(ey) < 0.5 and not intervention
        else:
            success = truncated and not intervention
        rewards = {"lane": 1.0 - (ey / self.MAX_LATERAL_M) ** 2, "collision": -state["overlap_frac"]}
        info = {"state": state, "termination": termination, "success": bool(success), "rewards": rewards}
        return self._obs(), float(sum(rewards.values())), terminated, truncated, info


def register_fake_envs() -> None:
    """Register the fake envs under test ids (idempotent)."""
    for task, name in (("overtake", "Overtake"), ("follow", "Follow"), ("lane", "Lane")):
        env_id = f"drivesim-test/Fake{name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point="eval_fakes:FakeDrivingEnv", kwargs={"task": task})


FAKE = {"env_id": "drivesim-test/FakeOvertake-v0", "env_entry_point": "eval_fakes:FakeDrivingEnv"}
"""The eval config keys that evaluate in the fake overtake env instead of a drivesim world."""


def fake_env_args(world: Path) -> list[str]:
    """`drivesim eval` arguments that evaluate on `world` in the fake overtake env (`FAKE`), trusted."""
    sets = [a for key in ("env_id", "env_entry_point") for a in ("--set", f"{key}={FAKE[key]}")]
    return ["--world", str(world), *sets, "--trust-entry-point"]


def fake_world(folder: Path, frames: int = 200) -> Path:
    """A folder with just the reference path the fake env reads (path.npz: a gentle curve, 1 m per frame)."""
    folder.mkdir(parents=True, exist_ok=True)
    x = np.arange(float(frames))
    np.savez(folder / "path.npz", x_m=x, y_m=0.002 * x**2, arc_length_m=x)
    return folder
