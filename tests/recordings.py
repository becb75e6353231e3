"""Small test recordings written with the real writers: rosbags (ROS1 bag, rosbag2 sqlite3/mcap) and mcap_ros2.

A recording is a list of `Msg(topic, msgtype, t_ns, values)`; `values` are nested dicts with ROS2 field names
(`k`, `d`, ...) that `build_msg` maps onto either typestore (ROS1 names `K`, `D` match case-insensitively).
Shared by the tests and by benchmarks/bench_ingest.py (large recordings); a fixture builder, not part of drivesim's
stages.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

TS_ROS2 = get_typestore(Stores.ROS2_HUMBLE)
TS_ROS1 = get_typestore(Stores.ROS1_NOETIC)
if "tf2_msgs/msg/TFMessage" not in TS_ROS1.types:  # rosbags' noetic store lacks tf2_msgs
    from rosbags.typesys import get_types_from_msg

    TS_ROS1.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
FORMATS = ("ros1", "rosbag2_sqlite3", "rosbag2_mcap", "mcap")

_BASE_DEFAULTS = {"string": "", "bool": False, "float32": 0.0, "float64": 0.0}
_NP_DTYPES = {
    "uint8": np.uint8,
    "int8": np.int8,
    "uint16": np.uint16,
    "int16": np.int16,
    "uint32": np.uint32,
    "int32": np.int32,
    "uint64": np.uint64,
    "int64": np.int64,
    "float32": np.float32,
    "float64": np.float64,
    "byte": np.uint8,
    "char": np.uint8,
}


@dataclass
class Msg:
    """One message to write: topic, ROS2 type name, log time (ns) and field values."""

    topic: str
    msgtype: str
    t_ns: int
    values: dict[str, Any]


def _lookup(values: dict[str, Any], name: str) -> Any:
    if name in values:
        return values[name]
    for key, value in values.items():
        if key.lower() == name.lower():
            return value
    return None


def _build_field(ts: Typestore, spec: tuple[Any, Any], value: Any) -> Any:
    nodetype, detail = spec
    kind = int(nodetype)
    if kind == 1:  # base type
        typ = detail[0]
        if value is None:
            return _BASE_DEFAULTS.get(typ, 0)
        return value
    if kind == 2:  # nested message
        return build_msg(ts, detail, value or {})
    sub, length = detail
    sub_kind, sub_detail = int(sub[0]), sub[1]
    if sub_kind == 1:
        dtype = _NP_DTYPES.get(sub_detail[0])
        if value is None:
            value = np.zeros(length if kind == 3 else 0, dtype=dtype)
        if dtype is not None:
            if isinstance(value, bytes | bytearray):
                return np.frombuffer(bytes(value), dtype=np.uint8).copy()
            return np.asarray(value, dtype=dtype).ravel()
        return list(value)
    return [build_msg(ts, sub_detail, v) for v in (value or [])]


def build_msg(ts: Typestore, msgtype: str, values: dict[str, Any]) -> Any:
    """A typestore message object of `msgtype` with the given field values (zeros elsewhere)."""
    _, fields = ts.fielddefs[msgtype]
    kwargs = {name: _build_field(ts, spec, _lookup(values, name)) for name, spec in fields}
    return ts.types[msgtype](**kwargs)


def to_plain(msg: Any) -> Any:
    """A typestore message as nested dicts/lists/bytes for `mcap_ros2.writer.Writer`."""
    if dataclasses.is_dataclass(msg):
        return {f.name: to_plain(getattr(msg, f.name)) for f in dataclasses.fields(msg) if f.name != "__msgtype__"}
    if isinstance(msg, np.ndarray):
        return msg.tobytes() if msg.dtype == np.uint8 else msg.tolist()
    if isinstance(msg, list):
        return [to_plain(m) for m in msg]
    return msg


def _write_rosbags(
    writer: Any, messages: Iterable[Msg], typestore: Typestore, serialize: Callable[[Any, str], bytes]
) -> None:
    """Write messages through a rosbags writer (ROS1 or rosbag2), one connection per topic."""
    conns: dict[str, Any] = {}
    for m in messages:
        if m.topic not in conns:
            conns[m.topic] = writer.add_connection(m.topic, m.msgtype, typestore=typestore)
        writer.write(conns[m.topic], m.t_ns, serialize(build_msg(typestore, m.msgtype, m.values), m.msgtype))


def write_recording(path: Path, fmt: str, messages: Iterable[Msg], mcap_compression: str = "zstd") -> Path:
    """Write messages (in the order given) as a ROS1 bag, a rosbag2 folder (sqlite3 or mcap) or a plain .mcap file.

    `mcap_compression` ("zstd", "lz4" or "none") applies to plain .mcap files.
    """
    path = Path(path)
    if fmt == "ros1":
        from rosbags.rosbag1 import Writer

        with Writer(path) as writer:
            _write_rosbags(writer, messages, TS_ROS1, TS_ROS1.serialize_ros1)
        return path
    if fmt in ("rosbag2_sqlite3", "rosbag2_mcap"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.SQLITE3 if fmt == "rosbag2_sqlite3" else StoragePlugin.MCAP
        with Writer(path, version=9, storage_plugin=plugin) as writer:
            _write_rosbags(writer, messages, TS_ROS2, TS_ROS2.serialize_cdr)
        return path
    if fmt == "mcap":
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        with open(path, "wb") as f:
            writer = Writer(f, compression=CompressionType[mcap_compression.upper()])
            schemas: dict[str, Any] = {}
            for m in messages:
                if m.msgtype not in schemas:
                    text = TS_ROS2.generate_msgdef(m.msgtype, ros_version=2)[0]
                    schemas[m.msgtype] = writer.register_msgdef(m.msgtype, text)
                plain = to_plain(build_msg(TS_ROS2, m.msgtype, m.values))
                writer.write_message(m.topic, schemas[m.msgtype], plain, log_time=m.t_ns, publish_time=m.t_ns)
            writer.finish()
        return path
    raise ValueError(f"unknown format {fmt!r}; one of {FORMATS}")


def recording_path(folder: Path, fmt: str, name: str = "rec") -> Path:
    """A file or folder name suited to the format."""
    return Path(folder) / {"ros1": f"{name}.bag", "mcap": f"{name}.mcap"}.get(fmt, name)


# ---------------------------------------------------------------- message values


def header(t_ns: int, frame_id: str = "") -> dict[str, Any]:
    """Header values for a stamp in ns."""
    return {"stamp": {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}, "frame_id": frame_id}


def encode_rgb(rgb: np.ndarray, encoding: str) -> tuple[bytes, int]:
    """(data, step) of an RGB uint8 image in a ROS encoding (the inverse of what ingest decodes)."""
    h, w, _ = rgb.shape
    if encoding == "rgb8":
        return rgb.tobytes(), w * 3
    if encoding == "bgr8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).tobytes(), w * 3
    if encoding == "rgba8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA).tobytes(), w * 4
    if encoding == "bgra8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA).tobytes(), w * 4
    if encoding == "mono8":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).tobytes(), w
    if encoding == "mono16":
        gray16 = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype("<u2") * 257
        return gray16.tobytes(), w * 2
    if encoding == "yuv422":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_UYVY).tobytes(), w * 2
    if encoding == "yuv422_yuy2":
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_YUYV).tobytes(), w * 2
    if encoding.startswith("bayer_") and encoding.endswith("8"):
        pattern = encoding[6:10]
        channel = {"r": 0, "g": 1, "b": 2}
        mosaic = np.empty((h, w), np.uint8)
        for dy in (0, 1):
            for dx in (0, 1):
                mosaic[dy::2, dx::2] = rgb[dy::2, dx::2, channel[pattern[2 * dy + dx]]]
        return mosaic.tobytes(), w
    raise ValueError(f"test helper cannot encode {encoding!r}")


def image_values(t_ns: int, rgb: np.ndarray, encoding: str = "rgb8", frame_id: str = "camera_optical") -> dict:
    """sensor_msgs/Image values."""
    data, step = encode_rgb(rgb, encoding)
    h, w, _ = rgb.shape
    return {"header": header(t_ns, frame_id), "height": h, "width": w, "encoding": encoding, "step": step, "data": data}


def compressed_values(t_ns: int, rgb: np.ndarray, fmt: str = "jpeg", frame_id: str = "camera_optical") -> dict:
    """sensor_msgs/CompressedImage values (jpeg quality 90 or png)."""
    ext = ".png" if fmt == "png" else ".jpg"
    params = [cv2.IMWRITE_JPEG_QUALITY, 90] if ext == ".jpg" else []
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    assert ok
    return {"header": header(t_ns, frame_id), "format": fmt, "data": buf.tobytes()}


def camera_info_values(
    t_ns: int, width: int, height: int, K: np.ndarray, D: Iterable[float] = (), model: str = "plumb_bob", frame_id=""
) -> dict:
    """sensor_msgs/CameraInfo values with P = [K | 0]."""
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "header": header(t_ns, frame_id or "camera_optical"),
        "height": height,
        "width": width,
        "distortion_model": model,
        "d": list(D),
        "k": np.asarray(K, float).ravel(),
        "r": np.eye(3).ravel(),
        "p": P.ravel(),
    }


def navsat_values(t_ns: int, lat_deg: float, lon_deg: float, alt_m: float = 100.0, status: int = 0) -> dict:
    """sensor_msgs/NavSatFix values with a 2 m / 4 m diagonal covariance."""
    cov = np.diag([4.0, 4.0, 16.0]).ravel()
    return {
        "header": header(t_ns, "gps"),
        "status": {"status": status, "service": 1},
        "latitude": lat_deg,
        "longitude": lon_deg,
        "altitude": alt_m,
        "position_covariance": cov,
        "position_covariance_type": 2,
    }


def imu_values(t_ns: int, yaw_rate_radps: float = 0.1, frame_id: str = "base_link") -> dict:
    """sensor_msgs/Imu values: a yaw rate, gravity on z, identity orientation."""
    return {
        "header": header(t_ns, frame_id),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "angular_velocity": {"x": 0.0, "y": 0.0, "z": yaw_rate_radps},
        "linear_acceleration": {"x": 0.5, "y": 0.0, "z": 9.81},
    }


def twist_values(t_ns: int, speed_mps: float) -> dict:
    """geometry_msgs/TwistStamped values."""
    return {"header": header(t_ns, "base_link"), "twist": {"linear": {"x": speed_mps}}}


def odometry_values(t_ns: int, x_m: float, speed_mps: float) -> dict:
    """nav_msgs/Odometry values for a vehicle at (x, 0) moving along x."""
    return {
        "header": header(t_ns, "odom"),
        "child_frame_id": "base_link",
        "pose": {"pose": {"position": {"x": x_m}, "orientation": {"w": 1.0}}},
        "twist": {"twist": {"linear": {"x": speed_mps}}},
    }


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def transform_values(t_ns: int, parent: str, child: str, T: np.ndarray) -> dict:
    """geometry_msgs/TransformStamped values for T_parent_child."""
    q = quat_xyzw(T[:3, :3])
    return {
        "header": header(t_ns, parent),
        "child_frame_id": child,
        "transform": {
            "translation": dict(zip("xyz", T[:3, 3].tolist(), strict=True)),
            "rotation": dict(zip("xyzw", q.tolist(), strict=True)),
        },
    }


def tf_static_values(t_ns: int, edges: list[tuple[str, str, np.ndarray]]) -> dict:
    """tf2_msgs/TFMessage values from (parent, child, T_parent_child) edges."""
    return {"transforms": [transform_values(t_ns, p, c, T) for p, c, T in edges]}


def pose_values(t_ns: int, T: np.ndarray) -> dict:
    """geometry_msgs/PoseStamped values from a 4x4 pose."""
    q = quat_xyzw(T[:3, :3])
    return {
        "header": header(t_ns, "world"),
        "pose": {
            "position": dict(zip("xyz", T[:3, 3].tolist(), strict=True)),
            "orientation": dict(zip("xyzw", q.tolist(), strict=True)),
        },
    }


def depth_values(t_ns: int, depth_m: np.ndarray) -> dict:
    """sensor_msgs/Image 32FC1 values."""
    h, w = depth_m.shape
    data = np.ascontiguousarray(depth_m, dtype="<f4").tobytes()
    return {
        "header": header(t_ns, "camera_optical"),
        "height": h,
        "width": w,
        "encoding": "32FC1",
        "step": w * 4,
        "data": data,
    }


def pointcloud_values(t_ns: int, points: np.ndarray, frame_id: str = "lidar") -> dict:
    """sensor_msgs/PointCloud2 values: float32 x, y, z, intensity (points (M, 4)), one row, 16-byte points."""
    fields = [
        {"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate(("x", "y", "z", "intensity"))
    ]
    data = np.ascontiguousarray(points, dtype="<f4").tobytes()
    return {
        "header": header(t_ns, frame_id),
        "height": 1,
        "width": len(points),
        "fields": fields,
        "is_bigendian": False,
        "point_step": 16,
        "row_step": 16 * len(points),
        "data": data,
        "is_dense": False,
    }


# ---------------------------------------------------------------- images and drives


def patch_image(width: int, height: int, colour: tuple[int, int, int] = (200, 40, 90), frame: int = 0) -> np.ndarray:
    """A grey gradient with a solid colour patch in the middle (its colour must survive any encoding)."""
    x = np.linspace(30, 220, width, dtype=np.float32)
    img = np.repeat(np.repeat(x[None, :, None], height, 0), 3, 2).astype(np.uint8)
    img[:, :, 1] = (img[:, :, 1].astype(int) + 3 * frame) % 256
    y0, x0 = height // 4, width // 4
    img[y0 : height - y0, x0 : width - x0] = colour
    return img


def textured_image(width: int, height: int, frame: int, seed: int = 0) -> np.ndarray:
    """A natural-looking texture (smoothed noise + shapes) that moves with `frame`: realistic for jpeg sizes."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (height // 8 + 2, width // 8 + 2, 3), dtype=np.uint8)
    img = cv2.resize(base, (width + 16, height + 16), interpolation=cv2.INTER_CUBIC)
    shift = frame % 16
    img = np.ascontiguousarray(img[shift : shift + height, shift : shift + width])
    noise = rng.integers(-12, 13, img.shape, dtype=np.int16)
    img = np.clip(img.astype(np.int16) + noise, 0, 255).astype(np.uint8)
    cv2.circle(img, (width // 2 + 3 * (frame % 50), height // 2), height // 6, (250, 250, 40), -1)
    return img


DEFAULT_K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 19.5], [0.0, 0.0, 1.0]])
# base_footprint -> base_link (IMU height) -> camera (1.2 m forward, 1.5 m above the ground, looking forward).
T_FOOTPRINT_LINK = np.array([[1.0, 0, 0, 0.0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.4], [0, 0, 0, 1.0]])
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_LINK_CAMERA = np.eye(4)
T_LINK_CAMERA[:3, :3] = R_LINK_OPTICAL
T_LINK_CAMERA[:3, 3] = [1.2, 0.1, 1.1]
START_NS = 1_700_000_000_000_000_000


