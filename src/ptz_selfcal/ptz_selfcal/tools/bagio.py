"""ROS 2 bag reading and writing with rosbags (rosbag2 and `ros2 bag` do not exist here).

Messages stay raw CDR bytes wherever possible: play publishes them unchanged, record writes what
arrived unchanged. The project's own message types are registered from their .msg definitions.
"""

from __future__ import annotations

import contextlib
import os
import struct
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

MSG_PACKAGE = "ptz_selfcal_msgs"


class BagError(Exception):
    """A bag that cannot be read or written; the message is a one-line explanation for users."""


def _msg_dirs() -> list[Path]:
    """Where the .msg files may be: ament prefixes, this interpreter's prefix, the source tree."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    dirs = [Path(p) / "share" / MSG_PACKAGE / "msg" for p in prefixes]
    dirs.append(Path(__file__).resolve().parents[3] / MSG_PACKAGE / "msg")
    return dirs


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The Jazzy typestore with ptz_selfcal_msgs registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for directory in _msg_dirs():
        files = sorted(directory.glob("*.msg"))
        if files:
            types: dict[str, Any] = {}
            for path in files:
                types.update(get_types_from_msg(path.read_text(), f"{MSG_PACKAGE}/msg/{path.stem}"))
            store.register(types)
            return store
    raise BagError(f"cannot find the {MSG_PACKAGE} message definitions (is the environment built?)")


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes of a rosbags message object."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(raw: bytes | memoryview, msgtype: str) -> Any:
    return typestore().deserialize_cdr(raw, msgtype)


def header_stamp_ns(raw: bytes | memoryview) -> int | None:
    """The header stamp of a CDR-serialised message whose first field is std_msgs/Header, without
    deserialising the rest (None if too short)."""
    if len(raw) < 12:
        return None
    sec, nanosec = struct.unpack_from("<iI" if raw[1] == 1 else ">iI", raw, 4)
    return sec * 1_000_000_000 + nanosec


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    timestamp_ns: int
    raw: bytes


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


def _check_bag_path(path: Path) -> Path:
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if path.is_file() and path.suffix in (".mcap", ".db3"):
        # A bare storage file: rosbags wants the bag directory with metadata.yaml.
        if (path.parent / "metadata.yaml").exists():
            return path.parent
        raise BagError(f"{path}: a storage file without its metadata.yaml (pass the bag directory)")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise BagError(f"{path}: not a ROS 2 bag (no metadata.yaml)")
    if path.is_file():
        raise BagError(f"{path}: not a ROS 2 bag (expected a bag directory)")
    return path


class BagReader:
    """Sequential reader over a ROS 2 bag (sqlite3 or mcap) with clear errors."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = _check_bag_path(Path(path))
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as exc:  # rosbags raises several types for damaged bags
            raise BagError(f"{self.path}: cannot open bag ({_one_line(exc)})") from exc

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with contextlib.suppress(Exception):  # a damaged bag's close must not mask the real error
            self._reader.close()

    @property
    def duration_ns(self) -> int:
        return int(self._reader.duration)

    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    def topics(self) -> list[TopicInfo]:
        return [
            TopicInfo(name, info.msgtype or "", info.msgcount)
            for name, info in sorted(self._reader.topics.items())
        ]

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages in bag-timestamp order; a damaged bag ends with BagError after its good messages."""
        wanted = set(topics) if topics is not None else None
        connections = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        try:
            for conn, timestamp, raw in self._reader.messages(connections=connections):
                yield BagMessage(conn.topic, conn.msgtype, int(timestamp), bytes(raw))
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"{self.path}: bag is damaged or truncated ({_one_line(exc)})") from exc


class BagWriter:
    """Writes raw CDR messages to a new bag (mcap by default); refuses to overwrite anything."""

    def __init__(self, path: str | os.PathLike[str], storage: str = "mcap") -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path}: already exists (refusing to overwrite)")
        if not self.path.parent.exists():
            raise BagError(f"{self.path.parent}: no such directory")
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._writer.open()
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=typestore())

    def write_raw(self, topic: str, timestamp_ns: int, raw: bytes | memoryview) -> None:
        self._writer.write(self._connections[topic], int(timestamp_ns), raw)

    def write(self, topic: str, msgtype: str, timestamp_ns: int, msg: Any) -> None:
        """Serialise a rosbags message object and write it (adds the topic on first use)."""
        self.add_topic(topic, msgtype)
        self.write_raw(topic, timestamp_ns, serialize(msg, msgtype))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def msg_class(msgtype: str) -> Any:
    """The rclpy (rosidl) Python class of a type name like 'sensor_msgs/msg/Image'."""
    import importlib

    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f"message type {msgtype} is not available in this environment") from exc
