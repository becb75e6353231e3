"""One driving episode as an MCAP file that Foxglove opens: the policy's camera, both cars, the road, plots, the end.

An `EpisodeCapture` collects what each step showed (filled by the eval rollout or `drivesim sim render`);
`write_episode_mcap` writes it with Foxglove's well-known protobuf schemas (`foxglove-schemas-protobuf`, each schema
stored as its `FileDescriptorSet` by `mcap-protobuf-support`'s helper) so Foxglove, `mcap` and any protobuf reader
decode it without drivesim. Every message of step k carries the same timestamp, the step's sim time
`t_ns = round(t_s * 1e9)` (step 0 = the reset at t = 0), as its log time, publish time and header stamp.

Topics (frames: `world` = the world's local ENU, `ego` / `other` = vehicle frames x forward, y left, z up, centred on
the footprint; `camera` = the optical frame, x right, y down, z forward, when the world has a camera.json):

    /camera/image      foxglove.CompressedImage  every step   what the policy saw (the observation, JPEG), frame camera
    /tf                foxglove.FrameTransform   every step   world->ego, world->other (when there is one), ego->camera
    /scene/vehicles    foxglove.SceneUpdate      every step   entities "ego", "other": a box (length x width x
                                                              VEHICLE_HEIGHT_M) and the footprint polygon the
                                                              clearance is computed from (LINE_LOOP on the ground);
                                                              "clearance": the shortest segment between the footprints
                                                              (below CLEARANCE_LINE_M)
    /scene/road        foxglove.SceneUpdate      step 0       the reference path (the lane centre), the lane bounds
                                                              (± lane_width_m / 2 of world.json) and the off-lane
                                                              limits (± Z_lat), over the stretch the episode drove
    /ego/step          JSON (schema drivesim.EpisodeStep) every step   plottable: the action of the step that ended
                                                              here (0 at the reset), steering curvature, q_lat, q_rot,
                                                              speed, clearance (null when no other car), each reward
                                                              term and their total, each termination flag, done
    /log               foxglove.Log              last step    how the episode ended: ERROR for an intervention
                                                              (collision, off lane, over-rotation), else INFO

The per-step plot message is JSON with a small hand-written JSON schema: Foxglove has no well-known schema for a
set of named scalars, and its Plot panel reads any numeric or boolean field of a JSON message.
"""

from __future__ import annotations

import functools
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation
from shapely import Polygon, shortest_line

VEHICLE_HEIGHT_M = 1.5
"""Height of the vehicle boxes (drawing only: the simulator's vehicles are footprints on the ground)."""
ROAD_MARGIN_M = 30.0
"""Road drawn beyond the stretch the episode drove, at each end [m]."""
CLEARANCE_LINE_M = 3.0
"""The shortest segment between the footprints is drawn while the clearance is below this [m] (shapely finds it in
0.3 ms, as long as the rest of the step's messages: only where it matters)."""
JPEG_QUALITY = 95
"""JPEG at quality 95 without chroma subsampling (mean error about 2 of 255 on a demo observation): 0.2 ms a frame,
where PNG's exact pixels took 1.4 ms (a fifth of a demo world's step) and twice the bytes."""
_JPEG_PARAMS = [
    cv2.IMWRITE_JPEG_QUALITY,
    JPEG_QUALITY,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
]
INTERVENTIONS = ("collision", "off_lane", "over_rotation")
STEP_SCHEMA_NAME = "drivesim.EpisodeStep"
_NUMBER = {"type": ["number", "null"]}
STEP_SCHEMA = {
    "title": STEP_SCHEMA_NAME,
    "description": "One step of a drivesim episode: the action of the step that ended here, state, rewards, end.",
    "type": "object",
    "properties": {
        "step": {"type": "integer"},
        "t_s": {"type": "number"},
        "action": _NUMBER,
        "steering_curvature_1pm": _NUMBER,
        "q_lat_m": _NUMBER,
        "q_rot_rad": _NUMBER,
        "speed_mps": _NUMBER,
        "clearance_m": _NUMBER,
        "other_rel_x_m": _NUMBER,
        "other_rel_y_m": _NUMBER,
        "reward": {"type": "object", "additionalProperties": _NUMBER},
        "termination": {"type": "object", "additionalProperties": {"type": "boolean"}},
        "done": {"type": "boolean"},
    },
}
_COLORS = {
    "ego": (0.16, 0.47, 0.85, 0.6),
    "other": (0.90, 0.45, 0.10, 0.6),
    "clearance": (0.9, 0.1, 0.1, 1.0),
    "path": (0.85, 0.85, 0.85, 1.0),
    "lane": (1.0, 1.0, 1.0, 0.9),
    "limit": (0.95, 0.25, 0.25, 0.8),
}


