"""ROS 2 bag reading and writing with rosbags (rosbag2 and `ros2 bag` do not exist here).

Messages stay raw CDR bytes wherever possible: play publishes them unchanged, record writes what
arrived unchanged. The project's own message types are registered from their .msg definitions.
A bag rosbags cannot open (cut off by a crash, no summary, a damaged sqlite3 tail) is read record by
record up to its last complete one, and the reader says what was lost.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import struct
import sys
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.storage_mcap import decompress, get_qos
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
    qos: tuple[Qos, ...] = ()  # the offered QoS profiles recorded with the topic


def _storage_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix in (".mcap", ".db3"))


def _check_bag_path(path: Path) -> Path:
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    if path.is_file() and path.suffix in (".mcap", ".db3"):
        # A bare storage file: rosbags wants the bag directory with metadata.yaml.
        if (path.parent / "metadata.yaml").exists():
            return path.parent
        return path  # a recording that died before writing metadata.yaml: recovered from the file alone
    if path.is_dir() and not (path / "metadata.yaml").exists():
        if len(_storage_files(path)) == 1:
            return path
        raise BagError(f"{path}: not a ROS 2 bag (no metadata.yaml)")
    if path.is_file():
        raise BagError(f"{path}: not a ROS 2 bag (expected a bag directory)")
    return path


# --------------------------------------------------------------------------------------------------
# Recovery: a bag rosbags cannot open (truncated by a crash, no summary, damaged sqlite3 tail) is read
# record by record up to its last complete one.
# --------------------------------------------------------------------------------------------------
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END = 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F


def _str(buf: bytes | memoryview, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


@dataclass
class _McapScan:
    """What a record-by-record pass over an MCAP file found."""

    schemas: dict[int, str] = field(default_factory=dict)  # schema id -> message type
    channels: dict[int, tuple[str, str, tuple[Qos, ...]]] = field(default_factory=dict)
    complete: bool = False  # reached DataEnd or the footer
    good_bytes: int = 0  # file offset after the last complete record read
    problem: str = ""


def _mcap_records(buf: bytes | memoryview, scan: _McapScan, base: int | None) -> Iterator[tuple]:
    """(op, body) of the complete records of buf; base is buf's file offset (None inside a chunk)."""
    pos = 0
    while pos + 9 <= len(buf):
        op = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        if pos + 9 + length > len(buf):
            break
        yield op, buf[pos + 9 : pos + 9 + length]
        pos += 9 + length
        if base is not None:
            scan.good_bytes = base + pos


def _mcap_scan(path: Path, scan: _McapScan) -> Iterator[tuple[int, int, bytes]]:
    """(channel id, log time, data) of every complete message, in file order (time order within a
    chunk); an incomplete uncompressed chunk yields its complete messages too."""
    with path.open("rb") as bio:
        if bio.read(8) != _MCAP_MAGIC:
            scan.problem = "not an MCAP file (bad magic)"
            return
        scan.good_bytes = 8
        yield from _mcap_stream(bio, scan)


def _mcap_stream(bio: BinaryIO, scan: _McapScan) -> Iterator[tuple[int, int, bytes]]:
    while True:
        start = bio.tell()
        head = bio.read(9)
        if len(head) < 9:
            return
        op = head[0]
        (length,) = struct.unpack_from("<Q", head, 1)
        body = bio.read(length)
        if op in (_OP_DATA_END, _OP_FOOTER) and len(body) == length:
            scan.complete = True
            scan.good_bytes = start + 9 + length
            return
        if len(body) < length:
            if op == _OP_CHUNK:
                yield from _mcap_chunk(body, scan, start, complete=False)
            return
        if op == _OP_CHUNK:
            yield from _mcap_chunk(body, scan, start, complete=True)
        else:
            yield from _mcap_record(op, body, scan)
        scan.good_bytes = start + 9 + length


