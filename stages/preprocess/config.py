"""The `drivesim preprocess` config: which frames, pose fusion and depth estimation (preset configs/preprocess.yaml)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivesim.pipeline.config import StageConfig

PoseSource = Literal["auto", "gps_imu", "odometry", "given", "sfm", "ground_truth"]


class PoseConfig(StageConfig):
    """How per-frame poses are estimated."""

    source: PoseSource = "auto"
    """Pose source. auto: given poses > GPS (+IMU, +speed) > odometry > error. ground_truth (synthetic drives) and
    sfm (camera-only, slow) are used only when asked for."""
    gps_max_std_m: float = Field(10.0, gt=0)
    """Fixes whose horizontal position std exceeds this (m) are dropped before fusion."""
    gps_min_std_m: float = Field(0.02, gt=0)
    """Floor on a fix's position std (m), so an over-confident receiver cannot pin the track."""
    gps_default_std_m: float = Field(3.0, gt=0)
    """Position std (m) assumed for fixes whose covariance is unknown (covariance_type 0)."""
    gps_gate_chi2: float = Field(13.8, gt=0)
    """Mahalanobis gate for fixes (chi-square, 2 dof; 13.8 = 99.9 %); farther fixes are outliers."""
    gps_gate_reset_s: float = Field(5.0, gt=0)
    """When every fix has been gated out for this long (s), the filter re-accepts fixes (it, not the GPS, drifted)."""
    accel_std_mps2: float = Field(1.0, gt=0)
    """Process noise: std of unmodelled longitudinal acceleration (m/s^2 per sqrt(Hz))."""
    yaw_accel_std_radps2: float = Field(0.5, gt=0)
    """Process noise: std of unmodelled yaw acceleration (rad/s^2 per sqrt(Hz))."""
    position_walk_m_per_sqrt_s: float = Field(0.05, ge=0)
    """Process noise: position random walk for what CTRV does not model (slip, bumps) (m/sqrt(s))."""
    gyro_bias_init_std_radps: float = Field(0.01, ge=0)
    """Prior std of the gyro's yaw-rate bias (rad/s); the filter estimates the bias."""
    gyro_bias_walk_radps_per_sqrt_s: float = Field(1e-4, ge=0)
    """Random walk of the gyro bias (rad/s/sqrt(s))."""
    imu_yaw_rate_std_radps: float = Field(0.01, gt=0)
    """Noise of one averaged IMU yaw-rate measurement (rad/s), i.e. one update at imu_rate_hz."""
    odometry_yaw_rate_std_radps: float = Field(0.05, gt=0)
    """Noise of odometry yaw rate (rad/s), used only without an IMU (wheel yaw rates slip)."""
    speed_std_mps: float = Field(0.1, gt=0)
    """Noise of one averaged speed measurement (m/s)."""
    imu_rate_hz: float = Field(25.0, gt=0)
    """IMU and speed samples are averaged into bins at this rate before fusion (Hz): a 1-hour drive at 100 Hz
    runs in seconds, and averaging loses little the CTRV model can use at 25 Hz."""
    smoothing: bool = True
    """Run the RTS smoother after the filter (off: the causal filter estimate)."""
    use_imu_tilt: bool = True
    """Roll and pitch of T_world_vehicle from the IMU's orientation where it gives one (else level); the heading
    always comes from the fusion."""
    use_altitude: bool = True
    """z from the smoothed GPS altitude (else 0)."""
    altitude_smoothing_s: float = Field(2.0, ge=0)
    """Gaussian smoothing of the altitude over time (s, sigma)."""
    curvature_min_speed_mps: float = Field(1.0, gt=0)
    """Speed v0 (m/s) of the curvature fit's prior kappa = 0 (yaw_rate = kappa * speed), so stops take the road's
    curvature from their neighbours and crawls stay bounded."""
    curvature_smoothing_m: float = Field(2.0, ge=0)
    """Gaussian smoothing of the curvature along the arc length (m, sigma)."""
    sfm_scale_m: float | None = Field(None, gt=0)
    """Camera-only SfM: the metric length of the camera path over the sequence (m), when there is no speed series."""
    sfm_image_width_px: int = Field(640, ge=64)
    """Camera-only SfM: frames are resized to at most this width (px) before feature extraction."""


