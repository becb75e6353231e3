"""Ingest of ROS recordings (ROS1 bag, rosbag2, plain MCAP) into a trace folder.

One pass over the recording in log-time order: camera frames are decoded, undistorted, resized and appended to
frames.imgs as they arrive; the series accumulate in growable arrays. Before that pass, the small topics that
configure it are read once: /tf_static, the first CameraInfo and the first camera message. The trace's calibration
and sources are written by the TraceWriter (writer.py), which checks them.

Bad input, case by case (issue 22):
- one damaged camera message (empty, short or undecodable payload): skipped and counted, as a camera driver drops
  a frame; more than writer.MAX_SKIPPED_FRAME_FRACTION of them refuses the recording;
- a non-finite GPS / IMU / odometry / twist / pose sample: skipped and counted (series.py);
- everything the whole trace depends on (CameraInfo intrinsics, /tf_static extrinsics, camera stamps, image size,
  the encoding, ground-truth depth that must match every frame): refused with one line, since no frame written
  with it would be right.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.pipeline.progress import progress_bar
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.extrinsics import StaticTfTree
from drivesim.stages.ingest.images import (
    CameraModel,
    CorruptImageError,
    EncodingError,
    FrameProcessor,
    compressed_format_ok,
    decode_compressed,
    decode_depth,
    decode_raw,
    resize_depth_nearest,
    working_size,
)
from drivesim.stages.ingest.output import FrameStore, GrowableArray, NpyStreamWriter
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
from drivesim.stages.ingest.sources import MessageSource, TopicInfo, open_source
from drivesim.stages.ingest.topics import TopicChoice, choose_topics, describe_topics
from drivesim.stages.ingest.writer import Extrinsics, FrameStream, TraceWriter, config_extrinsics

_FIRST_IMAGE_TRIES = 8  # camera messages tried for the recorded image size when the first ones are damaged


def camera_model_from_info(info: Any) -> CameraModel:
    """The camera model a CameraInfo message describes (ROS1 or ROS2 field names)."""
    try:
        K = np.asarray(field_of(info, "k", "K"), dtype=float).reshape(3, 3)
        D = np.asarray(field_of(info, "d", "D"), dtype=float).ravel()
        R = np.asarray(field_of(info, "r", "R"), dtype=float).reshape(3, 3)
        P = np.asarray(field_of(info, "p", "P"), dtype=float).reshape(3, 4)[:, :3]
    except ValueError as e:
        raise EncodingError(f"malformed CameraInfo ({e})") from None
    if not np.all(np.isfinite(np.concatenate([K.ravel(), D, R.ravel(), P.ravel()]))):
        raise EncodingError("CameraInfo has non-finite values in K, D, R or P: the intrinsics are unknown")
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
        # A size other than the first image's is refused, not skipped: it is a reconfigured camera as often as a
        # damaged message, and the CameraInfo intrinsics would not apply to it.
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


@dataclass
class _Camera:
    """The camera as the pre-pass found it: its topic, model, frame processing and optical frame name."""

    topic: TopicInfo
    info_topic: str
    model: CameraModel
    source_size: tuple[int, int]
    processor: FrameProcessor
    decode: _CameraDecoder
    frame_id: str


def _first(source: MessageSource, topic: str) -> Any | None:
    for _, _, msg in source.messages([topic]):
        return msg
    return None


def _first_image(source: MessageSource, camera: TopicInfo, path: Path) -> tuple[Any, tuple[int, int]]:
    """The first camera message that decodes, and its (width, height)."""
    problem = "no readable messages"
    for i, (_, _, msg) in enumerate(source.messages([camera.name])):
        if i >= _FIRST_IMAGE_TRIES:
            break
        if not camera.msgtype.endswith("CompressedImage"):
            return msg, (int(msg.width), int(msg.height))
        try:
            rgb = decode_compressed(msg.data)
        except CorruptImageError as e:
            problem = str(e)
            continue
        return msg, (rgb.shape[1], rgb.shape[0])
    raise InputError(f"camera topic {camera.name}: {problem}", path)


def _choose(source: MessageSource, path: Path, cfg: IngestConfig, trace: TraceWriter) -> TopicChoice:
    """The topic of each role; refuses a recording without a camera or (when required) a pose source."""
    choice = choose_topics(source.topics, cfg.topics, path)
    camera = choice.roles["camera"]
    trace.notes.append(f"camera: {camera.name} ({choice.camera_reason})")
    pose_topics = "gps" in choice.roles or "odometry" in choice.roles
    if cfg.require_pose_source and not pose_topics and choice.tf is None:
        raise InputError(
            f"camera {camera.name} has no pose source: no NavSatFix, Odometry or /tf topic "
            f"(found: {describe_topics(source.topics)}); set require_pose_source=false to rely on visual SfM",
            path,
        )
    if camera.message_count == 0:
        raise InputError(f"camera topic {camera.name} has no messages", path)
    return choice


def _static_tf(source: MessageSource, choice: TopicChoice) -> StaticTfTree:
    tf = StaticTfTree()
    if choice.tf_static is not None:
        for _, _, msg in source.messages([choice.tf_static.name]):
            tf.add_message(msg)
    return tf


def _camera(source: MessageSource, choice: TopicChoice, path: Path, cfg: IngestConfig) -> _Camera:
    """Read the first image and the CameraInfo; check that they agree; set up decoding and undistortion."""
    camera = choice.roles["camera"]
    first_image, (source_w, source_h) = _first_image(source, camera, path)
    info_topic = choice.roles.get("camera_info")
    info = _first(source, info_topic.name) if info_topic is not None else None
    if info_topic is None or info is None:
        raise InputError(
            f"no CameraInfo for camera {camera.name} (needed for the intrinsics K); "
            f"pass --topic camera_info=/... (found: {describe_topics(source.topics)})",
            path,
        )
    try:
        model = camera_model_from_info(info)
    except EncodingError as e:
        raise InputError(f"CameraInfo {info_topic.name}: {e}", path) from None
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
    frame_id = (info.header.frame_id or first_image.header.frame_id or "").lstrip("/")
    return _Camera(camera, info_topic.name, model, (source_w, source_h), processor, decode, frame_id)


def _extrinsics(
    cfg: IngestConfig, tf: StaticTfTree, camera_frame: str, notes: list[str]
) -> tuple[Extrinsics, str | None]:
    """(where the camera sits, the vehicle frame's name in the tf tree or None)."""
    configured = config_extrinsics(cfg)
    if configured is not None:
        return configured, None
    for vehicle_frame in cfg.extrinsics.vehicle_frames:
        T = tf.lookup(vehicle_frame, camera_frame) if camera_frame else None
        if T is None:
            continue
        height_m = float(T[2, 3]) if vehicle_frame == "base_footprint" else cfg.extrinsics.camera_height_m
        return Extrinsics(T, height_m, "tf_static"), vehicle_frame
    notes.append(
        f"no /tf_static path from {'/'.join(cfg.extrinsics.vehicle_frames)} to camera frame {camera_frame!r}: "
        "camera assumed at the vehicle origin looking forward (set extrinsics.T_vehicle_camera to fix)"
    )
    from drivesim.sim.geometry import camera_mount

    height_m = cfg.extrinsics.camera_height_m
    return Extrinsics(camera_mount(0.0, 0.0, height_m or 0.0), height_m, "default"), None


class _Pass:
    """The single pass over the recording: a handler per topic feeding the frame stream, depth, lidar and series."""

    def __init__(
        self, source: MessageSource, choice: TopicChoice, cam: _Camera, tf: StaticTfTree, vehicle_frame: str | None
    ) -> None:
        self.source, self.choice, self.cam, self.tf, self.vehicle_frame = source, choice, cam, tf, vehicle_frame
        self.path = source.path
        self.handlers: dict[str, Any] = {cam.topic.name: self.on_camera}
        self.recorders: dict[str, Any] = {}
        self.camera_messages = 0
        self.last_t = -1
        self.n_frames = cam.topic.message_count
        self.depth: NpyStreamWriter | None = None
        self.depth_times = GrowableArray((), np.int64)
        self.lidar: LidarWriter | None = None
        self.tf_poses: TfPoseRecorder | None = None
        self.frames: FrameStream | None = None
        self.out_dir = Path()
        self.notes: list[str] = []

    def add_recorders(self, vehicle_frames: list[str]) -> None:
        """One recorder per series role present (GPS, IMU, twist / odometry speed, odometry, /tf, ground truth)."""
        roles = self.choice.roles
        if "gps" in roles:
            self._record("gps", GpsRecorder())
        if "imu" in roles:
            self._record("imu", ImuRecorder(self.tf, self.vehicle_frame))
        speed = SpeedRecorder() if "twist" in roles or "odometry" in roles else None
        if "twist" in roles:
            self._record("twist", speed)
        elif speed is not None:
            self.recorders["speed"] = speed
        if "odometry" in roles:
            self._record("odometry", OdometryRecorder(speed if "twist" not in roles else None))
        if "gt_pose" in roles:
            self._record("gt_pose", GroundTruthPoseRecorder())
        if self.choice.tf is not None and "odometry" not in roles:
            self.tf_poses = TfPoseRecorder(vehicle_frames)
            self.handlers[self.choice.tf.name] = self.tf_poses
        if "lidar" in roles:
            self.handlers[roles["lidar"].name] = self.on_lidar

    def _record(self, role: str, recorder: Any) -> None:
        self.handlers[self.choice.roles[role].name] = recorder
        self.recorders[role] = recorder

    def open_depth(self) -> None:
        """gt_depth.npy, one row per camera frame, when the recording has ground-truth depth."""
        topic = self.choice.roles.get("gt_depth")
        if topic is None:
            return
        width, height = self.cam.processor.out_width, self.cam.processor.out_height
        self.depth = NpyStreamWriter(self.out_dir / "gt_depth.npy", (self.n_frames, height, width), np.float32)
        self.handlers[topic.name] = self.on_depth

    def on_camera(self, msg: Any, log_ns: int) -> None:
        """Check the stamp order and queue the frame for decoding."""
        t = stamp_ns(msg, log_ns)
        if t <= self.last_t:
            raise InputError(
                f"camera {self.cam.topic.name}: stamps not strictly increasing at frame {self.camera_messages} "
                f"({self.last_t} ns then {t} ns)",
                self.path,
            )
        self.last_t = t
        self.camera_messages += 1
        assert self.frames is not None
        self.frames.submit(msg, t)

    def on_depth(self, msg: Any, log_ns: int) -> None:
        """Decode one ground-truth depth image at the working resolution."""
        assert self.depth is not None
        if self.depth.rows_written >= self.n_frames:
            topic = self.choice.roles["gt_depth"].name
            raise InputError(f"{topic} has more messages than {self.cam.topic.name}", self.path)
        depth_m = decode_depth(msg.data, msg.encoding, int(msg.height), int(msg.width), int(msg.step))
        size = (self.cam.processor.out_width, self.cam.processor.out_height)
        self.depth.write(np.ascontiguousarray(resize_depth_nearest(depth_m, size), dtype=np.float32))
        self.depth_times.append(stamp_ns(msg, log_ns))

    def on_lidar(self, msg: Any, log_ns: int) -> None:
        """Append one scan in the vehicle frame (the writer is opened at the first scan)."""
        if self.lidar is None:
            frame_id = msg.header.frame_id.lstrip("/")
            vf = self.vehicle_frame
            T = self.tf.lookup(vf, frame_id) if vf and frame_id else None
            if T is None:
                self.notes.append(f"lidar frame {frame_id!r} not in /tf_static: points taken as in the vehicle frame")
            elif not np.all(np.isfinite(T)):
                raise InputError(f"/tf_static transform of lidar frame {frame_id!r} is not finite", self.path)
            self.lidar = LidarWriter(self.out_dir, T)
        self.lidar.add(stamp_ns(msg, log_ns), cloud_points(msg))

    def _work(self, keep: bool) -> Any:
        cam = self.cam

        def work(msg: Any) -> tuple[np.ndarray, np.ndarray | None]:
            rgb = cam.decode(msg)
            return cam.processor.process_keeping_original(rgb) if keep else (cam.processor.process(rgb), None)

        return work

    def run(self, trace: TraceWriter, cfg: IngestConfig) -> np.ndarray:
        """Read every handled message in log-time order; the stamps of the frames written."""
        self.out_dir = trace.out_dir
        self.add_recorders(cfg.extrinsics.vehicle_frames)
        if cfg.ground_truth_depth:
            self.open_depth()
        keep = cfg.image.keep_original
        size = (self.cam.processor.out_width, self.cam.processor.out_height)
        original = self.cam.source_size if keep else None
        store = FrameStore(trace.out_dir, self.n_frames, size, original, storage=trace.frame_storage)
        try:
            with progress_bar(f"ingest {self.cam.topic.name}", total=self.n_frames) as (progress, task):
                self.frames = FrameStream(
                    trace, store, self._work(keep), lambda: progress.advance(task), (CorruptImageError,)
                )
                for topic, log_ns, msg in self.source.messages(list(self.handlers)):
                    self.handlers[topic](msg, log_ns)
                times = self.frames.finish(self.cam.topic.name)
            if self.lidar is not None:
                self.lidar.close()
        except BaseException:
            if self.lidar is not None:
                self.lidar.abort()
            raise
        finally:
            if self.frames is not None:
                self.frames.close()
            store.close()
            if self.depth is not None:
                self.depth.close()
        return times

    def check_counts(self, times: np.ndarray) -> None:
        """Refuse a truncated camera stream and ground-truth depth that does not match the frames one to one."""
        if self.camera_messages != self.n_frames:
            raise InputError(
                f"camera {self.cam.topic.name}: the index announces {self.n_frames} messages but "
                f"{self.camera_messages} could be read (truncated recording?)",
                self.path,
            )
        if self.depth is not None and (
            self.depth.rows_written != len(times) or not np.array_equal(self.depth_times.array(), times)
        ):
            raise InputError(
                f"{self.choice.roles['gt_depth'].name}: {self.depth.rows_written} depth images whose stamps do not "
                f"match the {len(times)} frames of {self.cam.topic.name}",
                self.path,
            )

    def save_series(self, cfg: IngestConfig, trace: TraceWriter) -> None:
        """Write the series files; refuse when /tf was the only pose source and never moved the vehicle."""
        pose_topics = "gps" in self.choice.roles or "odometry" in self.choice.roles
        if self.tf_poses is not None and self.tf_poses.has_poses():
            self.tf_poses.save(self.out_dir, self.tf, self.vehicle_frame)
            assert self.choice.tf is not None
            self.choice.roles["tf"] = self.choice.tf
            trace.skip("tf", self.tf_poses.skipped)
        elif cfg.require_pose_source and not pose_topics:
            raise InputError(
                f"camera {self.cam.topic.name} has no pose source: no NavSatFix or Odometry topic, and /tf never "
                f"moves {' or '.join(cfg.extrinsics.vehicle_frames)} relative to a world frame",
                self.path,
            )
        for role, recorder in self.recorders.items():
            recorder.save(self.out_dir)
            trace.skip(role, recorder.skipped)
        trace.notes.extend(self.notes)
        written = [n for n in ("gps.npz", "odometry.npz") if (self.out_dir / n).is_file()]
        if cfg.require_pose_source and pose_topics and not written:
            raise InputError(
                f"camera {self.cam.topic.name} has no usable pose source: every GPS fix and odometry message has "
                "non-finite values; set require_pose_source=false to rely on visual SfM",
                self.path,
            )


def ingest_ros(path: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    """Read a ROS1 bag / rosbag2 folder / MCAP file (`trace.format`) at `path` into `trace`."""
    source = open_source(path, trace.format)
    try:
        _read(source, path, cfg, trace)
    except (EncodingError, PointCloudError) as e:
        raise InputError(str(e), path) from None
    finally:
        source.close()


def _read(source: MessageSource, path: Path, cfg: IngestConfig, trace: TraceWriter) -> None:
    choice = _choose(source, path, cfg, trace)
    tf = _static_tf(source, choice)
    cam = _camera(source, choice, path, cfg)
    trace.set_camera(cam.topic.name, cam.processor, cam.source_size, cam.model.model if cam.model.distorted else "none")
    extrinsics, vehicle_frame = _extrinsics(cfg, tf, cam.frame_id, trace.notes)
    trace.set_extrinsics(extrinsics)  # checked before the long pass, not after it
    one_pass = _Pass(source, choice, cam, tf, vehicle_frame)
    times = one_pass.run(trace, cfg)
    one_pass.check_counts(times)
    one_pass.save_series(cfg, trace)
    trace.set_times(times, "unix", frame_rows=len(times))
    for role, topic in _sensors(choice).items():
        trace.add_sensor(role, topic.name, topic.msgtype, topic.message_count)


_SENSOR_ORDER = (
    "camera", "camera_info", "gps", "imu", "twist", "odometry", "lidar", "tf", "tf_static", "gt_depth", "gt_pose"
)  # fmt: skip


def _sensors(choice: TopicChoice) -> dict[str, TopicInfo]:
    """{role: topic} in a fixed order, camera first."""
    topics = dict(choice.roles)
    if choice.tf_static is not None:
        topics["tf_static"] = choice.tf_static
    return {role: topics[role] for role in _SENSOR_ORDER if role in topics}
