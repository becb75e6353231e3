"""The synthetic drive as a ROS2 MCAP recording (CDR, standard message types) that `drivesim ingest` reads.

Topics (a contract with ingest; frames: base_footprint -> base_link (z = 0) -> camera_optical):
    /camera/image_raw     sensor_msgs/msg/Image        rgb8, frame camera_optical
    /camera/camera_info   sensor_msgs/msg/CameraInfo   plumb_bob, zero distortion, one per image, same stamp
    /gps/fix              sensor_msgs/msg/NavSatFix    WGS84, ENU covariance (diagonal known), frame base_link
    /imu/data             sensor_msgs/msg/Imu          frame base_link; no orientation (covariance[0] = -1)
    /vehicle/twist        geometry_msgs/msg/TwistStamped  wheel speed in linear.x, frame base_link
    /tf_static            tf2_msgs/msg/TFMessage       once, at the first stamp
    /ground_truth/depth   sensor_msgs/msg/Image        32FC1 metres along the optical axis, +inf = sky; camera stamp
    /ground_truth/pose    geometry_msgs/msg/PoseStamped  T_world_vehicle in the synth world's ENU frame ("world")
Log time = header stamp for every message, and messages are written in log-time order.
"""

from __future__ import annotations

from typing import Any, BinaryIO

import numpy as np
from mcap.records import Schema
from mcap_ros2.writer import Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

TOPIC_TYPES = {
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/gps/fix": "sensor_msgs/msg/NavSatFix",
    "/imu/data": "sensor_msgs/msg/Imu",
    "/vehicle/twist": "geometry_msgs/msg/TwistStamped",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/ground_truth/depth": "sensor_msgs/msg/Image",
    "/ground_truth/pose": "geometry_msgs/msg/PoseStamped",
}
CAMERA_FRAME = "camera_optical"
VEHICLE_FRAME = "base_link"
FOOTPRINT_FRAME = "base_footprint"
WORLD_FRAME = "world"
_CHUNK_BYTES = 4 << 20


def msgdef(datatype: str) -> str:
    """The ROS2 .msg definition text of `datatype` with its dependencies (the MCAP ros2msg schema encoding)."""
    return get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(datatype, ros_version=2)[0]


