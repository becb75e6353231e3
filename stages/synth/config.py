"""Configuration of `drivesim synth`: the procedural world, the camera, the sensors and the drive.

The world (road + scenery + seed) is what `SynthWorld.from_seed` rebuilds; camera, sensors and drive only shape
the recording made in it. Preset: `configs/synth.yaml`.
"""

from __future__ import annotations

from pydantic import Field

from drivesim.pipeline.config import StageConfig


class RoadConfig(StageConfig):
    """The road: two lanes (right-hand traffic) of clothoid/arc/straight segments."""

    length_m: float = Field(400.0, gt=50.0, le=20000.0)
    """Length of the road centreline (m); grown automatically when the drive needs more."""
    lane_width_m: float = Field(3.5, gt=2.0, le=5.0)
    """Width of each of the two lanes (m)."""
    parking_width_m: float = Field(2.2, ge=0.0, le=4.0)
    """Width of the parking strip between the edge line and the curb, on each side (m)."""
    edge_lines: bool = True
    """White lines at the lanes' outer edges. Off: only the dashed centre line is painted, and a lane ends where the
    parking strip's asphalt begins."""
    sidewalk_width_m: float = Field(2.5, gt=0.5, le=6.0)
    """Width of the raised sidewalk behind each curb (m)."""
    curb_height_m: float = Field(0.15, gt=0.0, le=0.4)
    """Height of the curb, i.e. of the sidewalk above the road surface (m)."""
    max_curvature_1pm: float = Field(1.0 / 30.0, gt=0.0, le=0.1)
    """Largest |curvature| of the driven lane centre (1/m); 1/30 is a tight urban bend."""
    straight_length_m: tuple[float, float] = (15.0, 70.0)
    """Range of the length of straight segments (m)."""
    transition_length_m: tuple[float, float] = (12.0, 30.0)
    """Range of the length of clothoid transitions into and out of a bend (m)."""
    arc_length_m: tuple[float, float] = (10.0, 50.0)
    """Range of the length of the constant-curvature part of a bend (m)."""
    max_heading_change_deg: float = Field(100.0, gt=0.0, le=180.0)
    """Largest heading change of one bend (deg); keeps the road from looping onto itself."""


class SceneryConfig(StageConfig):
    """What stands beside the road."""

    building_probability: float = Field(0.75, ge=0.0, le=1.0)
    """Chance that a stretch of roadside is built up rather than open grass with trees."""
    building_setback_m: tuple[float, float] = (1.0, 6.0)
    """Range of the gap between the sidewalk's outer edge and a building front (m)."""
    building_height_m: tuple[float, float] = (6.0, 22.0)
    """Range of building heights (m)."""
    tree_spacing_m: float = Field(14.0, gt=2.0)
    """Mean spacing of trees along each side of the road (m)."""
    parked_car_probability: float = Field(0.3, ge=0.0, le=1.0)
    """Chance that a parking bay (6 m) holds a parked car."""
    view_distance_m: float = Field(400.0, gt=20.0, le=5000.0)
    """Surfaces in 40 m cells wholly farther than this from the camera are not drawn (m); lower it to render faster."""
    ground_margin_m: float = Field(160.0, gt=10.0)
    """How far the textured ground extends beyond the road's bounding box (m)."""


class CameraConfig(StageConfig):
    """The forward camera."""

    width_px: int = Field(960, ge=16, le=4096)
    """Image width (pixels)."""
    height_px: int = Field(600, ge=16, le=4096)
    """Image height (pixels)."""
    hfov_deg: float = Field(80.0, gt=10.0, lt=170.0)
    """Horizontal field of view (deg); square pixels, principal point at the centre."""
    height_m: float = Field(1.6, gt=0.3, le=4.0)
    """Height of the optical centre above the ground (m)."""
    forward_m: float = Field(1.5, ge=-2.0, le=5.0)
    """Position of the camera ahead of the vehicle origin (rear axle, on the ground) (m)."""
    pitch_down_deg: float = Field(3.0, ge=-20.0, le=30.0)
    """Downward pitch of the optical axis (deg)."""
    rate_hz: float = Field(10.0, gt=0.0, le=60.0)
    """Frame rate (Hz)."""


