"""EnvConfig: every parameter of the driving environments, with units (paper §IV-A for the values)."""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Ranges (low, high) whose values are magnitudes (speeds, distances, factors): negative values are refused.
_NON_NEGATIVE_RANGES = (
    "ego_speed_mps", "other_speed_mps", "follow_speed_mps", "front_distance_m", "front_lateral_m", "gamma",
    "contrast", "saturation", "blur_sigma_px", "noise_std", "cutout_count", "cutout_size",
)  # fmt: skip


OTHER_CAR_KEYS: tuple[str, ...] = (
    "front_distance_m", "front_lateral_m", "front_side", "pursuit_gain", "pursuit_lookahead_m", "weight_collision",
    "collision_overlap_train", "collision_overlap_eval", "far_clearance_m",
)  # fmt: skip
"""Keys only tasks with another car read."""
TASK_ONLY_KEYS: tuple[str, ...] = (
    *OTHER_CAR_KEYS, "other_speed_mps", "follow_speed_mps", "pass_distance_m", "return_lateral_m", "weight_pass",
    "redraw_unwinnable", "end_on_success_in_training",
)  # fmt: skip
"""Keys some tasks read and others ignore; every other key is read by every task."""


def check_torch_device(value: str) -> str:
    """A torch device name that this machine has ("cpu", "cuda", "cuda:1"), or a ValueError saying what to give."""
    try:
        device = torch.device(value)
    except (RuntimeError, ValueError) as e:
        raise ValueError(f"{value!r} is not a torch device: give cpu or cuda") from e
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{value!r}: torch sees no CUDA device on this machine; give cpu")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"{value!r}: drivesim runs on cpu or cuda")
    return value