def drive_messages(
    n_frames: int = 8,
    width: int = 64,
    height: int = 40,
    encoding: str = "rgb8",
    compressed: str | None = None,
    K: np.ndarray | None = None,
    D: Iterable[float] = (),
    distortion_model: str = "plumb_bob",
    with_gps: bool = True,
    with_imu: bool = True,
    with_twist: bool = True,
    with_camera_info: bool = True,
    with_tf_static: bool = True,
    with_ground_truth: bool = False,
    frame_dt_ns: int = 100_000_000,
    image_fn: Any = None,
    stamps_ns: list[int] | None = None,
) -> list[Msg]:
    """A small drive: camera at 10 Hz, GPS 10 Hz, IMU 50 Hz, twist 20 Hz, tf_static; messages in log-time order."""
    K = DEFAULT_K if K is None else K
    image_fn = image_fn or (lambda i: patch_image(width, height, frame=i))
    msgs: list[Msg] = []
    if with_tf_static:
        edges = [("base_footprint", "base_link", T_FOOTPRINT_LINK), ("base_link", "camera_optical", T_LINK_CAMERA)]
        msgs.append(Msg("/tf_static", "tf2_msgs/msg/TFMessage", START_NS, tf_static_values(START_NS, edges)))
    duration_ns = n_frames * frame_dt_ns
    for i in range(n_frames):
        t = START_NS + i * frame_dt_ns + 1
        # header stamps may differ from log times (stamps_ns: to test out-of-order stamps)
        th = START_NS + stamps_ns[i] + 1 if stamps_ns is not None else t
        if compressed:
            values = compressed_values(th, image_fn(i), compressed)
            msgs.append(Msg("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", t, values))
        else:
            msgs.append(Msg("/camera/image_raw", "sensor_msgs/msg/Image", t, image_values(th, image_fn(i), encoding)))
        if with_camera_info:
            msgs.append(
                Msg(
                    "/camera/camera_info",
                    "sensor_msgs/msg/CameraInfo",
                    t,
                    camera_info_values(t, width, height, K, D, distortion_model),
                )
            )
        if with_ground_truth:
            depth = np.full((height, width), 5.0 + i, np.float32)
            depth[: height // 3] = np.inf
            msgs.append(Msg("/ground_truth/depth", "sensor_msgs/msg/Image", t, depth_values(t, depth)))
            T = np.eye(4)
            T[0, 3] = 1.5 * i
            msgs.append(Msg("/ground_truth/pose", "geometry_msgs/msg/PoseStamped", t, pose_values(t, T)))
    if with_gps:
        for i in range(0, duration_ns, 100_000_000):
            t = START_NS + i + 2
            msgs.append(Msg("/gps/fix", "sensor_msgs/msg/NavSatFix", t, navsat_values(t, 49.0 + i * 1e-15, 8.4)))
    if with_imu:
        for i in range(0, duration_ns, 20_000_000):
            t = START_NS + i + 3
            msgs.append(Msg("/imu/data", "sensor_msgs/msg/Imu", t, imu_values(t)))
    if with_twist:
        for i in range(0, duration_ns, 50_000_000):
            t = START_NS + i + 4
            msgs.append(Msg("/vehicle/twist", "geometry_msgs/msg/TwistStamped", t, twist_values(t, 10.0)))
    msgs.sort(key=lambda m: m.t_ns)
    return msgs
