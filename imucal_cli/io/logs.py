"""Reading ``sensor_msgs/Imu`` from every log format a user has.

One reader per container, picked by :func:`open_log` from the path:

==========================  ==============================================  ==================
path                        container                                       message encoding
==========================  ==============================================  ==================
``*.mcap`` file             plain MCAP (``mcap`` library)                   ROS 2 CDR or ROS 1
directory                   rosbag2, sqlite3 or mcap storage (``rosbags``)  ROS 2 CDR
``*.db3`` file              rosbag2 sqlite3 storage file alone              ROS 2 CDR
``*.bag`` file              ROS 1 bag (``rosbags``)                         ROS 1
==========================  ==============================================  ==================

Readers yield raw messages ``(topic, log_time_ns, data)`` in log-time order; decoding is a
separate step (:class:`ImuDecoder`). :func:`read_imu` assembles per-topic :class:`ImuStream`
objects timed by ``header.stamp`` (log time where the stamp is zero), sorted, with duplicate
stamps removed; what was reordered, removed or replaced is counted in :class:`ReadStats`.
"""

from __future__ import annotations

import sqlite3
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from imucal_cli.errors import LogError
from imucal_cli.io.fastimu import RawBatch, Ros1Bag, decode_imu, mcap_batches, pack_blobs, sqlite_batches
from imucal_cli.io.salvage import Loss, ScanResult, scan_mcap, scan_ros1, scan_sqlite_rows

if TYPE_CHECKING:
    from imucal_cli.types import ImuStream

IMU_MSGTYPE = "sensor_msgs/msg/Imu"

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"


def normalize_msgtype(msgtype: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1) -> ``sensor_msgs/msg/Imu`` (ROS 2 form used throughout)."""
    parts = msgtype.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype.strip()


@dataclass(frozen=True)
class TopicInfo:
    """A topic as the container describes it."""

    topic: str
    msgtype: str  # as stored: sensor_msgs/msg/Imu (ROS 2) or sensor_msgs/Imu (ROS 1)
    count: int
    encoding: str  # "cdr" or "ros1"

    @property
    def is_imu(self) -> bool:
        return normalize_msgtype(self.msgtype) == IMU_MSGTYPE


class LogReader(ABC):
    """A log opened for reading. Use as a context manager."""

    format_name: str = ""

    def __init__(self, path: Path) -> None:
        self.path = path
        #: What could not be read (damaged or cut-off parts), filled in as messages are read.
        self.losses: list[Loss] = []

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the file handles."""

    @abstractmethod
    def topics(self) -> dict[str, TopicInfo]:
        """Every topic in the log."""

    @abstractmethod
    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        """Yield ``(topic, log_time_ns, serialized message)`` in log-time order."""

    def error(self, problem: str, topic: str | None = None) -> LogError:
        return LogError(str(self.path), problem, topic)

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        """Bulk raw batches from the container's indexes, or None where there is no fast path."""
        return None


class McapLog(LogReader):
    """A plain MCAP file, messages in ROS 2 CDR or ROS 1 encoding."""

    format_name = "mcap"

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        from mcap.reader import make_reader

        self._file = path.open("rb")
        try:
            if self._file.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise self.error("not an MCAP file (bad magic bytes)")
            self._file.seek(0)
            self._reader = make_reader(self._file)
            self._summary = self._reader.get_summary()
        except LogError:
            self._file.close()
            raise
        except Exception as exc:  # the mcap library raises many types on corrupt input
            self._file.close()
            raise _NeedsSalvage(f"its summary cannot be read ({exc})") from None
        if self._summary is None:
            self._file.close()
            raise _NeedsSalvage("it has no summary section (cut off, or still being written)")

    def close(self) -> None:
        self._file.close()

    def topics(self) -> dict[str, TopicInfo]:
        assert self._summary is not None
        counts = self._summary.statistics.channel_message_counts if self._summary.statistics else {}
        result: dict[str, TopicInfo] = {}
        for channel_id, channel in self._summary.channels.items():
            schema = self._summary.schemas.get(channel.schema_id)
            msgtype = schema.name if schema else ""
            encoding = "ros1" if channel.message_encoding == "ros1" else channel.message_encoding
            count = int(counts.get(channel_id, 0))
            if channel.topic in result:  # several channels on one topic: add up
                count += result[channel.topic].count
            result[channel.topic] = TopicInfo(channel.topic, msgtype, count, encoding)
        return result

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        return mcap_batches(self.path, topics, self.losses)

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        try:
            for _schema, channel, message in self._reader.iter_messages(topics=list(topics)):
                yield channel.topic, int(message.log_time), bytes(message.data)
        except LogError:
            raise
        except Exception as exc:
            raise self.error(f"cannot read MCAP messages: {exc}") from None