class EnvConfig(BaseModel):
    """Parameters of the driving tasks (sim/envs/registry.py lists them); units in each key's name and docstring.

    One flat model for every task: the keys every task reads first, then `OTHER_CAR_KEYS`, then the keys of one task
    (`TASK_ONLY_KEYS`). Each task's values are its `default_config()` (sim/envs/<task>.py) and the keys it reads its
    `config_keys()`. The train and eval configs hold it as `envs.config` and `env`, so a typo or an out-of-range
    value is refused when the config is loaded.
    """

    # As pipeline.config.STRICT_MODEL_CONFIG (not imported: the simulator does not depend on the stage framework).
    model_config = ConfigDict(
        extra="forbid", use_attribute_docstrings=True, validate_assignment=True, allow_inf_nan=False
    )

    # --- every task -------------------------------------------------------------------------------------------
    dt_s: float = Field(0.1, gt=0.0, le=1.0)
    """Simulation step, seconds (0.1: 10 Hz)."""
    episode_steps: int = Field(300, ge=1)
    """Time limit in steps; reaching it truncates the episode."""
    wheelbase_m: float = Field(2.7, gt=0.0)
    """Inter-axle distance L of every vehicle's bicycle model, metres."""
    max_curvature_1pm: float = Field(0.2, gt=0.0)
    """Path curvature of a full steering action (a = ±1), 1/m; 0.2 is a car's 5 m turning radius, which a recorded
    intersection turn can need."""
    max_steering_rate_radps: float = Field(1.0, gt=0.0)
    """Steering-angle rate limit, rad/s."""
    ego_length_m: float = Field(4.5, gt=0.0)
    """Length of the ego's footprint, metres."""
    ego_width_m: float = Field(1.9, gt=0.0)
    """Width of the ego's footprint, metres."""
    ego_speed_mps: tuple[float, float] = (4.0, 10.0)
    """Range of the ego's speed, drawn once per episode and held, m/s."""
    initial_lateral_m: float = Field(0.3, ge=0.0)
    """The ego starts within ± this lateral offset from the lane centre, metres."""
    initial_yaw_rad: float = Field(0.05, ge=0.0)
    """The ego starts within ± this heading offset from the road, radians."""
    max_lateral_m: float = Field(2.5, gt=0.0)
    """Z_lat: |q_lat| above it ends the episode (off_lane); also R_lane's scale, metres."""
    max_rotation_rad: float = Field(0.5, gt=0.0)
    """Z_rot: |q_rot| above it ends the episode (over_rotation), radians."""
    min_path_length_m: float = Field(60.0, gt=0.0)
    """Road needed ahead of an episode's start, metres; a world shorter than it is refused."""
    end_margin_m: float = Field(8.0, ge=0.0)
    """end_of_data when an agent is within this distance of the end of the recorded path, metres."""
    weight_lane: float = Field(1.0, ge=0.0)
    """Weight of R_lane = 1 - (q_lat / Z_lat)^2 (follow: q_lat from the front car's path)."""
    weight_comfort: float = Field(0.01, ge=0.0)
    """Weight of R_comfort = -|δ̈| (δ̈ in rad/s²)."""
    roi_px: tuple[int, int, int, int] | None = None
    """(x0, y0, w, h) region of the world's sim image the policy sees, pixels; None: `roi_fov_deg`'s region, else the
    largest region of the observation's aspect, centred across, at the image's bottom."""
    roi_fov_deg: float | None = Field(None, gt=0.0, lt=180.0)
    """Horizontal field of view of the policy's image, degrees, placed by each world's camera (the same angles on
    every camera); None: `roi_px`, else the default region."""
    roi_horizon_fraction: float = Field(0.45, ge=0.0, lt=1.0)
    """With `roi_fov_deg`: where the horizon sits in the policy's image, as a fraction of its height from the top."""
    observation_width_px: int = Field(160, ge=8, le=4096)
    """Width of the observation (the policy's image), pixels; observation_shape = (3, height, width)."""
    observation_height_px: int = Field(64, ge=8, le=4096)
    """Height of the observation (the policy's image), pixels."""
    render_device: str = "cpu"
    """torch device the views are rendered on: "cpu", or "cuda" (all the views of a world one process steps are
    rendered in one batch)."""
    harmonizer: Literal["statistical", "learned"] = "statistical"
    """How inserted cars are matched to the frame: statistical (colour statistics moved toward the surroundings') or
    learned (a small network, sim/models/harmonizer.onnx)."""
    render_threads: int = Field(1, ge=1, le=16)
    """On the CPU, most threads each view's warp is split over (the same pixels), fewer while other processes hold
    the cores; 1 where envs already keep every core busy."""
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
    grey_probability: float = Field(0.0, ge=0.0, le=1.0)
    """Share of training episodes shown in grey (saturation 0), for policies that must also drive grey cameras."""
    mirror_probability: float = Field(0.0, ge=0.0, le=1.0)
    """Share of training episodes seen mirrored left to right (the image flipped, steering and expert labels
    negated). Never in evaluation."""
    pitch_jitter_deg: float = Field(0.0, ge=0.0, le=20.0)
    """Each training episode's camera pitch is drawn in ± this, degrees, shown as the image's vertical shift it
    makes; 0: off."""
    blur_sigma_px: tuple[float, float] = (0.0, 0.0)
    """Range of each training episode's Gaussian blur of the policy's image, pixels at the observation's size;
    (0, 0): off."""
    noise_std: tuple[float, float] = (0.0, 0.0)
    """Range of each training episode's per-pixel Gaussian noise, standard deviation as a fraction of full scale,
    new at every step; (0, 0): off."""
    cutout_count: tuple[int, int] = (0, 0)
    """Range (both ends included) of rectangles erased to a random colour from the policy's image at every training
    step; (0, 0): off."""
    cutout_size: tuple[float, float] = (0.1, 0.4)
    """Range of each erased rectangle's width and height, fractions of the image's width and height."""

    # --- tasks with another car (OTHER_CAR_KEYS) --------------------------------------------------------------
    front_distance_m: tuple[float, float] = (6.0, 15.0)
    """Range of the other car's start distance ahead of the ego (cut-in: where it cuts in), centre to centre, m."""
    front_lateral_m: tuple[float, float] = (1.0, 2.0)
    """Range of the other car's lateral shift from the lane centre (either side), metres."""
    front_side: Literal["either", "left", "right"] = "either"
    """Side of the lane centre the other car starts on (left = +); either: drawn per episode."""
    pursuit_gain: float = Field(0.8, gt=0.0)
    """Pure-pursuit gain of the other car (dimensionless)."""
    pursuit_lookahead_m: float = Field(5.0, gt=0.0)
    """Pure-pursuit lookahead of the other car, metres."""
    weight_collision: float = Field(10.0, ge=0.0)
    """Weight of R_collision = -|Dilate(P_ego) ∩ P_other| / |P_ego|."""
    collision_overlap_train: float = Field(0.0, ge=0.0, le=1.0)
    """Overlap of the undilated footprints (fraction of the ego's area) above which training counts a collision;
    0: any overlap, as evaluation."""
    collision_overlap_eval: float = Field(0.0, ge=0.0, le=1.0)
    """The same threshold in evaluation (0: any overlap is an intervention)."""
    far_clearance_m: float = Field(10.0, gt=0.0)
    """Beyond this centre distance, metres, the clearance is the centre distance minus both half-diagonals."""

    # --- one task's own keys (TASK_ONLY_KEYS; each task lists those it reads in `DrivingEnv.task_keys`) ------
    other_speed_mps: tuple[float, float] = (0.0, 4.0)
    """Range of the other car's speed (overtake, cut-in), m/s."""
    follow_speed_mps: tuple[float, float] = (4.0, 8.0)
    """Range of the common speed of both cars in follow, m/s."""
    pass_distance_m: float = Field(6.0, ge=0.0)
    """Z_pass: the ego has passed once this far ahead of the front car (centre to centre, along the road), metres."""
    return_lateral_m: float = Field(0.75, gt=0.0)
    """Overtake succeeds once passed and back within this lateral offset of the lane centre, metres."""
    weight_pass: float = Field(1.0, ge=0.0)
    """Weight of R_pass (1 per step once the ego is Z_pass ahead)."""
    redraw_unwinnable: bool = False
    """Overtake: draw again a start the hardest swerve cannot escape (info["episode"]["winnable"] labels it either
    way)."""
    end_on_success_in_training: bool = False
    """Whether a training overtake episode ends at its success; off: it goes on to the time limit. Evaluation always
    ends at the success."""

    @field_validator("render_device")
    @classmethod
    def _render_device(cls, value: str) -> str:
        return check_torch_device(value)

    @model_validator(mode="after")
    def _check_ranges(self) -> EnvConfig:
        for name, value in self:
            if isinstance(value, tuple) and len(value) == 2 and value[0] > value[1]:
                raise ValueError(f"{name}: the range ({value[0]}, {value[1]}) is reversed; give (low, high)")
            if name in _NON_NEGATIVE_RANGES and value[0] < 0:
                raise ValueError(f"{name}: ({value[0]}, {value[1]}) must not be negative")
        if not (self.cutout_size[0] > 0.0 and self.cutout_size[1] <= 1.0):
            raise ValueError(f"cutout_size: {self.cutout_size} must lie in (0, 1]: fractions of the image's sides")
        if self.gamma[0] <= 0:
            raise ValueError(f"gamma: ({self.gamma[0]}, {self.gamma[1]}) must be positive")
        if self.roi_px is not None and self.roi_fov_deg is not None:
            raise ValueError("roi_px and roi_fov_deg both given: give the region in pixels or in degrees, not both")
        if self.roi_px is not None and (min(self.roi_px) < 0 or self.roi_px[2] < 1 or self.roi_px[3] < 1):
            raise ValueError(f"roi_px {self.roi_px}: give (x0, y0, width, height) with x0, y0 >= 0 and a size >= 1")
        return self

    @property
    def observation_shape(self) -> tuple[int, int, int]:
        """(channels, height, width) of the observation: the one name of the policy's image size."""
        return (3, self.observation_height_px, self.observation_width_px)