def _mcap_chunk(body: bytes, scan: _McapScan, start: int, complete: bool) -> Iterator[tuple[int, int, bytes]]:
    if len(body) < 32:
        return
    (uncompressed_size, crc) = struct.unpack_from("<QI", body, 16)
    compression, pos = _str(body, 28)
    (size,) = struct.unpack_from("<Q", body, pos)
    data = memoryview(body)[pos + 8 : pos + 8 + size]
    if complete:
        try:
            records = decompress(bytes(data), compression, uncompressed_size, crc)
        except Exception as exc:
            scan.problem = f"chunk at byte {start} unreadable ({_one_line(exc)})"
            return
    elif compression:
        return  # a compressed chunk cut short cannot be decompressed
    else:
        records = data
    messages = []
    for op, rec in _mcap_records(records, scan, None if complete else start + 9 + pos + 8):
        messages.extend(_mcap_record(op, rec, scan))
    yield from sorted(messages, key=lambda m: m[1])


def _mcap_record(op: int, body: bytes | memoryview, scan: _McapScan) -> Iterator[tuple[int, int, bytes]]:
    if op == _OP_MESSAGE:
        channel, _seq, log_time = struct.unpack_from("<HIQ", body, 0)
        yield channel, log_time, bytes(body[22:])
    elif op == _OP_SCHEMA:
        (sid,) = struct.unpack_from("<H", body, 0)
        scan.schemas[sid] = _str(body, 2)[0]
    elif op == _OP_CHANNEL:
        cid, sid = struct.unpack_from("<HH", body, 0)
        topic, pos = _str(body, 4)
        _encoding, pos = _str(body, pos)
        (size,) = struct.unpack_from("<I", body, pos)
        try:
            qos = tuple(get_qos(bytes(body[pos + 4 : pos + 4 + size])))
        except Exception:
            qos = ()
        scan.channels[cid] = (topic, scan.schemas.get(sid, ""), qos)


def _sqlite_copy(db: Path, tmp: Path) -> Path:
    """A copy of a damaged sqlite3 file cut to whole pages, its header's page count set to match (a
    header promising pages the file lacks makes sqlite call the whole file malformed)."""
    data = bytearray(db.read_bytes())
    if len(data) < 100 or not data.startswith(b"SQLite format 3\x00"):
        raise BagError(f"{db}: not an sqlite3 file")
    (page_size,) = struct.unpack_from(">H", data, 16)
    page_size = 65536 if page_size == 1 else page_size
    pages = len(data) // page_size
    del data[pages * page_size :]
    struct.pack_into(">I", data, 28, pages)
    out = tmp / db.name
    out.write_bytes(bytes(data))
    return out