class RosbagsLog(LogReader):
    """A rosbag2 directory (sqlite3 or mcap storage) or a ROS 1 bag, through ``rosbags``."""

    def __init__(self, path: Path, ros1: bool) -> None:
        super().__init__(path)
        self.ros1 = ros1
        self.format_name = "rosbag1" if ros1 else "rosbag2"
        try:
            if ros1:
                from rosbags.rosbag1 import Reader as Rosbag1Reader

                self._reader: Any = Rosbag1Reader(path)
            else:
                from rosbags.rosbag2 import Reader as Rosbag2Reader

                self._reader = Rosbag2Reader(path)
            self._reader.open()
        except Exception as exc:
            raise self.error(f"cannot read {self.format_name}: {exc}") from None
        if not ros1:
            storage = getattr(self._reader, "storage", None)
            backends = getattr(storage, "storages", None) or [storage]
            name = type(backends[0]).__name__.lower()
            if "mcap" in name:
                self.format_name = "rosbag2-mcap"
            elif "sqlite" in name:
                self.format_name = "rosbag2-sqlite3"

    def close(self) -> None:
        try:
            self._reader.close()
        except Exception:  # noqa: S110 - closing a broken reader must not mask the real error
            pass

    def topics(self) -> dict[str, TopicInfo]:
        result: dict[str, TopicInfo] = {}
        for conn in self._reader.connections:
            if self.ros1:
                encoding = "ros1"
                msgtype = conn.msgtype.replace("/msg/", "/")
            else:
                encoding = getattr(conn.ext, "serialization_format", "cdr")
                msgtype = conn.msgtype
            count = int(conn.msgcount)
            if conn.topic in result:
                count += result[conn.topic].count
            result[conn.topic] = TopicInfo(conn.topic, msgtype, count, encoding)
        return result

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        # ROS 1 bags reach this reader only when their index could not be used (open_log).
        if self.ros1:
            return None
        storage = getattr(self._reader, "storage", None)
        metadata = getattr(storage, "metadata", None)
        if metadata is not None and getattr(metadata, "compression_format", None):
            return None
        backends = getattr(storage, "storages", None) or [storage]
        paths = [Path(b.path) for b in backends if getattr(b, "path", None) is not None]
        return _rosbag2_batches(self.format_name, paths, topics)

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        wanted = set(topics)
        connections = [c for c in self._reader.connections if c.topic in wanted]
        if not connections:
            return
        try:
            for conn, timestamp, data in self._reader.messages(connections=connections):
                yield conn.topic, int(timestamp), bytes(data)
        except Exception as exc:
            raise self.error(f"cannot read {self.format_name} messages: {exc}") from None


def _rosbag2_batches(format_name: str, files: list[Path], topics: Iterable[str]) -> Iterator[RawBatch] | None:
    """Fast batches of uncompressed rosbag2 storage files, or None where there is no fast path."""
    topics = list(topics)
    if not files:
        return None
    if format_name == "rosbag2-sqlite3":
        return sqlite_batches(files, topics)
    if format_name == "rosbag2-mcap":
        parts = [mcap_batches(f, topics) for f in files]
        if any(part is None for part in parts):
            return None
        return (batch for part in parts for batch in part)  # type: ignore[union-attr]
    return None


class _LazyFallback(LogReader):
    """A reader with its own fast index, that opens the generic ``rosbags`` reader only when a
    message has to be read one at a time."""

    def __init__(self, path: Path, ros1: bool) -> None:
        super().__init__(path)
        self._ros1 = ros1
        self._generic: RosbagsLog | None = None

    def _fallback(self) -> RosbagsLog:
        if self._generic is None:
            self._generic = RosbagsLog(self.path, ros1=self._ros1)
        return self._generic

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        return self._fallback().iter_raw(topics)

    def close(self) -> None:
        if self._generic is not None:
            self._generic.close()


class Ros1Log(_LazyFallback):
    """An indexed ROS 1 bag read through its own index (:class:`Ros1Bag`)."""

    format_name = "rosbag1"

    def __init__(self, path: Path) -> None:
        super().__init__(path, ros1=True)
        self._handle = path.open("rb")
        try:
            self._bag = Ros1Bag(self._handle)
        except Exception:
            self._handle.close()
            raise

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for conn, topic in self._bag.topics.items():
            count = self._bag.counts.get(conn, 0) + (out[topic].count if topic in out else 0)
            out[topic] = TopicInfo(topic, self._bag.types.get(conn, ""), count, "ros1")
        return out

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        return self._bag.batches(list(topics), self.losses)

    def close(self) -> None:
        super().close()
        self._handle.close()


class Rosbag2Log(LogReader):
    """An uncompressed rosbag2 directory: topics from its ``metadata.yaml``, messages from its
    storage files through the storage's own reader (:class:`Sqlite3Log`, or :class:`McapLog` per
    file), which also reads what is intact of a damaged file."""

    def __init__(self, path: Path) -> None:
        import yaml

        super().__init__(path)
        info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        if info.get("compression_format") or info.get("compression_mode"):
            raise ValueError("compressed rosbag2")
        storage = info["storage_identifier"]
        if storage not in ("sqlite3", "mcap"):
            raise ValueError(f"storage {storage}")
        self.format_name = f"rosbag2-{storage}"
        self.files = [path / Path(p).name for p in info["relative_file_paths"]]
        if not self.files or not all(f.is_file() for f in self.files):
            raise ValueError("storage files missing")
        self._topics: dict[str, TopicInfo] = {}
        for entry in info["topics_with_message_count"]:
            meta = entry["topic_metadata"]
            topic = meta["name"]
            count = int(entry["message_count"]) + (self._topics[topic].count if topic in self._topics else 0)
            self._topics[topic] = TopicInfo(topic, meta["type"], count, meta["serialization_format"])
        self._storage: list[LogReader] = [Sqlite3Log(path, self.files, count=False)] if storage == "sqlite3" else [_open_mcap(f) for f in self.files]
        for reader in self._storage:
            self.losses.extend(reader.losses)
            reader.losses = self.losses  # one list: what any storage file loses is this log's loss
            if "recovered" in reader.format_name:
                self.format_name += " (recovered)"

    def topics(self) -> dict[str, TopicInfo]:
        return dict(self._topics)

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        topics = list(topics)
        parts = [reader.fast_batches(topics) for reader in self._storage]
        if any(part is None for part in parts):
            return None
        return (batch for part in parts for batch in part)  # type: ignore[union-attr]

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        topics = list(topics)
        for reader in self._storage:
            yield from reader.iter_raw(topics)

    def close(self) -> None:
        for reader in self._storage:
            reader.close()