class GpsConfig(StageConfig):
    """NavSatFix receiver: geodetic origin and a correlated (Gauss–Markov) position error plus white noise."""

    rate_hz: float = Field(10.0, gt=0.0, le=100.0)
    """Fix rate (Hz)."""
    origin_lat_deg: float = Field(49.0, ge=-89.0, le=89.0)
    """Latitude of the synth world's ENU origin (deg, WGS84)."""
    origin_lon_deg: float = Field(8.4, ge=-180.0, le=180.0)
    """Longitude of the synth world's ENU origin (deg, WGS84)."""
    origin_alt_m: float = 115.0
    """Ellipsoidal height of the ENU origin (m)."""
    horizontal_error_m: float = Field(0.7, ge=0.0, le=20.0)
    """Stationary standard deviation of the correlated horizontal error, per axis (m)."""
    vertical_error_m: float = Field(1.2, ge=0.0, le=40.0)
    """Stationary standard deviation of the correlated vertical error (m)."""
    correlation_time_s: float = Field(20.0, gt=0.0)
    """Correlation time of the Gauss–Markov error (s)."""
    white_noise_m: float = Field(0.15, ge=0.0, le=10.0)
    """Standard deviation of the per-fix white noise added on top, per axis (m)."""


class ImuConfig(StageConfig):
    """Imu in base_link: gyro and accelerometer with white noise and a slowly wandering bias."""

    rate_hz: float = Field(100.0, gt=0.0, le=1000.0)
    """Sample rate (Hz)."""
    gyro_noise_radps: float = Field(0.003, ge=0.0)
    """White noise of each angular rate sample (rad/s)."""
    gyro_bias_radps: float = Field(0.002, ge=0.0)
    """Standard deviation of the constant part of the gyro bias, per axis (rad/s)."""
    gyro_bias_walk_radps: float = Field(0.0002, ge=0.0)
    """Random walk of the gyro bias after one second (rad/s)."""
    accel_noise_mps2: float = Field(0.05, ge=0.0)
    """White noise of each acceleration sample (m/s^2)."""
    accel_bias_mps2: float = Field(0.05, ge=0.0)
    """Standard deviation of the constant accelerometer bias, per axis (m/s^2)."""


class WheelConfig(StageConfig):
    """Wheel-speed odometry published as TwistStamped (forward speed)."""

    rate_hz: float = Field(50.0, gt=0.0, le=1000.0)
    """Sample rate (Hz)."""
    noise_mps: float = Field(0.03, ge=0.0)
    """White noise of each speed sample (m/s)."""
    scale_error: float = Field(0.01, ge=-0.2, le=0.2)
    """Relative scale error of the wheel speed (tyre radius error), e.g. 0.01 = reads 1 % fast."""


class SensorsConfig(StageConfig):
    """The pose sensors."""

    gps: GpsConfig = GpsConfig()
    """GPS receiver."""
    imu: ImuConfig = ImuConfig()
    """Inertial measurement unit."""
    wheel: WheelConfig = WheelConfig()
    """Wheel odometry."""


class DriveConfig(StageConfig):
    """How the car drives along the right lane centre."""

    duration_s: float = Field(8.0, gt=0.0, le=3600.0)
    """Length of the recording (s)."""
    speed_mps: float = Field(10.0, gt=0.5, le=40.0)
    """Mean speed (m/s)."""
    speed_variation_mps: float = Field(1.5, ge=0.0, le=10.0)
    """Amplitude of the slow speed variation around the mean (m/s)."""
    speed_period_s: float = Field(16.0, gt=1.0)
    """Period of the speed variation (s)."""
    start_m: float = Field(10.0, ge=0.0)
    """Arc length along the lane where the drive starts (m)."""
    start_epoch_s: float = Field(1767225600.0, ge=0.0)
    """Unix time of the first message (s); default 2026-01-01T00:00:00Z."""


class SynthWorldConfig(StageConfig):
    """Everything `SynthWorld.from_seed` needs besides the seed."""

    road: RoadConfig = RoadConfig()
    """The road."""
    scenery: SceneryConfig = SceneryConfig()
    """What stands beside the road."""


class SynthConfig(StageConfig):
    """`drivesim synth`: a procedural road world, a drive through it, and its recording."""

    seed: int = Field(0, ge=0)
    """Seed of the world and of the sensor noise; equal seeds give equal recordings."""
    world: SynthWorldConfig = SynthWorldConfig()
    """The procedural world."""
    camera: CameraConfig = CameraConfig()
    """The forward camera."""
    sensors: SensorsConfig = SensorsConfig()
    """GPS, IMU and wheel odometry."""
    drive: DriveConfig = DriveConfig()
    """The drive."""
