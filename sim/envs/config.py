"""EnvConfig: every parameter of the driving environments, with units (paper §IV-A for the values)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class EnvConfig(BaseModel):
    """Parameters of drivesim/Lane-v0, Follow-v0 and Overtake-v0."""

    model_config = ConfigDict(extra="forbid")

    dt_s: float = 0.1
    """Simulation step in seconds (10 Hz)."""
    episode_steps: int = 300
    """Time limit in steps; reaching it truncates the episode."""
    wheelbase_m: float = 2.7
    """Inter-axle distance L of every vehicle's bicycle model, metres."""
    max_curvature_1pm: float = 0.15
    """Curvature of a full steering action (a = ±1), 1/m."""
    max_steering_rate_radps: float = 1.0
    """Steering-angle rate limit, rad/s."""
    ego_length_m: float = 4.5
    """Length of the ego's footprint, metres."""
    ego_width_m: float = 1.9
    """Width of the ego's footprint, metres."""
    ego_speed_mps: tuple[float, float] = (4.0, 10.0)
    """Range of the ego's speed (lane, overtake), m/s, drawn once per episode."""
    other_speed_mps: tuple[float, float] = (0.0, 4.0)
    """Range of the front car's speed in overtake, m/s."""
    follow_speed_mps: tuple[float, float] = (4.0, 8.0)
    """Range of the common speed of both cars in follow, m/s."""
    front_distance_m: tuple[float, float] = (6.0, 15.0)
    """Range of the front car's start distance ahead of the ego (centre to centre, along the road), metres."""
    front_lateral_m: tuple[float, float] = (1.0, 2.0)
    """Range of the front car's lateral shift from the lane centre (either side, drawn), metres."""
    initial_lateral_m: float = 0.3
    """The ego starts within ± this lateral offset from the lane centre, metres."""
    initial_yaw_rad: float = 0.05
    """The ego starts within ± this heading offset from the road, radians."""
    max_lateral_m: float = 2.5
    """Z_lat: |q_lat| above it ends the episode (off_lane), and R_lane's scale, metres."""
    max_rotation_rad: float = 0.5
    """Z_rot: |q_rot| above it ends the episode (over_rotation), radians."""
    pass_distance_m: float = 6.0
    """Z_pass: the ego has passed when it is this far ahead of the front car (centre to centre along the road), m."""
    return_lateral_m: float = 0.75
    """Overtake succeeds once passed and back within this lateral offset of the lane centre, metres."""
    end_on_success_in_training: bool = False
    """Whether a training (mode "train") overtake episode ends at its success. Off (the default), it goes on to the
    time limit, so R_pass, paid per step once ahead, makes passing worth more than following the slow car in the
    lane; ended at the pass, an episode that stays behind collects more R_lane and the policy learns not to pass.
    Evaluation always ends at the success (its metric)."""
    collision_overlap_train: float = 0.05
    """Overlap of the undilated footprints (fraction of the ego's area) above which training counts a collision."""
    collision_overlap_eval: float = 0.0
    """The same threshold in evaluation (any overlap is an intervention)."""
    pursuit_gain: float = 0.8
    """Pure-pursuit gain of the other cars."""
    pursuit_lookahead_m: float = 5.0
    """Pure-pursuit lookahead of the other cars, metres."""
    min_path_length_m: float = 60.0
    """Road needed ahead of an episode's start, metres; a world shorter than it is refused."""
    end_margin_m: float = 8.0
    """end_of_data when an agent is within this distance of the end of the recorded path, metres."""
    weight_lane: float = 1.0
    """Weight of R_lane = 1 - (q_lat / Z_lat)^2 (follow: q_lat from the front car's path)."""
    weight_pass: float = 1.0
    """Weight of R_pass (1 per step once the ego is Z_pass ahead)."""
    weight_collision: float = 10.0
    """Weight of R_collision = -|Dilate(P_ego) ∩ P_other| / |P_ego|."""
    weight_comfort: float = 0.01
    """Weight of R_comfort = -|δ̈| (rad/s²)."""
    roi_px: tuple[int, int, int, int] | None = None
    """(x0, y0, w, h) region of the world's sim image that the policy sees, pixels; None: the largest region with
    the observation's aspect, centred across and at the bottom of the image ((0, 72, 320, 128) at 320 x 200)."""
    out_width_px: int = 160
    """Width of the observation, pixels."""
    out_height_px: int = 64
    """Height of the observation, pixels."""
    augment: bool = True
    """Episode-level photometric augmentation in training (never in evaluation)."""
    gamma: tuple[float, float] = (0.8, 1.25)
    """Range of the gamma exponent."""
    brightness: tuple[float, float] = (-0.1, 0.1)
    """Range of the added brightness, fraction of full scale."""
    contrast: tuple[float, float] = (0.8, 1.2)
    """Range of the contrast factor around mid-grey."""
    saturation: tuple[float, float] = (0.7, 1.3)
    """Range of the saturation factor."""
    far_clearance_m: float = 10.0
    """Beyond this centre distance the clearance is the centre distance minus both half-diagonals (no polygons)."""