class _NeedsSalvage(Exception):  # a signal to the opener, never seen by users
    """The container's index cannot be used: read it record by record instead."""


class SalvageLog(LogReader):
    """A damaged MCAP file or ROS 1 bag (no summary or index, cut off, damaged chunks), read
    record by record from the start (:mod:`imucal_cli.io.salvage`). What could not be read is
    in :attr:`losses` after a full pass (the opener makes one to list the topics)."""

    def __init__(self, path: Path, kind: str, why: str) -> None:
        super().__init__(path)
        self.kind = kind
        self.why = why
        self.format_name = f"{kind} (recovered)"
        self._scan = scan_mcap if kind == "mcap" else scan_ros1
        try:
            result, walk = self._scan(path, None)
            for _ in walk:
                pass
        except Exception as exc:  # noqa: BLE001 - a file this damaged is unreadable
            raise self.error(f"cannot read {kind}: {exc}") from None
        self.result: ScanResult = result
        self.losses = [Loss(f"read record by record: {why}", 0, 0, lost=False), *result.losses]
        if not result.channels:
            raise self.error(f"cannot read {kind}: {why}, and no topic could be recovered")

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for cid, channel in self.result.channels.items():
            count = self.result.counts.get(cid, 0) + (out[channel.topic].count if channel.topic in out else 0)
            out[channel.topic] = TopicInfo(channel.topic, channel.msgtype, count, channel.encoding)
        return out

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        _, walk = self._scan(self.path, set(topics))
        return walk

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        _, walk = self._scan(self.path, set(topics))
        for batch in walk:
            yield from batch.messages()


