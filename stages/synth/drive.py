"""The drive: the ego car following the right lane centre with a smoothly varying speed.

Speed is `v(t) = v0 + A sin(2 pi t / P)`, so arc length, speed and acceleration are closed-form in time; the car
has no side slip, so its heading is the lane's heading and its yaw rate is curvature times speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivesim.sim.geometry import pose_2d
from drivesim.stages.synth.config import DriveConfig
from drivesim.stages.synth.road import RoadPath


def arc_length_at(cfg: DriveConfig, t_s: np.ndarray | float) -> np.ndarray:
    """Arc length along the lane at time(s) `t_s` since the start of the drive (the integral of the speed)."""
    w = 2.0 * np.pi / cfg.speed_period_s
    t = np.asarray(t_s, float)
    return cfg.start_m + cfg.speed_mps * t + cfg.speed_variation_mps / w * (1.0 - np.cos(w * t))


def required_path_length_m(cfg: DriveConfig) -> float:
    """Lane length the drive needs, with 60 m to spare for the camera's view ahead."""
    return float(arc_length_at(cfg, cfg.duration_s)) + 60.0


@dataclass(frozen=True)
class Trajectory:
    """The ego vehicle's motion along `path` (the right lane centre).

    :param path: the lane-centre path the car follows.
    :param cfg: the drive's speed profile and start.
    """

    path: RoadPath
    cfg: DriveConfig

    def _omega(self) -> float:
        return 2.0 * np.pi / self.cfg.speed_period_s

    def speed_mps(self, t_s: np.ndarray | float) -> np.ndarray:
        """Forward speed at time(s) `t_s` since the start of the drive."""
        return self.cfg.speed_mps + self.cfg.speed_variation_mps * np.sin(self._omega() * np.asarray(t_s, float))

    def accel_mps2(self, t_s: np.ndarray | float) -> np.ndarray:
        """Forward acceleration (time derivative of speed)."""
        w = self._omega()
        return self.cfg.speed_variation_mps * w * np.cos(w * np.asarray(t_s, float))

    def arc_length_m(self, t_s: np.ndarray | float) -> np.ndarray:
        """Arc length along the path at time(s) `t_s` (integral of the speed)."""
        return arc_length_at(self.cfg, t_s)

    def state(self, t_s: np.ndarray | float) -> dict[str, np.ndarray]:
        """Ground-truth state at time(s) `t_s`: x_m, y_m, yaw_rad, speed_mps, accel_mps2, curvature_1pm,
        yaw_rate_radps, lateral_accel_mps2, arc_length_m."""
        s = self.arc_length_m(t_s)
        if np.any(s > self.path.length_m):
            raise ValueError(f"the drive reaches {np.max(s):.0f} m but the lane is {self.path.length_m:.0f} m long")
        p = self.path.at(s)
        v = self.speed_mps(t_s)
        return {
            **p,
            "arc_length_m": s,
            "speed_mps": v,
            "accel_mps2": self.accel_mps2(t_s),
            "yaw_rate_radps": p["curvature_1pm"] * v,
            "lateral_accel_mps2": p["curvature_1pm"] * v * v,
        }

    def vehicle_pose(self, t_s: float) -> np.ndarray:
        """T_world_vehicle (4x4) of base_link (rear axle on the ground, x forward) at time `t_s`."""
        p = self.state(t_s)
        return pose_2d(float(p["x_m"]), float(p["y_m"]), float(p["yaw_rad"]))
