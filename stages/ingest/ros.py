"""Ingest of ROS recordings (ROS1 bag, rosbag2, plain MCAP) into a trace folder.

One pass over the recording in log-time order: camera frames are decoded, undistorted, resized and appended to
frames.npy as they arrive; the series accumulate in growable arrays. Before that pass, the small topics that
configure it are read once: /tf_static, the first CameraInfo and the first camera message.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.progress import progress_bar
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.extrinsics import StaticTfTree
from drivesim.stages.ingest.images import (
    CameraModel,
    EncodingError,
    FrameProcessor,
    compressed_format_ok,
    decode_compressed,
    decode_depth,
    decode_raw,
    resize_depth_nearest,
    working_size,
)
from drivesim.stages.ingest.output import (
    FrameStore,
    GrowableArray,
    IngestResult,
    NpyStreamWriter,
    OrderedPipeline,
    write_json,
)
from drivesim.stages.ingest.pointcloud import LidarWriter, PointCloudError, cloud_points
from drivesim.stages.ingest.series import (
    GpsRecorder,
    GroundTruthPoseRecorder,
    ImuRecorder,
    OdometryRecorder,
    SpeedRecorder,
    TfPoseRecorder,
    field_of,
    stamp_ns,
)
from drivesim.stages.ingest.sources import MessageSource, open_source
from drivesim.stages.ingest.topics import TopicChoice, choose_topics, describe_topics


def _first(source: MessageSource, topic: str) -> Any | None:
    for _, _, msg in source.messages([topic]):
        return msg
    return None


def camera_model_from_info(info: Any) -> CameraModel:
    """The camera model a CameraInfo message describes (ROS1 or ROS2 field names)."""
    K = np.asarray(field_of(info, "k", "K"), dtype=float).reshape(3, 3)
    D = np.asarray(field_of(info, "d", "D"), dtype=float).ravel()
    R = np.asarray(field_of(info, "r", "R"), dtype=float).reshape(3, 3)
    P = np.asarray(field_of(info, "p", "P"), dtype=float).reshape(3, 4)[:, :3]
    if not np.any(R):
        R = np.eye(3)
    if not np.any(P) or P[0, 0] <= 0:
        P = K.copy()
    model = (info.distortion_model or "").strip().lower()
    if model in ("", "none") or not np.any(D):
        model = "none"
    elif model not in ("plumb_bob", "rational_polynomial", "equidistant", "fisheye"):
        raise EncodingError(f"unsupported distortion model {info.distortion_model!r}")
    if model == "fisheye":
        model = "equidistant"
    return CameraModel(K=K, D=D, model=model, P=P, R=R, width_px=int(info.width), height_px=int(info.height))


class _CameraDecoder:
    """Turns one camera message into RGB at source (or reduced) size."""

    def __init__(self, msgtype: str, reduce_factor: int, size: tuple[int, int]) -> None:
        self.compressed = msgtype.endswith("CompressedImage")
        self.reduce_factor = reduce_factor
        self.width, self.height = size

    def __call__(self, msg: Any) -> np.ndarray:
        if self.compressed:
            if not compressed_format_ok(msg.format):
                raise EncodingError(f"unsupported CompressedImage format {msg.format!r} (jpeg and png are)")
            rgb = decode_compressed(msg.data, self.reduce_factor)
            width, height = rgb.shape[1] * self.reduce_factor, rgb.shape[0] * self.reduce_factor
            if abs(width - self.width) >= self.reduce_factor or abs(height - self.height) >= self.reduce_factor:
                raise EncodingError(f"camera image size changed from {self.width}x{self.height} to {width}x{height}")
            return rgb
        if (int(msg.width), int(msg.height)) != (self.width, self.height):
            raise EncodingError(
                f"camera image size changed from {self.width}x{self.height} to {msg.width}x{msg.height}"
            )
        return decode_raw(
            msg.data, msg.encoding, int(msg.height), int(msg.width), int(msg.step), bool(msg.is_bigendian)
        )


def _source_size(msg: Any, msgtype: str) -> tuple[int, int]:
    if msgtype.endswith("CompressedImage"):
        rgb = decode_compressed(msg.data)
        return rgb.shape[1], rgb.shape[0]
    return int(msg.width), int(msg.height)


def _extrinsics(
    cfg: IngestConfig, tf: StaticTfTree, camera_frame: str, notes: list[str]
) -> tuple[np.ndarray, float | None, str, str | None]:
    """(T_vehicle_camera, camera height m or None, source, vehicle frame name)."""
    if cfg.extrinsics.T_vehicle_camera is not None:
        T = np.asarray(cfg.extrinsics.T_vehicle_camera, dtype=float)
        return T, cfg.extrinsics.camera_height_m, "config", None
    for vehicle_frame in cfg.extrinsics.vehicle_frames:
        T = tf.lookup(vehicle_frame, camera_frame) if camera_frame else None
        if T is None:
            continue
        height_m = cfg.extrinsics.camera_height_m
        if vehicle_frame == "base_footprint":
            height_m = float(T[2, 3])
        return T, height_m, "tf_static", vehicle_frame
    notes.append(
        f"no /tf_static path from {'/'.join(cfg.extrinsics.vehicle_frames)} to camera frame {camera_frame!r}: "
        "camera assumed at the vehicle origin looking forward (set extrinsics.T_vehicle_camera to fix)"
    )
    from drivesim.sim.geometry import camera_mount

    height_m = cfg.extrinsics.camera_height_m
    return camera_mount(0.0, 0.0, height_m or 0.0), height_m, "default", None


def ingest_ros(path: Path, fmt: str, cfg: IngestConfig, out_dir: Path) -> IngestResult:
    """Read a ROS1 bag / rosbag2 folder / MCAP file at `path` into the trace folder `out_dir`."""
    source = open_source(path, fmt)
    try:
        return _ingest(source, path, fmt, cfg, out_dir)
    except (EncodingError, PointCloudError) as e:
        raise InputError(str(e), path) from None
    finally:
        source.close()


def _ingest(source: MessageSource, path: Path, fmt: str, cfg: IngestConfig, out_dir: Path) -> IngestResult:
    notes: list[str] = []
    choice = choose_topics(source.topics, cfg.topics, path)
    camera = choice.roles["camera"]
    notes.append(f"camera: {camera.name} ({choice.camera_reason})")
    pose_topics = "gps" in choice.roles or "odometry" in choice.roles
    if cfg.require_pose_source and not pose_topics and choice.tf is None:
        raise InputError(
            f"camera {camera.name} has no pose source: no NavSatFix, Odometry or /tf topic "
            f"(found: {describe_topics(source.topics)}); set require_pose_source=false to rely on visual SfM",
            path,
        )
    if camera.message_count == 0:
        raise InputError(f"camera topic {camera.name} has no messages", path)

    tf = StaticTfTree()
    if choice.tf_static is not None:
        for _, _, msg in source.messages([choice.tf_static.name]):
            tf.add_message(msg)

    first_image = _first(source, camera.name)
    if first_image is None:
        raise InputError(f"camera topic {camera.name} has no readable messages", path)
    source_w, source_h = _source_size(first_image, camera.msgtype)

    info_topic = choice.roles.get("camera_info")
    info = _first(source, info_topic.name) if info_topic is not None else None
    if info is None:
        raise InputError(
            f"no CameraInfo for camera {camera.name} (needed for the intrinsics K); "
            f"pass --topic camera_info=/... (found: {describe_topics(source.topics)})",
            path,
        )
    model = camera_model_from_info(info)
    if model.K[0, 0] <= 0 or model.K[1, 1] <= 0:
        raise InputError(f"CameraInfo {info_topic.name} has no focal length (uncalibrated camera)", path)
    if (model.width_px, model.height_px) != (source_w, source_h):
        raise InputError(
            f"CameraInfo {info_topic.name} is for {model.width_px}x{model.height_px} images but "
            f"{camera.name} has {source_w}x{source_h}",
            path,
        )

    out_size = working_size(source_w, source_h, cfg.image.width_px, cfg.image.upscale)
    processor = FrameProcessor(model, out_size, cfg.image.interpolation)
    reduce_ok = cfg.image.reduced_jpeg_decode and not cfg.image.keep_original
    reduce = processor.reduce_factor_for(source_w) if reduce_ok else 1
    decode = _CameraDecoder(camera.msgtype, reduce, (source_w, source_h))

    camera_frame = (info.header.frame_id or first_image.header.frame_id or "").lstrip("/")
    T_vehicle_camera, height_m, extrinsics_source, vehicle_frame = _extrinsics(cfg, tf, camera_frame, notes)

    n_frames = camera.message_count
    width, height = out_size
    keep = cfg.image.keep_original
    frames = FrameStore(out_dir, n_frames, out_size, (source_w, source_h) if keep else None)
    frame_times = GrowableArray((), np.int64)

    gt_depth_topic = choice.roles.get("gt_depth")
    depth_writer = None
    depth_times = GrowableArray((), np.int64)
    if gt_depth_topic is not None:
        depth_writer = NpyStreamWriter(out_dir / "gt_depth.npy", (n_frames, height, width), np.float32)

    handlers: dict[str, Any] = {}
    last_t = [-1]

    def on_camera(msg: Any, log_ns: int) -> None:
        t = stamp_ns(msg, log_ns)
        if t <= last_t[0]:
            raise InputError(
                f"camera {camera.name}: stamps not strictly increasing at frame {len(frame_times)} "
                f"({last_t[0]} ns then {t} ns)",
                path,
            )
        last_t[0] = t
        frame_times.append(t)
        pipeline.submit(msg)

    handlers[camera.name] = on_camera

    if depth_writer is not None:

        def on_depth(msg: Any, log_ns: int) -> None:
            if depth_writer.rows_written >= n_frames:
                raise InputError(f"{gt_depth_topic.name} has more messages than {camera.name}", path)
            depth_m = decode_depth(msg.data, msg.encoding, int(msg.height), int(msg.width), int(msg.step))
            depth_writer.write(np.ascontiguousarray(resize_depth_nearest(depth_m, out_size), dtype=np.float32))
            depth_times.append(stamp_ns(msg, log_ns))

        handlers[gt_depth_topic.name] = on_depth

    recorders: list[Any] = []

    def record(role: str, recorder: Any) -> None:
        handlers[choice.roles[role].name] = recorder
        recorders.append(recorder)

    if "gps" in choice.roles:
        record("gps", GpsRecorder())
    if "imu" in choice.roles:
        record("imu", ImuRecorder(tf, vehicle_frame))
    speed = SpeedRecorder() if "twist" in choice.roles or "odometry" in choice.roles else None
    if "twist" in choice.roles:
        record("twist", speed)
    elif speed is not None:
        recorders.append(speed)
    if "odometry" in choice.roles:
        record("odometry", OdometryRecorder(speed if "twist" not in choice.roles else None))
    if "gt_pose" in choice.roles:
        record("gt_pose", GroundTruthPoseRecorder())

    lidar: LidarWriter | None = None
    if "lidar" in choice.roles:

        def on_lidar(msg: Any, log_ns: int) -> None:
            nonlocal lidar
            frame_id = msg.header.frame_id.lstrip("/")
            if lidar is None:
                T = tf.lookup(vehicle_frame, frame_id) if vehicle_frame and frame_id else None
                if T is None:
                    notes.append(f"lidar frame {frame_id!r} not in /tf_static: points taken as in the vehicle frame")
                lidar = LidarWriter(out_dir, T)
            lidar.add(stamp_ns(msg, log_ns), cloud_points(msg))

        handlers[choice.roles["lidar"].name] = on_lidar

    tf_poses: TfPoseRecorder | None = None
    if choice.tf is not None and "odometry" not in choice.roles:
        tf_poses = TfPoseRecorder(cfg.extrinsics.vehicle_frames)
        handlers[choice.tf.name] = tf_poses

    def sink_frame(frame: tuple[np.ndarray, np.ndarray | None]) -> None:
        frames.write(frame)
        progress.advance(task)

    def work(msg: Any) -> tuple[np.ndarray, np.ndarray | None]:
        rgb = decode(msg)
        return processor.process_keeping_original(rgb) if keep else (processor.process(rgb), None)

    pipeline = OrderedPipeline(work, sink_frame)
    try:
        with progress_bar(f"ingest {camera.name}", total=n_frames) as (progress, task):
            for topic, log_ns, msg in source.messages(list(handlers)):
                handlers[topic](msg, log_ns)
            pipeline.finish()
        if lidar is not None:
            lidar.close()
    except BaseException:
        if lidar is not None:
            lidar.abort()
        raise
    finally:
        pipeline.close()
        frames.close()
        if depth_writer is not None:
            depth_writer.close()

    times = frame_times.array()
    if len(times) != n_frames:
        raise InputError(
            f"camera {camera.name}: the index announces {n_frames} messages but {len(times)} could be read "
            "(truncated recording?)",
            path,
        )
    np.save(out_dir / "frame_times_ns.npy", times)
    if depth_writer is not None and (
        depth_writer.rows_written != n_frames or not np.array_equal(depth_times.array(), times)
    ):
        raise InputError(
            f"{gt_depth_topic.name}: {depth_writer.rows_written} depth images whose stamps do not match the "
            f"{n_frames} frames of {camera.name}",
            path,
        )

    if tf_poses is not None and tf_poses.has_poses():
        tf_poses.save(out_dir, tf, vehicle_frame)
        choice.roles["tf"] = choice.tf
    elif cfg.require_pose_source and not pose_topics:
        raise InputError(
            f"camera {camera.name} has no pose source: no NavSatFix or Odometry topic, and /tf never moves "
            f"{' or '.join(cfg.extrinsics.vehicle_frames)} relative to a world frame",
            path,
        )
    for recorder in recorders:
        recorder.save(out_dir)

    write_json(
        out_dir / "calibration.json",
        {
            "width_px": width,
            "height_px": height,
            "K": processor.K_out,
            "K_source": processor.K_source,
            "source_width_px": source_w,
            "source_height_px": source_h,
            "distortion_model": model.model if model.distorted else "none",
            "T_vehicle_camera": T_vehicle_camera,
            "camera_height_m": height_m,
            "extrinsics_source": extrinsics_source,
            "time_base": "unix",
        },
    )
    sensors = _sensors(choice)
    write_json(
        out_dir / "sources.json",
        {"recording": str(path), "format": fmt, "camera_topic": camera.name, "sensors": sensors},
    )
    duration_s = float(times[-1] - times[0]) / 1e9 if len(times) > 1 else 0.0
    summary = {
        "frame_count": int(n_frames),
        "duration_s": round(duration_s, 3),
        "width_px": width,
        "height_px": height,
        "sensors": sensors,
    }
    return IngestResult(summary=summary, notes=notes)


_SENSOR_ORDER = (
    "camera", "camera_info", "gps", "imu", "twist", "odometry", "lidar", "tf", "tf_static", "gt_depth", "gt_pose"
)  # fmt: skip


def _sensors(choice: TopicChoice) -> dict[str, dict[str, Any]]:
    """{role: {topic, type, message_count}} in a fixed order, camera first."""
    topics = dict(choice.roles)
    if choice.tf_static is not None:
        topics["tf_static"] = choice.tf_static
    return {
        role: {"topic": topics[role].name, "type": topics[role].msgtype, "message_count": topics[role].message_count}
        for role in _SENSOR_ORDER
        if role in topics
    }