class Sqlite3Log(LogReader):
    """rosbag2 sqlite3 storage files read directly: a lone ``.db3`` file, the storage of a
    rosbag2 directory, or one whose ``metadata.yaml`` is missing or unreadable. A file SQLite
    cannot read (cut off, damaged) is read page by page instead
    (:func:`~imucal_cli.io.salvage.scan_sqlite_rows`)."""

    format_name = "rosbag2-sqlite3"

    def __init__(self, path: Path, files: list[Path], why: str = "", count: bool = True) -> None:
        super().__init__(path)
        self.files = files
        self._count_rows = count  # False where metadata.yaml has the counts: no table scan
        if why:
            self.format_name = "rosbag2-sqlite3 (storage read directly)"
        self._topics: dict[str, TopicInfo] = {}
        self._salvaged: dict[Path, tuple[dict[int, tuple[str, str, str]], list[tuple[int, int, int, bytes]]]] = {}
        for db in files:
            try:
                rows, counts = self._query_topics(db, self._count_rows)
            except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
                try:
                    topics, losses, messages = scan_sqlite_rows(db)
                except (OSError, ValueError) as scan_exc:
                    raise LogError(str(db), f"cannot read rosbag2 sqlite3 storage: {exc}; {scan_exc}") from None
                if not topics:
                    raise LogError(str(db), f"cannot read rosbag2 sqlite3 storage: {exc}; no topic could be recovered") from None
                self.format_name = "rosbag2-sqlite3 (recovered)"
                self.losses.append(Loss(f"{db.name}: SQLite cannot read it ({exc}); its pages were read directly", 0, 0, lost=False))
                self.losses.extend(losses)
                self._salvaged[db] = (topics, messages)
                rows = [(tid, name, msgtype, fmt) for tid, (name, msgtype, fmt) in topics.items()]
                counts = {}
                for _, tid, _, _ in messages:
                    counts[tid] = counts.get(tid, 0) + 1
            for tid, name, msgtype, fmt in rows:
                count = int(counts.get(tid, 0)) + (self._topics[name].count if name in self._topics else 0)
                self._topics[name] = TopicInfo(name, msgtype, count, fmt)

    @staticmethod
    def _query_topics(db: Path, count: bool) -> tuple[list[tuple[int, str, str, str]], dict[int, int]]:
        connection = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        connection.text_factory = lambda raw: raw.decode("utf-8", errors="replace")  # damaged text stays readable
        try:
            rows = connection.execute("SELECT id, name, type, serialization_format FROM topics").fetchall()
            counts = dict(connection.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id").fetchall()) if count else {}
        finally:
            connection.close()
        return rows, counts

    def topics(self) -> dict[str, TopicInfo]:
        return dict(self._topics)

    def fast_batches(self, topics: Iterable[str]) -> Iterator[RawBatch] | None:
        wanted = set(topics)

        def generate() -> Iterator[RawBatch]:
            for db in self.files:
                if db not in self._salvaged:
                    yield from sqlite_batches([db], wanted, losses=self.losses)
                    continue
                names, messages = self._salvaged[db]
                ids = {tid: name for tid, (name, _, fmt) in names.items() if name in wanted and fmt == "cdr"}
                for tid, name in ids.items():
                    picked = [(stamp, blob) for _, t, stamp, blob in messages if t == tid]
                    if not picked:
                        continue
                    buffer, starts, lengths = pack_blobs([b for _, b in picked])
                    yield RawBatch(name, "cdr", buffer, starts, lengths, np.array([t for t, _ in picked], dtype=np.int64))

        return generate()

    def iter_raw(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        batches = self.fast_batches(topics)
        assert batches is not None
        for batch in batches:
            yield from batch.messages()


def _storage_directly(path: Path, why: str) -> LogReader | None:
    """A rosbag2 directory without usable metadata: its storage files, read directly."""
    dbs = sorted(path.glob("*.db3"))
    mcaps = sorted(path.glob("*.mcap"))
    if dbs:
        reader: LogReader = Sqlite3Log(path, dbs, why)
    elif len(mcaps) == 1:
        reader = _open_mcap(mcaps[0])
    else:
        return None
    reader.losses.insert(0, Loss(f"metadata.yaml unusable ({why.removeprefix(str(path) + ': ')}); storage files read directly", 0, 0, lost=False))
    return reader


def _open_mcap(path: Path) -> LogReader:
    try:
        return McapLog(path)
    except _NeedsSalvage as exc:
        return SalvageLog(path, "mcap", str(exc))


def detect_format(path: Path) -> str:
    """``mcap``, ``rosbag2`` or ``rosbag1`` from the path (and its first bytes)."""
    if path.is_dir():
        return "rosbag2"
    suffix = path.suffix.lower()
    if suffix == ".mcap":
        return "mcap"
    if suffix == ".bag":
        return "rosbag1"
    if suffix == ".db3":
        return "rosbag2"
    try:
        with path.open("rb") as handle:
            head = handle.read(16)
    except OSError as exc:
        raise LogError(str(path), f"cannot open: {exc.strerror}") from None
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(ROSBAG1_MAGIC):
        return "rosbag1"
    if head.startswith(SQLITE_MAGIC):
        return "rosbag2"
    raise LogError(
        str(path), "unknown log format (expected .mcap, .bag, a rosbag2 directory or .db3)"
    )


def open_log(path: str | Path) -> LogReader:
    """Open a log for reading, picking the reader from the path. Raises :class:`LogError`."""
    path = Path(path)
    if not path.exists():
        raise LogError(str(path), "no such file or directory")
    kind = detect_format(path)
    if kind == "mcap":
        return _open_mcap(path)
    if kind == "rosbag1":
        try:
            return Ros1Log(path)
        except Exception as exc:  # noqa: BLE001 - unindexed, cut off or damaged: walk it
            return SalvageLog(path, "rosbag1", f"its index cannot be used ({exc})")
    if path.is_file():  # a lone .db3 storage file
        return Sqlite3Log(path, [path])
    try:
        return Rosbag2Log(path)
    except Exception:  # noqa: BLE001 - compressed, or metadata the generic reader must judge
        pass
    try:
        return RosbagsLog(path, ros1=False)
    except LogError as exc:
        direct = _storage_directly(path, str(exc))
        if direct is None:
            raise
        return direct


# --------------------------------------------------------------------------- decoding


@dataclass(frozen=True)
class ImuSample:
    stamp_ns: int
    frame_id: str
    gyro: tuple[float, float, float]
    accel: tuple[float, float, float]


class ImuDecoder:
    """Decode serialized ``sensor_msgs/Imu`` with the ``rosbags`` deserializers."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self._ros2 = get_typestore(Stores.ROS2_HUMBLE)
        self._ros1 = get_typestore(Stores.ROS1_NOETIC)

    def decoder(self, encoding: str) -> Callable[[bytes], ImuSample]:
        if encoding == "cdr":
            deserialize = self._ros2.deserialize_cdr
        elif encoding == "ros1":
            deserialize = self._ros1.deserialize_ros1
        else:
            raise ValueError(f"unsupported message encoding {encoding!r}")

        def decode(data: bytes) -> ImuSample:
            msg = deserialize(data, IMU_MSGTYPE)
            stamp = msg.header.stamp
            w = msg.angular_velocity
            a = msg.linear_acceleration
            return ImuSample(
                int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
                msg.header.frame_id,
                (w.x, w.y, w.z),
                (a.x, a.y, a.z),
            )

        return decode


@dataclass
class ReadStats:
    """What reading one topic found and did. Nothing is dropped without being counted here."""

    messages: int = 0  # messages read from the log
    zero_stamps: int = 0  # header.stamp was zero: log time used instead
    backwards: int = 0  # stamp earlier than the previous message's (in log order): sorted
    duplicates: int = 0  # stamp equal to an earlier one: removed (the first is kept)
    decode_errors: int = 0  # messages that could not be deserialized: skipped
    non_finite: int = 0  # a NaN or infinite gyro or accelerometer value: dropped
    saturated: int = 0  # a gyro or accelerometer axis clipped at its range: dropped
    clock_jumps: int = 0  # stamps leaping by more than CLOCK_JUMP_S (forwards or back)
    gaps: int = 0  # steps over GAP_MEDIAN_PERIODS median periods: windows spanning them are not used
    implausible: int = 0  # values no IMU measures (|gyro| > 100 rad/s, |accel| > 2000 m/s^2): dropped
    stamp_outliers: int = 0  # a lone stamp far from both neighbours (a damaged message): dropped
    frame_ids: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "messages": self.messages,
            "zero_stamps": self.zero_stamps,
            "backwards": self.backwards,
            "duplicates": self.duplicates,
            "decode_errors": self.decode_errors,
            "non_finite": self.non_finite,
            "saturated": self.saturated,
            "clock_jumps": self.clock_jumps,
            "gaps": self.gaps,
            "implausible": self.implausible,
            "stamp_outliers": self.stamp_outliers,
        }


@dataclass(frozen=True)
class ImuRead:
    stream: ImuStream
    stats: ReadStats
    log_time_ns: np.ndarray  # log (receive) time of each kept sample, same order as the stream


def _finish_topic(
    stamps: list[int], log_times: list[int], gyro: list[Any], accel: list[Any], stats: ReadStats
) -> ImuRead:
    # imported here: reading needs no scipy (imucal_cli.types imports scipy.spatial), so the
    # CLI can start the reader before the math's imports
    from imucal_cli.types import ImuStream

    t_ns = np.asarray(stamps, dtype=np.int64)
    log_ns = np.asarray(log_times, dtype=np.int64)
    gyro_arr = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    accel_arr = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
    steps = np.diff(t_ns)
    stats.backwards = int(np.count_nonzero(steps < 0))
    if len(t_ns) < 2 or np.all(steps > 0):  # the usual case: already sorted, no duplicates
        frame_id = stats.frame_ids[0] if stats.frame_ids else ""
        return ImuRead(ImuStream(t_ns, gyro_arr, accel_arr, frame_id), stats, log_ns)
    order = np.argsort(t_ns, kind="stable")
    t_sorted = t_ns[order]
    keep = np.ones(len(t_sorted), dtype=bool)
    if len(t_sorted) > 1:
        keep[1:] = np.diff(t_sorted) != 0
    stats.duplicates = int(np.count_nonzero(~keep))
    index = order[keep]
    frame_id = stats.frame_ids[0] if stats.frame_ids else ""
    stream = ImuStream(t_ns[index], gyro_arr[index], accel_arr[index], frame_id)
    return ImuRead(stream, stats, log_ns[index])


class _TopicColumns:
    """Decoded samples of one topic, copied batch by batch into columns made for the number of
    messages the container's index gives (grown when it gave too few): the copies happen while
    the reader's threads decode the next batches, not all at the end."""

    #: Largest number of samples made room for at once from an index's word (a damaged index
    #: could claim any number).
    MAX_PREALLOCATED = 1 << 24

    def __init__(self, expected: int = 0) -> None:
        self.size = 0
        n = max(0, min(int(expected), self.MAX_PREALLOCATED))
        self.stamps = np.empty(n, dtype=np.int64)
        self.log_times = np.empty(n, dtype=np.int64)
        self.gyro = np.empty((n, 3))
        self.accel = np.empty((n, 3))
        self.stats = ReadStats()

    def add(self, stamps: np.ndarray, log_times: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        end = self.size + len(stamps)
        if end > len(self.stamps):
            room = max(end, 2 * len(self.stamps), 1024)
            for name in ("stamps", "log_times", "gyro", "accel"):
                old = getattr(self, name)
                grown = np.empty((room, *old.shape[1:]), dtype=old.dtype)
                grown[: self.size] = old[: self.size]
                setattr(self, name, grown)
        self.stamps[self.size : end] = stamps
        self.log_times[self.size : end] = log_times
        self.gyro[self.size : end] = gyro
        self.accel[self.size : end] = accel
        self.size = end

    def finish(self) -> ImuRead:
        n = self.size
        stamps, log_times, gyro, accel = self.stamps[:n], self.log_times[:n], self.gyro[:n], self.accel[:n]
        if n > 1 and np.any(np.diff(log_times) < 0):  # log order, for the backwards count
            order = np.argsort(log_times, kind="stable")
            stamps, log_times, gyro, accel = stamps[order], log_times[order], gyro[order], accel[order]
        return _finish_topic(stamps, log_times, gyro, accel, self.stats)


def _check_topics(log: LogReader, wanted: list[str]) -> dict[str, TopicInfo]:
    available = log.topics()
    for topic in wanted:
        if topic not in available:
            imu_topics = sorted(t for t, info in available.items() if info.is_imu)
            listing = ", ".join(imu_topics) if imu_topics else "none"
            raise log.error(f"topic not found; the log's IMU topics are: {listing}", topic)
        info = available[topic]
        if not info.is_imu:
            raise log.error(f"has type {info.msgtype}, expected {IMU_MSGTYPE}", topic)
    return available


class _LazyDecoders:
    """Generic per-message decoders, made (rosbags typestores are slow to build) on first use."""

    def __init__(self, encodings: dict[str, str]) -> None:
        self.encodings = encodings
        self._made: dict[str, Callable[[bytes], ImuSample]] = {}
        self._decoder: ImuDecoder | None = None

    def __getitem__(self, topic: str) -> Callable[[bytes], ImuSample]:
        if topic not in self._made:
            if self._decoder is None:
                self._decoder = ImuDecoder()
            self._made[topic] = self._decoder.decoder(self.encodings[topic])
        return self._made[topic]


#: A step between consecutive stamps of one topic longer than this (s) is a clock jump.
CLOCK_JUMP_S = 60.0
#: Smallest magnitude a run of identical extreme samples must have to be called clipped: a
#: gyro past 2 rad/s or an accelerometer past 1.5 g is beyond vehicle motion and at the range
#: of common MEMS parts (+-125 deg/s and up, +-2 g and up).
SATURATION_GYRO_RADPS = 2.0
#: Beyond these no IMU measures: such values are damaged data, dropped and counted.
IMPLAUSIBLE_GYRO_RADPS = 100.0
IMPLAUSIBLE_ACCEL_MPS2 = 2000.0
SATURATION_ACCEL_MPS2 = 1.5 * 9.80665
#: A value repeated this many samples in a row at its batch's extreme is clipped.
SATURATION_RUN = 3


def _stamp_outliers(stamps: np.ndarray) -> np.ndarray:
    """Runs of stamps that leap more than ``CLOCK_JUMP_S`` away and come back within the batch
    (to within ``CLOCK_JUMP_S`` of where they left): damaged stamps (a flipped bit, copied along
    by the compressor), not a clock jump, after which the stamps stay moved."""
    out = np.zeros(len(stamps), dtype=bool)
    if len(stamps) < 2:
        return out
    jump = CLOCK_JUMP_S * 1e9
    t = stamps.astype(np.float64)
    leaps = np.flatnonzero(np.abs(np.diff(t)) > jump)  # a leap between k and k + 1
    if len(leaps) and leaps[0] == 0 and np.all(np.abs(t[1:] - t[0]) > jump):
        out[0] = True  # the first stamp alone is off: no later stamp comes near it
        leaps = leaps[1:]
    k = 0
    while k < len(leaps):
        start = leaps[k]
        back = next((j for j in leaps[k + 1 :] if abs(t[j + 1] - t[start]) <= jump), None)
        if back is None:  # a clock jump: the stamps stay moved; later runs may still come back
            k += 1
            continue
        out[start + 1 : back + 1] = True
        k = int(np.searchsorted(leaps, back)) + 1
    return out


def _clipped(values: np.ndarray, floor: float) -> np.ndarray:
    """Rows where some axis sits at the batch's extreme magnitude (at least ``floor``) for
    ``SATURATION_RUN`` or more samples in a row: what a sensor at the end of its range outputs."""
    out = np.zeros(len(values), dtype=bool)
    if len(values) < SATURATION_RUN:
        return out
    # the largest magnitude per axis, column by column (numpy reduces an (n, 3) array over its
    # long axis seven times slower than three columns one at a time)
    extreme = np.array([max(-float(column.min()), float(column.max())) for column in values.T])
    for axis in np.flatnonzero(extreme >= floor):
        at = np.abs(values[:, axis]) == extreme[axis]
        if np.count_nonzero(at) < SATURATION_RUN:
            continue  # too few samples at the extreme for a run
        run = np.convolve(at.astype(np.int64), np.ones(SATURATION_RUN, dtype=np.int64), mode="valid") == SATURATION_RUN
        for k in range(SATURATION_RUN):
            out[k : k + len(run)] |= run
    return out


class ImuBatches:
    """Decoded ``sensor_msgs/Imu`` batches of a log, in the container's order, without holding
    the whole log: ``(topic, stamp_ns, log_time_ns, gyro, accel)`` per batch (stamps that are
    zero replaced by the log time). What was read is counted in :attr:`stats`."""

    def __init__(self, path: str | Path, topics: Iterable[str], fast: bool = True) -> None:
        self.path = Path(path)
        self.topics = list(dict.fromkeys(topics))
        self.fast = fast
        self.stats = {t: ReadStats() for t in self.topics}
        #: What of the log could not be read (damaged or cut-off parts), after iterating.
        self.losses: list[Loss] = []
        #: The container as opened (``"mcap (recovered)"`` where it had to be walked).
        self.format_name = ""
        self._last_stamp: dict[str, int] = {}
        self._reached: dict[str, int] = {}  # per topic: the latest stamp kept so far
        self._period: dict[str, float] = {}  # per topic: median step between stamps (ns)
        #: Per topic, the number of messages the container says it has (once iterating).
        self.expected: dict[str, int] = {}

    def _screen(self, topic: str, stamps: np.ndarray, log_times: np.ndarray, gyro: np.ndarray, accel: np.ndarray):  # noqa: ANN202
        """Drop (and count) samples with non-finite, implausible or clipped values and damaged
        stamps. The common case (nothing to drop) costs a few whole-batch reductions."""
        st = self.stats[topic]
        zero = stamps == 0
        if zero.any():
            st.zero_stamps += int(np.count_nonzero(zero))
            stamps = np.where(zero, log_times, stamps)
        if not len(stamps):
            return stamps, log_times, gyro, accel
        jump = int(CLOCK_JUMP_S * 1e9)
        reached_before = self._reached.get(topic, -(2**62))
        # whole-array extremes (a NaN anywhere makes them NaN, and the comparisons False)
        g_lo, g_hi, a_lo, a_hi = float(gyro.min()), float(gyro.max()), float(accel.min()), float(accel.max())
        values_ok = (
            -SATURATION_GYRO_RADPS < g_lo and g_hi < SATURATION_GYRO_RADPS
            and -SATURATION_ACCEL_MPS2 < a_lo and a_hi < SATURATION_ACCEL_MPS2
        )
        low, high = int(stamps.min()), int(stamps.max())
        # no step can leap by more than `jump` when the whole batch spans less than that
        narrow = high - low <= jump
        stamps_ok = (narrow or bool(np.abs(np.diff(stamps)).max() <= jump)) and low >= reached_before - jump
        quiet = narrow and low >= reached_before - jump  # nothing leaps, nothing falls behind
        if values_ok and stamps_ok:
            self._reached[topic] = max(reached_before, high)
            return stamps, log_times, gyro, accel
        # values past the saturation floors but finite and plausible, stamps quiet (a lively
        # sensor): only a clipped run could be dropped, and there is none in the usual case
        plausible = (
            -IMPLAUSIBLE_GYRO_RADPS <= g_lo and g_hi <= IMPLAUSIBLE_GYRO_RADPS
            and -IMPLAUSIBLE_ACCEL_MPS2 <= a_lo and a_hi <= IMPLAUSIBLE_ACCEL_MPS2
        )  # and finite: a NaN anywhere makes the extremes NaN, and the comparisons False
        if quiet and plausible and not (_clipped(gyro, SATURATION_GYRO_RADPS).any() or _clipped(accel, SATURATION_ACCEL_MPS2).any()):
            self._reached[topic] = max(reached_before, high)
            return stamps, log_times, gyro, accel
        finite = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        bad = ~finite
        st.non_finite += int(np.count_nonzero(bad))
        with np.errstate(invalid="ignore"):
            absurd = finite & ((np.abs(gyro) > IMPLAUSIBLE_GYRO_RADPS).any(axis=1) | (np.abs(accel) > IMPLAUSIBLE_ACCEL_MPS2).any(axis=1))
        st.implausible += int(np.count_nonzero(absurd))
        bad |= absurd
        finite &= ~absurd
        outlier = _stamp_outliers(stamps)
        # stamps that leap back by minutes or more behind what this topic already reached
        # cannot be placed in time: dropped (a forward leap is kept: time moves on)
        running = np.maximum(np.maximum.accumulate(np.where(outlier, -(2**62), stamps)), reached_before)
        behind = ~outlier & (stamps < running - jump)
        if (~outlier).any():
            self._reached[topic] = max(reached_before, int(stamps[~outlier].max()))
        st.stamp_outliers += int(np.count_nonzero((outlier | behind) & ~bad))
        st.clock_jumps += int(np.count_nonzero(np.diff(np.concatenate([[0], behind.astype(np.int8)])) == 1))
        bad |= outlier | behind
        clipped = np.zeros(len(stamps), dtype=bool)
        if finite.any():
            clipped[finite] = _clipped(gyro[finite], SATURATION_GYRO_RADPS) | _clipped(accel[finite], SATURATION_ACCEL_MPS2)
        st.saturated += int(np.count_nonzero(clipped))
        bad |= clipped
        if bad.any():
            keep = ~bad
            return stamps[keep], log_times[keep], gyro[keep], accel[keep]
        return stamps, log_times, gyro, accel

    def _count(self, topic: str, stamps: np.ndarray, log_times: np.ndarray, frame_ids: list[str]) -> np.ndarray:
        st = self.stats[topic]
        if len(stamps):
            previous = self._last_stamp.get(topic)
            steps = np.diff(stamps if previous is None else np.concatenate([[previous], stamps]))
            st.backwards += int(np.count_nonzero(steps < 0))
            jumps = np.abs(steps) > CLOCK_JUMP_S * 1e9
            st.clock_jumps += int(np.count_nonzero(jumps))
            period = self._period.get(topic)
            if period is None:  # the topic's median period, from its first batch long enough
                positive = steps[steps > 0]
                if len(positive) >= 10:
                    period = self._period[topic] = float(np.median(positive))
            if period is not None:
                st.gaps += int(np.count_nonzero((steps > GAP_MEDIAN_PERIODS * period) & ~jumps))
            self._last_stamp[topic] = int(stamps[-1])
        for name in frame_ids:
            if name not in st.frame_ids:
                st.frame_ids.append(name)
        return stamps

    def __iter__(self) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        with open_log(self.path) as log:
            self.format_name = log.format_name
            try:
                yield from self._read(log)
            finally:
                self.losses = list(log.losses)

    def _read(self, log: LogReader) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        available = _check_topics(log, self.topics)
        self.expected = {t: available[t].count for t in self.topics}
        decoders = _LazyDecoders({t: available[t].encoding for t in self.topics})
        batches = log.fast_batches(self.topics) if self.fast else None
        if batches is not None:
            try:
                for batch in batches:
                    self.stats[batch.topic].messages += len(batch.starts)
                    decoded = batch.decoded if batch.decoded is not None else decode_imu(batch)
                    parts = [(decoded.stamp_ns, decoded.log_time_ns, decoded.gyro, decoded.accel, decoded.frame_ids)]
                    for i in decoded.undecoded:  # what the layout check did not recognise
                        start, length = int(batch.starts[i]), int(batch.lengths[i])
                        one = self._decode_one(batch.topic, decoders[batch.topic], bytes(batch.buffer[start : start + length]), int(batch.log_time_ns[i]))
                        if one is not None:
                            parts.append(one)
                    for stamps, log_times, gyro, accel, frames in parts:
                        stamps, log_times, gyro, accel = self._screen(batch.topic, stamps, log_times, gyro, accel)
                        yield batch.topic, self._count(batch.topic, stamps, log_times, frames), log_times, gyro, accel
            except LogError:
                raise
            except Exception as exc:  # noqa: BLE001 - a damaged container: say so, naming the file
                raise log.error(f"cannot read messages: {exc}") from None
            return
        pending: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]]] = {t: [] for t in self.topics}
        count = 0
        for topic, log_time_ns, data in log.iter_raw(self.topics):
            self.stats[topic].messages += 1
            one = self._decode_one(topic, decoders[topic], data, log_time_ns)
            if one is not None:
                pending[topic].append(one)
            count += 1
            if count % 4096 == 0:
                yield from self._flush(pending)
        yield from self._flush(pending)

    def _flush(self, pending: dict[str, list]) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        for topic, items in pending.items():
            if not items:
                continue
            stamps = np.concatenate([i[0] for i in items])
            log_times = np.concatenate([i[1] for i in items])
            frames = [f for i in items for f in i[4]]
            gyro, accel = np.concatenate([i[2] for i in items]), np.concatenate([i[3] for i in items])
            stamps, log_times, gyro, accel = self._screen(topic, stamps, log_times, gyro, accel)
            stamps = self._count(topic, stamps, log_times, list(dict.fromkeys(frames)))
            yield topic, stamps, log_times, gyro, accel
            items.clear()

    def _decode_one(self, topic: str, decode: Callable[[bytes], ImuSample], data: bytes, log_time_ns: int):  # noqa: ANN202
        try:
            sample = decode(data)
        except Exception:  # noqa: BLE001 - counted, never silently kept
            self.stats[topic].decode_errors += 1
            return None
        return (
            np.array([sample.stamp_ns], dtype=np.int64),
            np.array([log_time_ns], dtype=np.int64),
            np.array([sample.gyro], dtype=np.float64),
            np.array([sample.accel], dtype=np.float64),
            [sample.frame_id],
        )