@dataclass
class StepSample:
    """What one step showed.

    :param image_rgb: (h, w, 3) uint8, the policy's observation.
    :param state: the env's `info["state"]` (metres, radians, seconds; see the env docstrings).
    :param action: the normalized steering action of the step that ended here (0 at the reset).
    :param rewards: the weighted reward terms of that step by name ({} at the reset).
    :param termination: the termination flags after that step ({} at the reset).
    """

    image_rgb: np.ndarray
    state: dict[str, float]
    action: float
    rewards: dict[str, float]
    termination: dict[str, bool]


@dataclass
class EpisodeCapture:
    """The steps of one episode, filled with `add` after the reset and after each step.

    :param seed: the reset seed. :param task: the task name. :param episode: `info["episode"]` of the reset
    (vehicle sizes `ego_length_m`, `ego_width_m`, `other_length_m`, `other_width_m`).
    """

    seed: int
    task: str
    episode: dict[str, Any] = field(default_factory=dict)
    steps: list[StepSample] = field(default_factory=list)
    success: bool = False

    def add(self, obs: np.ndarray, info: dict[str, Any], action: float) -> None:
        """Keep one step: the observation ((3, h, w) or (h, w, 3) uint8), its info, the action that led to it."""
        if not self.steps and "episode" in info:
            self.episode = dict(info["episode"])
        image = np.asarray(obs)
        if image.ndim == 3 and image.shape[0] in (1, 3) and image.shape[-1] not in (1, 3):
            image = image.transpose(1, 2, 0)
        self.steps.append(
            StepSample(
                np.array(image, dtype=np.uint8, copy=True),
                dict(info.get("state", {})),
                float(action),
                {k: float(v) for k, v in info.get("rewards", {}).items()},
                {k: bool(v) for k, v in info.get("termination", {}).items()},
            )
        )
        self.success = bool(info.get("success", False))

    @property
    def causes(self) -> list[str]:
        """The interventions the episode ended with (empty for a success or a time limit)."""
        last = self.steps[-1].termination if self.steps else {}
        return [k for k in INTERVENTIONS if last.get(k)]

    @property
    def outcome(self) -> str:
        """ "collision", "off_lane", ... (joined by "+"), "success", or the other flag that ended it."""
        if self.causes:
            return "+".join(self.causes)
        if self.success:
            return "success"
        last = self.steps[-1].termination if self.steps else {}
        return next((k for k, v in last.items() if v), "unfinished")


@dataclass
class Road:
    """The recorded path (the lane centre) and the widths to draw around it.

    :param x_m: (N,) lane centre, world frame. :param y_m: (N,). :param arc_length_m: (N,) distance along it.
    :param lane_half_width_m: half the lane width (world.json `lane_width_m`), None when unknown.
    :param limit_m: Z_lat, the off-lane limit, None when unknown.
    :param T_vehicle_camera: (4, 4) the camera in the vehicle frame, None when unknown.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    arc_length_m: np.ndarray
    lane_half_width_m: float | None = None
    limit_m: float | None = None
    T_vehicle_camera: np.ndarray | None = None

    @classmethod
    def from_world(cls, world: Path, limit_m: float | None = None) -> Road:
        """From a world folder's path.npz, and world.json / camera.json when present."""
        world = Path(world)
        with np.load(world / "path.npz") as path:
            x, y = np.asarray(path["x_m"], float), np.asarray(path["y_m"], float)
            arc = np.asarray(path["arc_length_m"], float) if "arc_length_m" in path else _arc(x, y)
        lane = _json_number(world / "world.json", "lane_width_m")
        T = None
        if (world / "camera.json").is_file():
            T = np.asarray(json.loads((world / "camera.json").read_text())["T_vehicle_camera"], float)
        return cls(x, y, arc, None if lane is None else 0.5 * lane, limit_m, T)

    def lines(self, arc_from_m: float, arc_to_m: float) -> dict[str, list[np.ndarray]]:
        """(K, 2) polylines between two arc lengths: "path", and "lane" / "limit" pairs left and right."""
        keep = (self.arc_length_m >= arc_from_m) & (self.arc_length_m <= arc_to_m)
        if keep.sum() < 2:
            keep = np.ones_like(self.arc_length_m, dtype=bool)
        xy = np.column_stack([self.x_m[keep], self.y_m[keep]])
        d = np.gradient(xy, axis=0) if len(xy) > 1 else np.array([[1.0, 0.0]])
        normal = np.column_stack([-d[:, 1], d[:, 0]]) / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        out: dict[str, list[np.ndarray]] = {"path": [xy]}
        for name, half in (("lane", self.lane_half_width_m), ("limit", self.limit_m)):
            if half is not None and math.isfinite(half):
                out[name] = [xy + half * normal, xy - half * normal]
        return out


