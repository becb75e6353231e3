"""Recording readers with one interface: topics with message counts up front, then decoded messages in log-time order.

ROS1 bags and rosbag2 folders (sqlite3 or mcap storage) are read with `rosbags.highlevel.AnyReader`; plain `.mcap`
files with `mcap` and `mcap_ros2`'s CDR decoder. Message type names are normalised to the ROS2 form
(`sensor_msgs/msg/Image`), and reader failures become `InputError`s that name the file.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from drivesim.pipeline.errors import InputError

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_ROSBAG1_MAGIC = b"#ROSBAG V2.0"


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a recording: its name, ROS2-style message type and message count."""

    name: str
    msgtype: str
    message_count: int


class MessageSource(Protocol):
    """What the ROS ingest needs from a recording reader."""

    path: Path
    format: str
    topics: dict[str, TopicInfo]

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, decoded message) for the given topics in log-time order."""
        ...

    def close(self) -> None:
        """Release the files."""
        ...


def normalise_msgtype(name: str) -> str:
    """`sensor_msgs/Image` and `sensor_msgs/msg/Image` both become `sensor_msgs/msg/Image`."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def _head(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(16)
    except OSError:
        return b""


def is_mcap_file(path: Path) -> bool:
    """An MCAP file (by its magic bytes)."""
    return path.is_file() and _head(path).startswith(_MCAP_MAGIC)


def is_ros1_bag(path: Path) -> bool:
    """A ROS1 bag v2.0 (by its magic line)."""
    return path.is_file() and _head(path).startswith(_ROSBAG1_MAGIC)


def is_rosbag2_folder(path: Path) -> bool:
    """A rosbag2 recording folder (it has metadata.yaml)."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


_ACCEPTED = (
    "give a ROS1 .bag, an .mcap file, a rosbag2 folder (with metadata.yaml), a KITTI raw drive folder (image_0X/ + "
    "oxts/), a KITTI odometry sequence (image_l/ + poses.txt + calib.txt), a video file (.mp4, .mov, .mkv, .avi, "
    ".m4v, .webm, .mpg, .mpeg, .ts) or a folder of PNG/JPEG images only (with --fps)"
)
"""Every kind of recording `drivesim ingest` reads (stages/ingest/run.py FORMATS), for the refusal of any other."""


def unrecognised(path: Path) -> InputError:
    """The one-line refusal for a path no format matched, saying what it looks like and what to pass instead."""
    if not path.exists():
        return InputError("no such file or folder", path)
    if path.is_file():
        try:
            with open(path, "rb") as f:
                f.read(16)
        except OSError as e:
            return InputError(f"cannot read the file: {e.strerror}", path)
        if path.suffix == ".db3" or (path.suffix == ".mcap" and (path.parent / "metadata.yaml").is_file()):
            return InputError("this is one file of a rosbag2 recording; pass its folder instead", path)
        return InputError(f"not a recording drivesim can read; {_ACCEPTED}", path)
    names = {p.name for p in path.iterdir()}
    if "calib_cam_to_cam.txt" in names:
        drives = sorted(n for n in names if n.endswith("_sync"))
        hint = f" (e.g. {path / drives[0]})" if drives else ""
        return InputError(f"this is a KITTI date folder; pass one drive folder inside it{hint}", path)
    if any(n.endswith((".db3", ".mcap")) for n in names):
        return InputError("rosbag2 folder without metadata.yaml (incomplete recording?)", path)
    from drivesim.stages.ingest.video import IMAGE_SUFFIXES

    images = sum(1 for n in names if Path(n).suffix.lower() in IMAGE_SUFFIXES)
    mixed = f" ({images} PNG/JPEG file(s) beside other files: an image folder holds images only)" if images else ""
    return InputError(f"folder is not a recording drivesim can read{mixed}; {_ACCEPTED}", path)


def _reader_errors() -> tuple[type[BaseException], ...]:
    """What a reader may raise on a damaged file: any Exception. A flipped byte reaches the readers' length fields,
    decompressors (zstd, lz4), CDR/ROS1 deserialisers and sqlite, and the fuzz test found OverflowError and
    ZstdError besides the readers' own errors; listing types would leave tracebacks. Only the readers' own calls run
    inside these `try` blocks (our handlers run outside the generators), and drivesim's errors pass through."""
    return (Exception,)