class _Recovered:
    """A bag read record by record; `damage` says what could not be read."""

    def __init__(self, path: Path, first_error: str) -> None:
        self.path = path
        directory = path if path.is_dir() else path.parent
        files = [path] if path.is_file() else _storage_files(path)
        if len(files) != 1:
            raise BagError(f"{path}: cannot open bag ({first_error})")
        self.file = files[0]
        self.expected = _expected_counts(directory)
        self.counts: Counter[str] = Counter()
        self.types: dict[str, str] = {}
        self.qos: dict[str, tuple[Qos, ...]] = {}
        self.start_ns = self.end_ns = 0
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self.problem = ""
        try:
            for msg in self.messages(None):
                self.counts[msg.topic] += 1
                self.start_ns = min(self.start_ns or msg.timestamp_ns, msg.timestamp_ns)
                self.end_ns = max(self.end_ns, msg.timestamp_ns)
        except Exception as exc:
            raise BagError(f"{path}: cannot open bag ({first_error}; recovery: {_one_line(exc)})") from exc
        if not self.types:
            raise BagError(f"{path}: cannot open bag ({first_error}; nothing readable)")
        self.damage = self._describe(first_error)

    def _describe(self, first_error: str) -> str:
        read = sum(self.counts.values())
        text = f"{self.path}: {first_error.rstrip('.')}; read {read} messages"
        if self.expected:
            lost = {
                t: n - self.counts.get(t, 0) for t, n in self.expected.items() if n > self.counts.get(t, 0)
            }
            text += f" of {sum(self.expected.values())}"
            if lost:
                text += (
                    " (lost: " + ", ".join(f"{t} {n} of {self.expected[t]}" for t, n in lost.items()) + ")"
                )
        if self.problem:
            text += f"; {self.problem}"
        return text

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def messages(self, wanted: set[str] | None) -> Iterator[BagMessage]:
        if self.file.suffix == ".db3":
            yield from self._sqlite_messages(wanted)
            return
        scan = _McapScan()
        for channel, log_time, data in _mcap_scan(self.file, scan):
            if channel not in scan.channels:
                continue
            topic, msgtype, qos = scan.channels[channel]
            self.types.setdefault(topic, msgtype)
            self.qos.setdefault(topic, qos)
            if wanted is None or topic in wanted:
                yield BagMessage(topic, msgtype, log_time, data)
        size = self.file.stat().st_size
        if not scan.complete:
            self.problem = f"{size - scan.good_bytes} of {size} bytes after the last complete record unread"
        if scan.problem:
            self.problem = scan.problem
        for topic, msgtype, qos in scan.channels.values():
            self.types.setdefault(topic, msgtype)
            self.qos.setdefault(topic, qos)

    def _sqlite_messages(self, wanted: set[str] | None) -> Iterator[BagMessage]:
        if self._tmp is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="ptz_selfcal_bag_")
            self._copy = _sqlite_copy(self.file, Path(self._tmp.name))
        db = sqlite3.connect(f"file:{self._copy}?mode=ro", uri=True)
        try:
            cols = {row[1] for row in db.execute("PRAGMA table_info(topics)")}
            qos_col = ", offered_qos_profiles" if "offered_qos_profiles" in cols else ", ''"
            topics: dict[int, tuple[str, str]] = {}
            for tid, name, msgtype, qos in db.execute(f"SELECT id, name, type{qos_col} FROM topics"):
                topics[tid] = (name, msgtype)
                self.types.setdefault(name, msgtype)
                with contextlib.suppress(Exception):
                    self.qos.setdefault(name, tuple(parse_qos(qos)))
            # Rows in insertion order, up to the first one the damage made unreadable.
            rows = db.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id")
            while True:
                try:
                    row = next(rows, None)
                except sqlite3.DatabaseError as exc:
                    self.problem = f"rows after the damage unreadable ({_one_line(exc)})"
                    return
                if row is None:
                    return
                name, msgtype = topics.get(row[0], ("", ""))
                if name and (wanted is None or name in wanted):
                    yield BagMessage(name, msgtype, int(row[1]), bytes(row[2]))
        finally:
            db.close()