def _arc(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])


def _json_number(path: Path, key: str) -> float | None:
    try:
        value = json.loads(path.read_text()).get(key)
    except (OSError, ValueError):
        return None
    return float(value) if isinstance(value, int | float) else None


@functools.cache
def _schema(message_class: type) -> bytes:
    """The message's FileDescriptorSet (its .proto and their dependencies), built once per process."""
    return build_file_descriptor_set(message_class).SerializeToString()


class _Writer:
    """mcap's writer with one channel per topic; protobuf schemas registered once from the message class."""

    def __init__(self, stream: Any) -> None:
        self._mcap = Writer(stream, compression=CompressionType.ZSTD)
        self._mcap.start(profile="", library="drivesim")
        self._channels: dict[str, int] = {}

    def _channel(self, topic: str, encoding: str, schema: tuple[str, str, bytes]) -> int:
        if topic not in self._channels:
            schema_id = self._mcap.register_schema(name=schema[0], encoding=schema[1], data=schema[2])
            self._channels[topic] = self._mcap.register_channel(topic, encoding, schema_id)
        return self._channels[topic]

    def proto(self, topic: str, message: Any, t_ns: int) -> None:
        """Write a protobuf message (its schema: the message's FileDescriptorSet)."""
        if topic not in self._channels:
            self._channel(topic, "protobuf", (type(message).DESCRIPTOR.full_name, "protobuf", _schema(type(message))))
        channel = self._channels[topic]
        self._mcap.add_message(channel, log_time=t_ns, data=message.SerializeToString(), publish_time=t_ns)

    def json(self, topic: str, schema: dict[str, Any], value: dict[str, Any], t_ns: int) -> None:
        """Write a JSON message with its JSON schema."""
        if topic not in self._channels:
            self._channel(topic, "json", (schema["title"], "jsonschema", json.dumps(schema).encode()))
        channel = self._channels[topic]
        data = json.dumps(value, allow_nan=False, separators=(",", ":")).encode()
        self._mcap.add_message(channel, log_time=t_ns, data=data, publish_time=t_ns)

    def finish(self) -> None:
        self._mcap.finish()


def write_episode_mcap(capture: EpisodeCapture, road: Road | None, path: Path, title: str = "") -> Path:
    """Write the episode to `path` (atomically: a temporary file moved into place); returns `path`.

    :param capture: the episode's steps (at least the reset).
    :param road: the road to draw (None: no road lines).
    :param path: the .mcap file to write.
    :param title: first words of the termination log line (e.g. "overtake seed 12").
    """
    if not capture.steps:
        raise ValueError("an episode with no steps cannot be recorded")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as stream:
            writer = _Writer(stream)
            times = [_t_ns(s, k) for k, s in enumerate(capture.steps)]
            camera = _camera_pose(road)
            if road is not None:
                writer.proto("/scene/road", _road_update(road, capture, times[0]), times[0])
            for k, (sample, t_ns) in enumerate(zip(capture.steps, times, strict=True)):
                _write_step(writer, capture, camera, k, sample, t_ns)
            writer.proto("/log", _termination_log(capture, title, times[-1]), times[-1])
            writer.finish()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _t_ns(sample: StepSample, k: int) -> int:
    t_s = sample.state.get("t_s", math.nan)
    return int(round((t_s if math.isfinite(t_s) else 0.1 * k) * 1e9))


_CameraPose = tuple[tuple[float, ...], tuple[float, ...]]


