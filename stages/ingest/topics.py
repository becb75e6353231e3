"""Which topic plays which role (camera, GPS, IMU, ...): found by message type, or chosen by the user."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.stages.ingest.config import TopicsConfig
from drivesim.stages.ingest.sources import TopicInfo

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ROLE_TYPES: dict[str, tuple[str, ...]] = {
    "camera": IMAGE_TYPES,
    "camera_info": (CAMERA_INFO_TYPE,),
    "gps": ("sensor_msgs/msg/NavSatFix",),
    "imu": ("sensor_msgs/msg/Imu",),
    "twist": ("geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/TwistWithCovarianceStamped"),
    "odometry": ("nav_msgs/msg/Odometry",),
    "gt_depth": ("sensor_msgs/msg/Image",),
    "gt_pose": ("geometry_msgs/msg/PoseStamped",),
    "lidar": ("sensor_msgs/msg/PointCloud2",),
}
TF_TYPE = "tf2_msgs/msg/TFMessage"
DEFAULT_GT_TOPICS = {"gt_depth": "/ground_truth/depth", "gt_pose": "/ground_truth/pose"}


@dataclass
class TopicChoice:
    """The topic of each role present in the recording, and how the camera was chosen."""

    roles: dict[str, TopicInfo] = field(default_factory=dict)
    tf_static: TopicInfo | None = None
    tf: TopicInfo | None = None
    camera_reason: str = ""


def _short_type(msgtype: str) -> str:
    return msgtype.rsplit("/", 1)[-1]


def describe_topics(topics: dict[str, TopicInfo]) -> str:
    """`/fix NavSatFix, /imu/data Imu, ...` for error messages."""
    return ", ".join(f"{t.name} {_short_type(t.msgtype)}" for t in sorted(topics.values(), key=lambda t: t.name))


def _is_ground_truth_or_depth(name: str) -> bool:
    low = name.lower()
    return low.startswith("/ground_truth") or "depth" in low


def _namespace(topic: str) -> str:
    """`/cam/image_raw` and `/cam/image_raw/compressed` -> `/cam` (where its CameraInfo lives)."""
    if topic.endswith("/compressed"):
        topic = topic[: -len("/compressed")]
    return topic.rsplit("/", 1)[0]


def choose_topics(topics: dict[str, TopicInfo], wanted: TopicsConfig, path: Path) -> TopicChoice:
    """Assign a topic to each role; refuse when there is no camera or a chosen topic is absent or of the wrong type."""
    choice = TopicChoice()
    chosen = wanted.model_dump()
    for role, name in chosen.items():
        if name is None:
            continue
        if name not in topics:
            raise ConfigError(f"--topic {role}={name}: no such topic in {path}; found: {describe_topics(topics)}")
        if topics[name].msgtype not in ROLE_TYPES[role]:
            expected = " or ".join(_short_type(t) for t in ROLE_TYPES[role])
            raise ConfigError(
                f"--topic {role}={name}: it carries {_short_type(topics[name].msgtype)}, expected {expected}"
            )
        choice.roles[role] = topics[name]

    for role, default in DEFAULT_GT_TOPICS.items():
        if role not in choice.roles and default in topics and topics[default].msgtype in ROLE_TYPES[role]:
            choice.roles[role] = topics[default]

    infos = sorted((t for t in topics.values() if t.msgtype == CAMERA_INFO_TYPE), key=lambda t: t.name)
    if "camera" in choice.roles:
        choice.camera_reason = "chosen with --topic camera"
    else:
        used = {t.name for t in choice.roles.values()}
        cameras = sorted(
            (
                t
                for t in topics.values()
                if t.msgtype in IMAGE_TYPES and not _is_ground_truth_or_depth(t.name) and t.name not in used
            ),
            key=lambda t: t.name,
        )
        if not cameras:
            raise InputError(
                f"no camera topic (sensor_msgs/Image or CompressedImage) in the recording; "
                f"found: {describe_topics(topics) or 'no topics'}",
                path,
            )
        with_info = [c for c in cameras if any(_namespace(i.name) == _namespace(c.name) for i in infos)]
        pick = (with_info or cameras)[0]
        choice.roles["camera"] = pick
        if len(cameras) == 1:
            choice.camera_reason = "the only camera topic"
        elif with_info:
            choice.camera_reason = f"first of {len(cameras)} camera topics with a CameraInfo; use --topic camera="
        else:
            choice.camera_reason = f"first of {len(cameras)} camera topics (none has a CameraInfo); use --topic camera="

    camera = choice.roles["camera"]
    if "camera_info" not in choice.roles:
        same_ns = [i for i in infos if _namespace(i.name) == _namespace(camera.name)]
        if same_ns:
            choice.roles["camera_info"] = same_ns[0]
        elif len(infos) == 1:
            choice.roles["camera_info"] = infos[0]

    for role in ("gps", "imu", "twist", "odometry", "lidar"):
        if role in choice.roles:
            continue
        candidates = sorted((t for t in topics.values() if t.msgtype in ROLE_TYPES[role]), key=lambda t: t.name)
        candidates = [t for t in candidates if not _is_ground_truth_or_depth(t.name)]
        if candidates:
            choice.roles[role] = candidates[0]

    tf_static = topics.get("/tf_static")
    if tf_static is not None and tf_static.msgtype == TF_TYPE:
        choice.tf_static = tf_static
    tf = topics.get("/tf")
    if tf is not None and tf.msgtype == TF_TYPE:
        choice.tf = tf
    return choice
