"""drivesim/Lane-v0: keep the lane of the recorded drive, alone on the road."""

from __future__ import annotations

from drivesim.sim.envs.base import DrivingEnv
from drivesim.sim.envs.config import EnvConfig


class LaneEnv(DrivingEnv):
    """Lane keeping in a data-driven world (paper §III-C).

    ## Action space
    Box(-1, 1, (1,), float32): the normalized steering curvature; the commanded path curvature is
    a · max_curvature_1pm (1/m, + = left), tracked through the steering rate u_δ under max_steering_rate_radps.

    ## Observation space
    Box(0, 255, (3, observation_height_px, observation_width_px), uint8): the ego camera's region of interest
    `roi_px` of the view synthesized at the ego's pose, scaled to the output size, channels first (RGB), with the
    episode's photometric augmentation in training.

    ## Rewards (each weighted term by name in info["rewards"], their sum is the reward)
    lane = weight_lane · (1 - (q_lat / Z_lat)²); comfort = -weight_comfort · |δ̈|; collision is 0.

    ## Start state
    A random place of the recorded path with at least min_path_length_m of road ahead; the ego within
    ±initial_lateral_m of the lane centre, ±initial_yaw_rad of the road heading, steering with the road's curve there
    (within max_curvature_1pm), at a speed drawn from ego_speed_mps and held. Other cars start steering with the road
    too.

    ## Episode end
    Terminated: off_lane (|q_lat| > Z_lat = max_lateral_m), over_rotation (|q_rot| > Z_rot = max_rotation_rad),
    end_of_data (end_margin_m before the end of the recording). Truncated: time_limit after episode_steps steps.
    info["success"]: the episode ended without off_lane, over_rotation or collision.
    """

    task = "lane"
    has_other = False

    @classmethod
    def default_config(cls) -> EnvConfig:
        """The base's, with each training episode's camera pitched by up to 3 degrees, a blur and sensor noise."""
        return (
            super()
            .default_config()
            .model_copy(update={"pitch_jitter_deg": 3.0, "blur_sigma_px": (0.0, 1.0), "noise_std": (0.0, 0.03)})
        )