def _write_step(
    writer: _Writer, capture: EpisodeCapture, camera: _CameraPose | None, k: int, s: StepSample, t_ns: int
) -> None:
    ok, jpeg = cv2.imencode(".jpg", s.image_rgb[:, :, ::-1], _JPEG_PARAMS)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError("OpenCV could not encode the camera image as JPEG")
    image = CompressedImage(frame_id="camera", data=jpeg.tobytes(), format="jpeg")
    image.timestamp.FromNanoseconds(t_ns)
    writer.proto("/camera/image", image, t_ns)
    for transform in _transforms(s.state, camera, t_ns):
        writer.proto("/tf", transform, t_ns)
    writer.proto("/scene/vehicles", _vehicles_update(capture.episode, s.state, t_ns), t_ns)
    writer.json("/ego/step", STEP_SCHEMA, _step_values(k, s, k == len(capture.steps) - 1), t_ns)


def _finite(state: dict[str, float], key: str) -> bool:
    value = state.get(key)
    return value is not None and math.isfinite(value)


def _yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, math.sin(0.5 * yaw_rad), math.cos(0.5 * yaw_rad)


def _camera_pose(road: Road | None) -> _CameraPose | None:
    """(translation, quaternion x y z w) of the camera in the ego frame, None when unknown."""
    if road is None or road.T_vehicle_camera is None:
        return None
    T = road.T_vehicle_camera
    return tuple(float(v) for v in T[:3, 3]), tuple(float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat())


def _transforms(state: dict[str, float], camera: _CameraPose | None, t_ns: int) -> list[Any]:
    out = []
    for name in ("ego", "other"):
        if not (_finite(state, f"{name}_x_m") and _finite(state, f"{name}_y_m")):
            continue
        t = FrameTransform(parent_frame_id="world", child_frame_id=name)
        t.translation.x, t.translation.y = state[f"{name}_x_m"], state[f"{name}_y_m"]
        q = _yaw_quaternion(state.get(f"{name}_yaw_rad", 0.0) if _finite(state, f"{name}_yaw_rad") else 0.0)
        t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = q
        out.append(t)
    if camera is not None and out:
        t = FrameTransform(parent_frame_id="ego", child_frame_id="camera")
        t.translation.x, t.translation.y, t.translation.z = camera[0]
        t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = camera[1]
        out.append(t)
    for t in out:
        t.timestamp.FromNanoseconds(t_ns)
    return out


def _rgba(target: Any, name: str) -> None:
    target.r, target.g, target.b, target.a = _COLORS[name]