def _expected_counts(directory: Path) -> dict[str, int]:
    """Per-topic message counts metadata.yaml promises ({} without one)."""
    import yaml

    try:
        info = yaml.safe_load((directory / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return {
            t["topic_metadata"]["name"]: int(t["message_count"]) for t in info["topics_with_message_count"]
        }
    except Exception:
        return {}


class BagReader:
    """Sequential reader over a ROS 2 bag (sqlite3 or mcap) with clear errors.

    A bag rosbags cannot open (truncated, no summary, damaged sqlite3 tail, no metadata.yaml) is read up
    to its last complete record; `damage` then says what was lost (None for a sound bag)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = _check_bag_path(Path(path))
        self._recovered: _Recovered | None = None
        self.damage: str | None = None
        try:
            if self.path.is_file():
                raise BagError("no metadata.yaml")
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as exc:  # rosbags raises several types for damaged bags
            self._recovered = _Recovered(self.path, _one_line(exc))
            self.damage = self._recovered.damage

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._recovered is not None:
            self._recovered.close()
            return
        with contextlib.suppress(Exception):  # a damaged bag's close must not mask the real error
            self._reader.close()

    @property
    def duration_ns(self) -> int:
        if self._recovered is not None:
            rec = self._recovered
            return rec.end_ns - rec.start_ns + 1 if rec.counts else 0
        return int(self._reader.duration)

    @property
    def start_ns(self) -> int:
        if self._recovered is not None:
            return self._recovered.start_ns
        return int(self._reader.start_time)

    def unread(self, topic: str) -> int | None:
        """Messages of a topic the damage made unreadable: 0 for a sound bag, None when unknown (a
        damaged bag without metadata.yaml)."""
        if self._recovered is None:
            return 0
        rec = self._recovered
        if not rec.expected:
            return None
        return max(0, rec.expected.get(topic, 0) - rec.counts.get(topic, 0))

    def topics(self) -> list[TopicInfo]:
        if self._recovered is not None:
            rec = self._recovered
            return [
                TopicInfo(name, rec.types[name], rec.counts.get(name, 0), rec.qos.get(name, ()))
                for name in sorted(rec.types)
            ]
        return [
            TopicInfo(
                name,
                info.msgtype or "",
                info.msgcount,
                tuple(info.connections[0].ext.offered_qos_profiles) if info.connections else (),
            )
            for name, info in sorted(self._reader.topics.items())
        ]

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages in bag-timestamp order (file order for a recovered bag: time order as recorded);
        a damaged bag ends with BagError after its good messages."""
        wanted = set(topics) if topics is not None else None
        if self._recovered is not None:
            yield from self._recovered.messages(wanted)
            return
        connections = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        try:
            for conn, timestamp, raw in self._reader.messages(connections=connections):
                yield BagMessage(conn.topic, conn.msgtype, int(timestamp), bytes(raw))
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"{self.path}: bag is damaged or truncated ({_one_line(exc)})") from exc


# How `play` publishes (reliable, keep-all, volatile): the profile a topic gets when no other is known.
_INFINITE = QosTime(9223372036, 854775807)  # rmw's infinite duration, as rosbag2 writes it
PLAY_QOS = Qos(
    QosHistory.KEEP_ALL,
    0,
    QosReliability.RELIABLE,
    QosDurability.VOLATILE,
    _INFINITE,
    _INFINITE,
    QosLiveliness.AUTOMATIC,
    _INFINITE,
    False,
)


def qos_from_rclpy(profile: Any) -> Qos:
    """rosbags' Qos of an rclpy QoSProfile (the policy enums share rmw's numbering)."""

    def duration(value: Any) -> QosTime:
        ns = int(value.nanoseconds)
        return _INFINITE if ns >= 2**63 - 1 else QosTime(ns // 1_000_000_000, ns % 1_000_000_000)

    return Qos(
        QosHistory(int(profile.history)),
        int(profile.depth),
        QosReliability(int(profile.reliability)),
        QosDurability(int(profile.durability)),
        duration(profile.deadline),
        duration(profile.lifespan),
        QosLiveliness(int(profile.liveliness)),
        duration(profile.liveliness_lease_duration),
        bool(profile.avoid_ros_namespace_conventions),
    )


class BagWriter:
    """Writes raw CDR messages to a new bag (mcap by default); refuses to overwrite anything.

    A topic's connection is created with its first message (or at close), so that its offered QoS
    profiles can be set once the publishers are known (`set_qos`)."""

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
        self._pending: dict[str, tuple[str, tuple[Qos, ...]]] = {}  # topic -> type, QoS

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """Declare a topic (again: no change); without QoS profiles it gets PLAY_QOS unless set later."""
        if topic not in self._connections and topic not in self._pending:
            self._pending[topic] = (msgtype, tuple(qos))

    def set_qos(self, topic: str, qos: Sequence[Qos]) -> None:
        """The offered QoS profiles of a declared topic that has no message yet (otherwise ignored)."""
        if topic in self._pending and qos:
            self._pending[topic] = (self._pending[topic][0], tuple(qos))

    def _connection(self, topic: str) -> Any:
        conn = self._connections.get(topic)
        if conn is None:
            msgtype, qos = self._pending.pop(topic)
            conn = self._writer.add_connection(
                topic, msgtype, typestore=typestore(), offered_qos_profiles=list(qos or (PLAY_QOS,))
            )
            self._connections[topic] = conn
        return conn

    def write_raw(self, topic: str, timestamp_ns: int, raw: bytes | memoryview) -> None:
        self._writer.write(self._connection(topic), int(timestamp_ns), raw)

    def write(self, topic: str, msgtype: str, timestamp_ns: int, msg: Any) -> None:
        """Serialise a rosbags message object and write it (adds the topic on first use)."""
        self.add_topic(topic, msgtype)
        self.write_raw(topic, timestamp_ns, serialize(msg, msgtype))

    def close(self) -> None:
        if self._writer is not None:
            for topic in list(self._pending):
                self._connection(topic)
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