def start_reading(log: str | Path, topics: list[str]) -> tuple[ImuBatches, Iterator[Any]]:
    """Start reading ``topics`` of ``log`` ahead in a child process, for
    :func:`imucal_cli.api.stream_log`'s ``reading``. Importing this module needs no scipy, so
    a caller can start the reader before the math's imports (about a second); the ``imucal``
    command starts it earlier still, before numpy (:mod:`imucal_cli.launch`)."""
    from imucal_cli.io.prefetch import read_ahead

    reader = ImuBatches(Path(log), topics)
    return reader, read_ahead(reader)


def read_imu(
    path: str | Path,
    topics: Iterable[str],
    progress: Callable[[int], None] | None = None,
    fast: bool = True,
    losses: list[Loss] | None = None,
) -> dict[str, ImuRead]:
    """Read ``sensor_msgs/Imu`` topics of a log into one :class:`ImuRead` per topic.

    With ``fast`` (the default) messages are decoded in bulk from the container's indexes
    (:mod:`imucal_cli.io.fastimu`), bit-exact with the generic path, which is used for what the
    fast path does not recognise and with ``fast=False``.

    Raises
    ------
    LogError
        The log cannot be read, a topic is missing (the message lists the IMU topics the
        log has) or a topic is not ``sensor_msgs/Imu``.
    """
    reader = ImuBatches(path, topics, fast=fast)
    columns: dict[str, _TopicColumns] = {}
    count = 0
    for topic, stamps, log_times, gyro, accel in reader:
        if topic not in columns:  # made once the reader knows the counts its index gives
            columns[topic] = _TopicColumns(reader.expected.get(topic, 0))
        columns[topic].add(stamps, log_times, gyro, accel)
        count += len(stamps)
        if progress is not None:
            progress(count)
    if losses is not None:
        losses.extend(reader.losses)
    out = {}
    for topic in reader.topics:
        stats = reader.stats[topic]
        stats.backwards = 0  # recounted in log order by finish()
        column = columns.get(topic) or _TopicColumns()
        column.stats = stats
        out[topic] = column.finish()
    return out