class MvsConfig(StageConfig):
    """Plane-sweep stereo settings (method `mvs`)."""

    neighbour_offsets: list[int] = Field(default_factory=lambda: [-3, -1, 1, 3])
    """Frames matched against each frame, as index offsets (0 not allowed); at the ends of the drive an offset past
    the end takes the last frame on that side."""
    num_hypotheses: int = Field(48, ge=4, le=512)
    """Fronto-parallel depth planes swept, spaced evenly in inverse depth between min_depth_m and max_depth_m."""
    min_depth_m: float = Field(3.0, gt=0.0)
    """Nearest depth swept (m); the planes are even in inverse depth. Road nearer than this keeps the ground plane as
    its hypothesis."""
    patch_size_px: int = Field(13, ge=3, le=31)
    """Side of the square window of the ZNCC matching cost, in matching-resolution pixels (odd)."""
    matching_width_px: int = Field(448, ge=32)
    """Width of the images the sweep runs on (matching resolution); frames wider than this are downscaled."""
    aggregation_radius_px: int = Field(0, ge=0, le=15)
    """Radius (matching pixels) of the guided filter that smooths each hypothesis's matching cost, guided by the
    reference image so depth edges stay sharp; 0 disables."""
    aggregation_eps: float = Field(1e-3, gt=0.0)
    """Guided filter regularization (grey variance, grey in [0, 1]): edges weaker than about sqrt(eps) are smoothed
    across."""
    best_k: int = Field(2, ge=1)
    """The cost of a hypothesis is the mean of the best k neighbours' costs (robust to occlusion at the borders)."""
    visible_best_k: bool = False
    """A pixel that fewer than best_k neighbours see (the outer side of a turn) takes the mean over those that do,
    instead of counting the others as mismatches (which leaves it to the fill heuristics)."""
    min_zncc: float = Field(0.7, ge=-1.0, le=1.0)
    """Stereo is trusted only where the best aggregated ZNCC score is at least this."""
    min_distinctness: float = Field(0.02, ge=0.0)
    """Stereo is trusted only where the second-best cost minimum (away from the best) is this much worse."""
    min_parallax_px: float = Field(0.25, ge=0.0)
    """Stereo is trusted only where a 25 % depth change moves the pixel at least this far (matching pixels) in the
    widest-baseline neighbour."""
    plane_margin: float = Field(0.03, ge=0.0)
    """The ground plane is kept wherever its ZNCC cost is within this margin of the best swept plane."""
    plane_prior_margin: float = Field(0.0, ge=0.0)
    """A filled pixel below the horizon takes the ground plane unless its own depth's cost beats the plane's by more
    than this (ZNCC cost (1 - ZNCC) / 2); 0 disables."""
    fill_sigma_px: float = Field(3.0, ge=0.0)
    """Sigma (matching pixels) of the Gaussian fill of pixels with neither trusted stereo nor an agreeing plane, from
    the trusted inverse depth around them; 0 disables."""
    sky_max_std: float = Field(0.012, ge=0.0)
    """Sky: textureless pixels (grey window deviation below this, grey in [0, 1]) above the horizon connected to the
    image top; they get max_depth_m."""
    temporal_window: int = Field(0, ge=0, le=5)
    """Each frame's depth becomes the per-pixel median (inverse depth) of its own and its neighbours' estimates
    warped into it, this many frames on each side; 0 keeps every frame's own estimate."""
    upsample: Literal["joint_bilateral", "bilinear"] = "joint_bilateral"
    """How the matching-resolution depth returns to the working resolution: joint_bilateral follows colour edges."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Torch device of the sweep; auto uses CUDA when available."""

    @model_validator(mode="after")
    def _check(self) -> MvsConfig:
        if not self.neighbour_offsets or 0 in self.neighbour_offsets:
            raise ValueError("neighbour_offsets must be a non-empty list of non-zero frame offsets")
        if self.patch_size_px % 2 == 0:
            raise ValueError("patch_size_px must be odd")
        return self