def reader_error(path: Path, err: BaseException) -> InputError:
    """A reader failure as one line naming the file (drivesim's own errors are returned as they are)."""
    if isinstance(err, InputError):
        return err
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return InputError(f"unreadable or truncated recording ({type(err).__name__}: {text})", path)


class RosbagsSource:
    """A ROS1 bag or rosbag2 folder read with `rosbags.highlevel.AnyReader`.

    :param path: the .bag file or rosbag2 folder.
    :param fmt: "ros1" or "rosbag2".
    """

    def __init__(self, path: Path, fmt: str) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.format = fmt
        self._errors = _reader_errors()
        try:
            # rosbag2 recordings made before type descriptions were stored need a default typestore.
            self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self._reader.open()
        except self._errors as e:
            raise reader_error(path, e) from None
        self.topics: dict[str, TopicInfo] = {}
        for name, info in self._reader.topics.items():
            self.topics[name] = TopicInfo(name, normalise_msgtype(info.msgtype or "?"), int(info.msgcount))

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, decoded message) for the given topics in log-time order."""
        wanted = set(topics)
        connections = [c for c in self._reader.connections if c.topic in wanted]
        if not connections:
            return
        deserialize = self._reader.deserialize
        try:
            for connection, log_time_ns, raw in self._reader.messages(connections=connections):
                yield connection.topic, log_time_ns, deserialize(raw, connection.msgtype)
        except self._errors as e:
            raise reader_error(self.path, e) from None

    def close(self) -> None:
        """Release the files."""
        with contextlib.suppress(*self._errors):
            self._reader.close()


class McapSource:
    """A plain .mcap file of ROS2 CDR messages read with `mcap` + `mcap_ros2.decoder.DecoderFactory`.

    :param path: the .mcap file.
    """

    format = "mcap"

    def __init__(self, path: Path) -> None:
        from mcap.reader import make_reader

        self.path = path
        self._errors = _reader_errors()
        try:
            self._file = open(path, "rb")  # noqa: SIM115 (closed by close())
            # Chunk CRCs checked as chunks are read: a flipped bit in a chunk is an error, not a corrupted frame.
            self._reader = make_reader(self._file, validate_crcs=True)
            summary = self._reader.get_summary()
        except self._errors as e:
            raise reader_error(path, e) from None
        if summary is None or summary.statistics is None:
            raise InputError("truncated MCAP file: no summary section with message counts (was it closed?)", path)
        self._schemas = summary.schemas
        self._channels = summary.channels
        counts = summary.statistics.channel_message_counts
        self.topics = {}
        for channel_id, channel in summary.channels.items():
            schema = summary.schemas.get(channel.schema_id)
            msgtype = normalise_msgtype(schema.name) if schema is not None else "?"
            previous = self.topics.get(channel.topic)
            count = int(counts.get(channel_id, 0)) + (previous.message_count if previous else 0)
            self.topics[channel.topic] = TopicInfo(channel.topic, msgtype, count)
        self._decoders: dict[int, Any] = {}

    def _decoder(self, schema: Any, channel: Any) -> Any:
        from mcap_ros2.decoder import DecoderFactory

        decoder = self._decoders.get(channel.id)
        if decoder is None:
            if channel.message_encoding != "cdr" or schema is None or schema.encoding != "ros2msg":
                raise InputError(
                    f"topic {channel.topic}: only ROS2 CDR messages with ros2msg schemas are supported "
                    f"(found encoding {channel.message_encoding!r})",
                    self.path,
                )
            decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
            self._decoders[channel.id] = decoder
        return decoder

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time ns, decoded message) for the given topics in log-time order."""
        if not topics:
            return
        try:
            for schema, channel, message in self._reader.iter_messages(topics=topics, log_time_order=True):
                yield channel.topic, message.log_time, self._decoder(schema, channel)(message.data)
        except self._errors as e:
            raise reader_error(self.path, e) from None

    def close(self) -> None:
        """Release the file."""
        self._file.close()


def open_source(path: Path, fmt: str) -> MessageSource:
    """A reader for a ROS recording of the detected format."""
    if fmt == "mcap":
        return McapSource(path)
    return RosbagsSource(path, fmt)