# --------------------------------------------------------------------------- inspect


@dataclass(frozen=True)
class TopicTiming:
    """Timing of one topic, as ``imucal inspect`` reports it (seconds since ``t0_ns``)."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float
    duration_s: float
    gaps: list[tuple[float, float]]
    backwards: int
    duplicates: int
    time_source: str  # "header.stamp" or "log_time"


@dataclass(frozen=True)
class LogSummary:
    path: str
    format_name: str
    t0_ns: int
    topics: list[TopicTiming]
    losses: list[Loss] = field(default_factory=list)


#: A gap is a step between consecutive stamps longer than this many median periods.
GAP_MEDIAN_PERIODS = 5.0


def _timing(
    topic: str, msgtype: str, stamps_in_log_order: np.ndarray, t0_ns: int, time_source: str
) -> TopicTiming:
    n = len(stamps_in_log_order)
    if n == 0:
        return TopicTiming(topic, msgtype, 0, 0.0, 0.0, [], 0, 0, time_source)
    backwards = int(np.count_nonzero(np.diff(stamps_in_log_order) < 0))
    t_sorted = np.sort(stamps_in_log_order)
    steps = np.diff(t_sorted)
    duplicates = int(np.count_nonzero(steps == 0))
    positive = steps[steps > 0]
    median = float(np.median(positive)) if len(positive) else 0.0
    rate = 1e9 / median if median > 0 else 0.0
    gaps: list[tuple[float, float]] = []
    if median > 0:
        for i in np.flatnonzero(steps > GAP_MEDIAN_PERIODS * median):
            gaps.append(
                (float(t_sorted[i] - t0_ns) * 1e-9, float(t_sorted[i + 1] - t0_ns) * 1e-9)
            )
    duration = float(t_sorted[-1] - t_sorted[0]) * 1e-9
    return TopicTiming(topic, msgtype, n, rate, duration, gaps, backwards, duplicates, time_source)


def summarize_log(path: str | Path) -> LogSummary:
    """Per topic: type, count, median rate, duration, gaps, backwards jumps, duplicates.

    IMU topics are timed by ``header.stamp`` (log time where it is zero), others by log time.
    """
    path = Path(path)
    with open_log(path) as log:
        available = log.topics()
        decoder = ImuDecoder()
        decoders = {
            t: decoder.decoder(info.encoding)
            for t, info in available.items()
            if info.is_imu and info.encoding in ("cdr", "ros1")
        }
        stamps: dict[str, list[int]] = {t: [] for t in available}
        for topic, log_time_ns, data in log.iter_raw(list(available)):
            stamp = log_time_ns
            if topic in decoders:
                try:
                    stamp = decoders[topic](data).stamp_ns or log_time_ns
                except Exception:
                    continue
            stamps[topic].append(stamp)
        format_name = log.format_name
        losses = list(log.losses)
    arrays = {t: np.asarray(s, dtype=np.int64) for t, s in stamps.items()}
    firsts = [int(a.min()) for a in arrays.values() if len(a)]
    t0_ns = min(firsts) if firsts else 0
    timings = [
        _timing(
            topic,
            available[topic].msgtype,
            arrays[topic],
            t0_ns,
            "header.stamp" if topic in decoders else "log_time",
        )
        for topic in sorted(available)
    ]
    return LogSummary(str(path), format_name, t0_ns, timings, losses)