class LidarConfig(StageConfig):
    """Point-cloud projection settings (method `lidar`)."""

    fill_radius_px: int = Field(4, ge=0, le=64)
    """Holes between projected points are filled from the nearest point up to this many pixels away."""
    fallback: Literal["plane", "far"] = "plane"
    """What pixels with no point nearby get: the ground-plane depth, or max_depth_m."""


class StereoConfig(StageConfig):
    """Semi-global block matching on a rectified stereo pair (method `stereo`)."""

    min_depth_m: float = Field(2.0, gt=0.0)
    """Nearest depth matched (m): sets the disparity range fx * baseline / min_depth_m."""
    block_size_px: int = Field(5, ge=1, le=21)
    """Side of SGBM's matching block (px at the working resolution, odd)."""
    uniqueness_ratio: int = Field(10, ge=0, le=100)
    """A match must beat the second best by this many percent of its cost, else the pixel is left unmatched."""
    speckle_window_px: int = Field(100, ge=0)
    """Connected disparity blobs smaller than this (px) are discarded as speckles; 0 disables the filter."""

    @model_validator(mode="after")
    def _check(self) -> StereoConfig:
        if self.block_size_px % 2 == 0:
            raise ValueError("stereo.block_size_px must be odd")
        return self


class DepthConfig(StageConfig):
    """Per-frame depth estimation."""

    method: Literal["auto", "plane", "mvs", "stereo", "lidar"] = "auto"
    """auto (lidar > stereo > mvs, as the recording allows; printed), plane (flat ground, fast), mvs (multi-view stereo,
    camera only), stereo (second camera), lidar (point cloud)."""
    max_depth_m: float = Field(80.0, gt=0.0)
    """Farthest depth (m): sky, rays above the horizon and anything without an estimate get this value."""
    mvs: MvsConfig = Field(default_factory=MvsConfig)
    """Multi-view stereo settings."""
    lidar: LidarConfig = Field(default_factory=LidarConfig)
    """Point-cloud settings."""
    stereo: StereoConfig = Field(default_factory=StereoConfig)
    """Stereo-pair settings."""

    @model_validator(mode="after")
    def _check(self) -> DepthConfig:
        if self.mvs.min_depth_m >= self.max_depth_m:
            raise ValueError("mvs.min_depth_m must be below max_depth_m")
        return self


class FrameSelection(StageConfig):
    """Which frames of the trace are preprocessed (and so become the world): trace indices start:stop:step."""

    start: int = Field(0, ge=0)
    """First trace frame used (index)."""
    stop: int | None = Field(None, ge=1)
    """One past the last trace frame used (index); null = to the end of the trace."""
    step: int = Field(1, ge=1)
    """Use every step-th frame (2 halves the frame rate, the depth work and the world's size)."""


class PreviewConfig(StageConfig):
    """The depth preview image written for people (depth_preview.png)."""

    frame_count: int = Field(4, ge=1, le=12)
    """How many frames, evenly spaced over the drive, the preview shows."""


class PreprocessConfig(StageConfig):
    """Poses and per-frame depth from the trace."""

    frames: FrameSelection = Field(default_factory=FrameSelection)
    """Which trace frames to use."""
    poses: PoseConfig = Field(default_factory=PoseConfig)
    """Pose fusion (GPS + IMU + speed, odometry, or visual SfM)."""
    depth: DepthConfig = Field(default_factory=DepthConfig)
    """Per-frame depth estimation."""
    preview: PreviewConfig = Field(default_factory=PreviewConfig)
    """The depth preview image."""
    backend: Literal["local", "ray"] = Field("local", exclude=True)
    """local: depth in this process; ray: mvs depth split over a Ray cluster's workers (other methods run here).
    Not part of the artifact's identity (the same depth)."""
    address: str | None = Field(None, exclude=True)
    """With backend ray: "auto" (`ray start` on this machine) or the head's host:port; null = start Ray here. Not
    part of the artifact's identity."""

    @model_validator(mode="after")
    def _check(self) -> PreprocessConfig:
        if self.frames.stop is not None and self.frames.stop <= self.frames.start:
            raise ValueError("frames.stop must be after frames.start")
        return self