def footprint_corners(
    x_m: float, y_m: float, yaw_rad: float, length_m: float, width_m: float
) -> list[tuple[float, float]]:
    """The four corners of `sim.footprint.footprint`'s rectangle, in its order (front left first).

    Plain math rather than the shapely polygon: it runs for every car of every recorded step, 5x faster."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    half_l, half_w = 0.5 * length_m, 0.5 * width_m
    corners = ((half_l, half_w), (-half_l, half_w), (-half_l, -half_w), (half_l, -half_w))
    return [(x_m + u * c - v * s, y_m + u * s + v * c) for u, v in corners]


def _footprint_xy(state: dict[str, float], name: str, episode: dict[str, Any]) -> list[tuple[float, float]] | None:
    length, width = episode.get(f"{name}_length_m"), episode.get(f"{name}_width_m")
    keys = (f"{name}_x_m", f"{name}_y_m", f"{name}_yaw_rad")
    if not all(_finite(state, k) for k in keys) or not isinstance(length, int | float) or not math.isfinite(length):
        return None
    return footprint_corners(state[keys[0]], state[keys[1]], state[keys[2]], float(length), float(width))


def _vehicles_update(episode: dict[str, Any], state: dict[str, float], t_ns: int) -> Any:
    update = SceneUpdate()
    corners = {}
    for name in ("ego", "other"):
        xy = _footprint_xy(state, name, episode)
        if xy is None:
            continue
        corners[name] = xy
        entity = update.entities.add(frame_id="world", id=name)
        entity.timestamp.FromNanoseconds(t_ns)
        cube = entity.cubes.add()
        cube.pose.position.x, cube.pose.position.y = state[f"{name}_x_m"], state[f"{name}_y_m"]
        cube.pose.position.z = 0.5 * VEHICLE_HEIGHT_M
        q = _yaw_quaternion(state[f"{name}_yaw_rad"])
        cube.pose.orientation.x, cube.pose.orientation.y, cube.pose.orientation.z, cube.pose.orientation.w = q
        cube.size.x, cube.size.y = float(episode[f"{name}_length_m"]), float(episode[f"{name}_width_m"])
        cube.size.z = VEHICLE_HEIGHT_M
        _rgba(cube.color, name)
        loop = entity.lines.add(type=LinePrimitive.LINE_LOOP, thickness=0.08, scale_invariant=False)
        loop.pose.orientation.w = 1.0
        for x, y in xy:
            loop.points.add(x=x, y=y, z=0.02)
        _rgba(loop.color, name)
    clearance = state.get("clearance_m", math.inf)
    if "ego" in corners and "other" in corners and clearance < CLEARANCE_LINE_M:
        (ax, ay), (bx, by) = shortest_line(Polygon(corners["ego"]), Polygon(corners["other"])).coords
        entity = update.entities.add(frame_id="world", id="clearance")
        entity.timestamp.FromNanoseconds(t_ns)
        line = entity.lines.add(type=LinePrimitive.LINE_LIST, thickness=0.05, scale_invariant=False)
        line.pose.orientation.w = 1.0
        line.points.add(x=ax, y=ay, z=0.05)
        line.points.add(x=bx, y=by, z=0.05)
        _rgba(line.color, "clearance")
    else:  # entities stay until replaced: remove the segment of an earlier step
        deletion = update.deletions.add(type=SceneEntityDeletion.MATCHING_ID, id="clearance")
        deletion.timestamp.FromNanoseconds(t_ns)
    return update


def _road_update(road: Road, capture: EpisodeCapture, t_ns: int) -> Any:
    arcs = [s.state.get("arc_length_m", math.nan) for s in capture.steps]
    arcs = [a for a in arcs if math.isfinite(a)] or [float(road.arc_length_m[0]), float(road.arc_length_m[-1])]
    update = SceneUpdate()
    entity = update.entities.add(frame_id="world", id="road")
    entity.timestamp.FromNanoseconds(t_ns)
    for name, polylines in road.lines(min(arcs) - ROAD_MARGIN_M, max(arcs) + ROAD_MARGIN_M).items():
        for xy in polylines:
            line = entity.lines.add(
                type=LinePrimitive.LINE_STRIP, thickness=0.12 if name == "path" else 0.06, scale_invariant=False
            )
            line.pose.orientation.w = 1.0
            for x, y in xy:
                line.points.add(x=float(x), y=float(y), z=0.0)
            _rgba(line.color, name)
    return update


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else None


def _step_values(k: int, s: StepSample, last: bool) -> dict[str, Any]:
    st = s.state
    rewards = {name: _number(v) for name, v in s.rewards.items()}
    if s.rewards:
        rewards["total"] = _number(sum(s.rewards.values()))
    return {
        "step": k,
        "t_s": _number(st.get("t_s")) or 0.0,
        "action": _number(s.action),
        "steering_curvature_1pm": _number(st.get("steering_curvature_1pm")),
        "q_lat_m": _number(st.get("q_lat_m")),
        "q_rot_rad": _number(st.get("q_rot_rad")),
        "speed_mps": _number(st.get("ego_speed_mps")),
        "clearance_m": _number(st.get("clearance_m")),
        "other_rel_x_m": _number(st.get("other_rel_x_m")),
        "other_rel_y_m": _number(st.get("other_rel_y_m")),
        "reward": rewards,
        "termination": dict(s.termination),
        "done": last,
    }


def _termination_log(capture: EpisodeCapture, title: str, t_ns: int) -> Any:
    last = capture.steps[-1].state
    clearance = _number(last.get("clearance_m"))
    words = [
        f"{title}: " if title else "",
        f"{capture.outcome} after {len(capture.steps) - 1} steps ({t_ns / 1e9:.1f} s)",
        f", q_lat {last.get('q_lat_m', math.nan):+.2f} m, q_rot {last.get('q_rot_rad', math.nan):+.3f} rad",
        "" if clearance is None else f", clearance {clearance:.2f} m",
    ]
    log = Log(level=Log.ERROR if capture.causes else Log.INFO, message="".join(words), name="drivesim.episode")
    log.timestamp.FromNanoseconds(t_ns)
    return log