def stamp(t_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time of a Unix time in nanoseconds."""
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def header(t_ns: int, frame_id: str) -> dict[str, Any]:
    """std_msgs/Header."""
    return {"stamp": stamp(t_ns), "frame_id": frame_id}


def pose_msg(T: np.ndarray) -> tuple[dict[str, float], dict[str, float]]:
    """(translation/position, rotation quaternion) dicts of a 4x4 transform."""
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])}, {"x": x, "y": y, "z": z, "w": w}


def image_msg(rgb: np.ndarray, t_ns: int) -> dict[str, Any]:
    """sensor_msgs/Image rgb8 of an (H, W, 3) uint8 frame."""
    h, w = rgb.shape[:2]
    return {
        "header": header(t_ns, CAMERA_FRAME),
        "height": h,
        "width": w,
        "encoding": "rgb8",
        "is_bigendian": 0,
        "step": 3 * w,
        "data": np.ascontiguousarray(rgb, np.uint8).tobytes(),
    }


def depth_msg(depth_m: np.ndarray, t_ns: int) -> dict[str, Any]:
    """sensor_msgs/Image 32FC1 (little-endian float32 metres, +inf where nothing)."""
    h, w = depth_m.shape
    return {
        "header": header(t_ns, CAMERA_FRAME),
        "height": h,
        "width": w,
        "encoding": "32FC1",
        "is_bigendian": 0,
        "step": 4 * w,
        "data": np.ascontiguousarray(depth_m, "<f4").tobytes(),
    }


def camera_info_msg(K: np.ndarray, width_px: int, height_px: int, t_ns: int) -> dict[str, Any]:
    """sensor_msgs/CameraInfo: plumb_bob with zero distortion (the images are ideal pinhole)."""
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "header": header(t_ns, CAMERA_FRAME),
        "height": height_px,
        "width": width_px,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [float(v) for v in np.asarray(K).ravel()],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [float(v) for v in P.ravel()],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def navsat_msg(lat_deg: float, lon_deg: float, alt_m: float, covariance_m2: np.ndarray, t_ns: int) -> dict[str, Any]:
    """sensor_msgs/NavSatFix with a GPS fix and a known diagonal ENU covariance."""
    return {
        "header": header(t_ns, VEHICLE_FRAME),
        "status": {"status": 0, "service": 1},
        "latitude": float(lat_deg),
        "longitude": float(lon_deg),
        "altitude": float(alt_m),
        "position_covariance": [float(v) for v in np.asarray(covariance_m2).ravel()],
        "position_covariance_type": 2,
    }


def imu_msg(
    angular_velocity_radps: np.ndarray,
    linear_acceleration_mps2: np.ndarray,
    gyro_var: float,
    accel_var: float,
    t_ns: int,
) -> dict[str, Any]:
    """sensor_msgs/Imu without orientation (orientation_covariance[0] = -1, the ROS convention)."""
    w, a = angular_velocity_radps, linear_acceleration_mps2
    return {
        "header": header(t_ns, VEHICLE_FRAME),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": {"x": float(w[0]), "y": float(w[1]), "z": float(w[2])},
        "angular_velocity_covariance": [gyro_var, 0, 0, 0, gyro_var, 0, 0, 0, gyro_var],
        "linear_acceleration": {"x": float(a[0]), "y": float(a[1]), "z": float(a[2])},
        "linear_acceleration_covariance": [accel_var, 0, 0, 0, accel_var, 0, 0, 0, accel_var],
    }


def twist_msg(speed_mps: float, t_ns: int) -> dict[str, Any]:
    """geometry_msgs/TwistStamped with the forward wheel speed."""
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": header(t_ns, VEHICLE_FRAME),
        "twist": {"linear": {"x": float(speed_mps), "y": 0.0, "z": 0.0}, "angular": zero},
    }


def tf_static_msg(T_vehicle_camera: np.ndarray, t_ns: int) -> dict[str, Any]:
    """tf2_msgs/TFMessage: base_footprint -> base_link (identity, z = 0) and base_link -> camera_optical."""
    transforms = []
    for parent, child, T in (
        (FOOTPRINT_FRAME, VEHICLE_FRAME, np.eye(4)),
        (VEHICLE_FRAME, CAMERA_FRAME, T_vehicle_camera),
    ):
        translation, rotation = pose_msg(T)
        transforms.append(
            {
                "header": header(t_ns, parent),
                "child_frame_id": child,
                "transform": {"translation": translation, "rotation": rotation},
            }
        )
    return {"transforms": transforms}


def pose_stamped_msg(T_world_vehicle: np.ndarray, t_ns: int) -> dict[str, Any]:
    """geometry_msgs/PoseStamped of the vehicle in the synth world's ENU frame."""
    position, orientation = pose_msg(T_world_vehicle)
    return {"header": header(t_ns, WORLD_FRAME), "pose": {"position": position, "orientation": orientation}}


class RecordingWriter:
    """Writes ROS2 messages to an MCAP stream, registering each topic's schema on first use.

    :param stream: a binary file opened for writing.
    """

    def __init__(self, stream: BinaryIO) -> None:
        self._writer = Writer(stream, chunk_size=_CHUNK_BYTES)
        self._schemas: dict[str, Schema] = {}
        self.counts: dict[str, int] = {}
        self._last_ns = -1

    def write(self, topic: str, message: dict[str, Any], t_ns: int) -> None:
        """Write `message` on `topic` with log time `t_ns` (non-decreasing across calls)."""
        if t_ns < self._last_ns:
            raise ValueError(f"{topic}: log time {t_ns} before the previous message ({self._last_ns})")
        self._last_ns = t_ns
        datatype = TOPIC_TYPES[topic]
        if datatype not in self._schemas:
            self._schemas[datatype] = self._writer.register_msgdef(datatype, msgdef(datatype))
        sequence = self.counts.get(topic, 0)
        self._writer.write_message(
            topic, self._schemas[datatype], message, log_time=t_ns, publish_time=t_ns, sequence=sequence
        )
        self.counts[topic] = sequence + 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (string key/values)."""
        self._writer.add_metadata(name, data)

    def finish(self) -> None:
        """Write the summary section; the stream is then a complete MCAP file."""
        self._writer.finish()
