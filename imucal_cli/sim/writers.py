"""Writing ``sensor_msgs/Imu`` logs in every format imucal reads (for the simulator and tests).

Messages are serialised in bulk (:mod:`imucal_cli.sim.serialize`, byte-identical with the
``rosbags`` serialisers), containers are written by the ``mcap`` writer (plain MCAP) and the
``rosbags`` writers (rosbag2 sqlite3/mcap, ROS 1 bag).
"""

from __future__ import annotations

import heapq
import itertools
import shutil
import sqlite3
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.errors import InputError
from imucal_cli.io.formats import FORMATS as LOG_FORMATS
from imucal_cli.io.formats import by_suffix
from imucal_cli.io.imu_msg import IMU_MSGTYPE
from imucal_cli.paths import refuse_existing
from imucal_cli.sim.serialize import serialize_cdr, serialize_ros1
from imucal_cli.types import ImuStream, Transform

#: ``--format`` names (:data:`imucal_cli.io.formats.FORMATS`).
FORMATS = tuple(LOG_FORMATS)
#: What an SQLite URI reads as its own: a query, a fragment, an escape.
_URI_CHARACTERS = frozenset("#?%")


def format_for(out: Path, fmt: str | None) -> str:
    """The format to write ``out`` in: ``fmt``, else the one its suffix names (a rosbag2
    folder where it names none); an error where the two disagree."""
    suffix = out.suffix.lower()
    if fmt is None:
        fmt = getattr(by_suffix(suffix), "name", "rosbag2-sqlite3")
    expected = LOG_FORMATS[fmt].suffix
    if expected is not None and suffix != expected:
        raise InputError(f"{out}: format {fmt} writes a {expected} file; name OUT with that suffix")
    if expected is None and suffix in {".mcap", ".bag"}:
        raise InputError(
            f"{out}: format {fmt} writes a rosbag2 directory; name OUT without {suffix}"
        )
    return fmt


Progress = Callable[[int, int | None], None]
#: Static transforms to write on ``/tf_static``: ``(parent, child, T_parent_child)``.
StaticTransforms = Sequence[tuple[str, str, Transform]]


def _first_ns(topics: Mapping[str, TopicData]) -> int:
    """The log time of the log's first message."""
    return min(
        int((d.stream.t_ns if d.log_time_ns is None else d.log_time_ns).min())
        for d in topics.values()
    )


#: The pieces of a log written as they are made (each topics' data), and their messages' total
#: where known.
Pieces = tuple[Iterable[Mapping[str, "TopicData"]], int | None]
#: A message written once at the log's start: (topic, msgtype, serialised).
Static = tuple[str, str, bytes]


def _statics(
    tf_static: StaticTransforms,
    description: str | None,
    topics: Mapping[str, TopicData],
    ros1: bool,
) -> list[Static]:
    """``tf_static`` as one ``TFMessage`` on /tf_static and ``description`` as a
    ``std_msgs/String`` on /robot_description (where given), stamped at the first message."""
    from imucal_cli.frames import DESCRIPTION_TOPIC, TF_MSGTYPES, TF_TOPIC, tf_message, tf_typestore

    if not tf_static and description is None:
        return []
    store = tf_typestore(ros1)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    out = []
    if tf_static:
        message = tf_message(store, list(tf_static), _first_ns(topics))
        out.append((TF_TOPIC, TF_MSGTYPES[0], bytes(serialize(message, TF_MSGTYPES[0]))))
    if description is not None:
        kind = "std_msgs/msg/String"
        text = bytes(serialize(store.types[kind](data=description), kind))
        out.append((DESCRIPTION_TOPIC, kind, text))
    return out


@dataclass(frozen=True)
class TopicData:
    """One IMU topic to write: the samples and the time each reached the recorder."""

    stream: ImuStream
    log_time_ns: np.ndarray | None = None  # defaults to the stamps


def _serialised_messages(
    pieces: Iterable[Mapping[str, TopicData]],
    ros1: bool,
    progress: Progress | None,
    total: int | None,
) -> Iterator[tuple[int, str, bytes]]:
    """``(log_time_ns, topic, serialised message)`` of every piece in turn (a long drive, made
    and written piece by piece), each merged in log-time order; ``progress`` told (written,
    ``total``: None where not known) every 10,000 messages."""
    count = 0
    for piece in pieces:
        blob = _Serialized(piece, ros1)
        for log_ns, topic, i in _merged(piece):
            count += 1
            if progress is not None and (count % 10_000 == 0 or count == total):
                progress(count, total)
            yield log_ns, topic, blob(topic, i)


def _merged(topics: Mapping[str, TopicData]) -> Iterator[tuple[int, str, int]]:
    def one(topic: str, data: TopicData) -> Iterator[tuple[int, str, int]]:
        log_ns = data.stream.t_ns if data.log_time_ns is None else data.log_time_ns
        order = np.argsort(log_ns, kind="stable")
        for i in order:
            yield int(log_ns[i]), topic, int(i)

    return heapq.merge(*(one(t, d) for t, d in topics.items()))


def _msgdef(ros1: bool) -> tuple[str, object]:
    """The message definition text and the rosbags typestore for the encoding."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    text, _ = typestore.generate_msgdef(IMU_MSGTYPE, ros_version=1 if ros1 else 2)
    return text, typestore


class _Serialized:
    """The messages of every topic, serialised in bulk a block of :data:`SERIAL_BLOCK` at a
    time as the writer asks for them (all at once: 0.7 GB an hour of five IMUs), the last two
    blocks of each topic kept (log-time order reaches back across a block's edge)."""

    def __init__(self, topics: Mapping[str, TopicData], ros1: bool) -> None:
        self.topics, self.serialize = topics, serialize_ros1 if ros1 else serialize_cdr
        self.blocks: dict[str, dict[int, np.ndarray]] = {topic: {} for topic in topics}

    def __call__(self, topic: str, i: int) -> bytes:
        block, kept = i // SERIAL_BLOCK, self.blocks[topic]
        if block not in kept:
            stream, start = self.topics[topic].stream, block * SERIAL_BLOCK
            part = slice(start, start + SERIAL_BLOCK)
            kept[block] = self.serialize(
                ImuStream(stream.t_ns[part], stream.gyro[part], stream.accel[part], stream.frame_id)
            )
            for old in [b for b in kept if b < block - 1]:
                del kept[old]
        return bytes(kept[block][i - block * SERIAL_BLOCK])


#: Messages serialised at a time by the writers.
SERIAL_BLOCK = 8192


def _write_mcap(
    path: Path,
    topics: Mapping[str, TopicData],
    ros1: bool,
    compression: str = "zstd",
    chunk_size: int = 1024 * 1024,
    progress: Progress | None = None,
    statics: Sequence[Static] = (),
    pieces: Pieces | None = None,
) -> None:
    """``topics`` (the first piece's, where ``pieces`` holds every piece and their messages'
    total) to an MCAP file at ``path``."""
    from mcap.writer import CompressionType, Writer

    msgdef, _ = _msgdef(ros1)
    every, total = pieces or ([topics], sum(len(d.stream) for d in topics.values()))
    with path.open("wb") as handle:
        writer = Writer(
            handle, compression=CompressionType[compression.upper()], chunk_size=chunk_size
        )
        writer.start(profile="ros1" if ros1 else "ros2", library="imucal")
        schema_id = writer.register_schema(
            name="sensor_msgs/Imu" if ros1 else IMU_MSGTYPE,
            encoding="ros1msg" if ros1 else "ros2msg",
            data=msgdef.encode(),
        )
        channels = {
            topic: writer.register_channel(
                topic=topic, message_encoding="ros1" if ros1 else "cdr", schema_id=schema_id
            )
            for topic in topics
        }
        for static in statics:
            _mcap_static(writer, static, _first_ns(topics), ros1)
        sequence = dict.fromkeys(topics, 0)
        for log_ns, topic, data in _serialised_messages(every, ros1, progress, total):
            writer.add_message(
                channel_id=channels[topic],
                log_time=log_ns,
                data=data,
                publish_time=log_ns,
                sequence=sequence[topic],
            )
            sequence[topic] += 1
        writer.finish()


def _mcap_static(writer: Any, static: Static, stamp: int, ros1: bool) -> None:
    """One message written once into an MCAP writer: its schema, channel and message."""
    from imucal_cli.frames import tf_typestore

    topic, msgtype, data = static
    text, _ = tf_typestore(ros1).generate_msgdef(msgtype, ros_version=1 if ros1 else 2)
    schema = writer.register_schema(
        name=msgtype.replace("/msg/", "/") if ros1 else msgtype,
        encoding="ros1msg" if ros1 else "ros2msg",
        data=text.encode(),
    )
    channel = writer.register_channel(
        topic=topic, message_encoding="ros1" if ros1 else "cdr", schema_id=schema
    )
    writer.add_message(channel_id=channel, log_time=stamp, data=data, publish_time=stamp)


def _fill_rosbags_writer(
    writer: Any,
    topics: Mapping[str, TopicData],
    ros1: bool,
    progress: Progress | None = None,
    statics: Sequence[Static] = (),
    pieces: Pieces | None = None,
) -> None:
    """Open a rosbags writer, add one connection per topic, write every message (of every
    piece, as :func:`_write_mcap`), close."""
    _, typestore = _msgdef(ros1)
    every, total = pieces or ([topics], sum(len(d.stream) for d in topics.values()))
    writer.open()
    try:
        from imucal_cli.frames import tf_typestore

        for topic, msgtype, data in statics:
            connection = writer.add_connection(topic, msgtype, typestore=tf_typestore(ros1))
            writer.write(connection, _first_ns(topics), data)
        connections = {
            topic: writer.add_connection(topic, IMU_MSGTYPE, typestore=typestore)
            for topic in topics
        }
        for log_ns, topic, data in _serialised_messages(every, ros1, progress, total):
            writer.write(connections[topic], log_ns, data)
    finally:
        writer.close()


def _write_rosbag2(
    path: Path,
    topics: Mapping[str, TopicData],
    storage: str,
    progress: Progress | None = None,
    statics: Sequence[Static] = (),
    pieces: Pieces | None = None,
) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    # rosbags opens sqlite3 storage through an SQLite URI it does not escape (``file:{path}``):
    # a ``#``, ``?`` or ``%`` in the path sends the database elsewhere (cut at the ``#``: a
    # file beside the output's folder, named by its start) and leaves the bag without it. Such
    # a bag is written where the path is plain, and moved.
    if plugin == StoragePlugin.SQLITE3 and _URI_CHARACTERS & set(str(path.resolve())):
        with tempfile.TemporaryDirectory(prefix="imucal-") as plain:
            target = Path(plain) / "".join("_" if c in _URI_CHARACTERS else c for c in path.name)
            if _URI_CHARACTERS & set(str(target.resolve())):
                raise InputError(f"{path}: the temporary folder {plain} holds #, ? or %")
            _write_rosbag2(target, topics, storage, progress, statics, pieces)
            shutil.move(target, path)
        return
    writer = Writer(path, version=9, storage_plugin=plugin)
    _fill_rosbags_writer(writer, topics, False, progress, statics, pieces)


def _write_rosbag1(
    path: Path,
    topics: Mapping[str, TopicData],
    progress: Progress | None = None,
    statics: Sequence[Static] = (),
    pieces: Pieces | None = None,
) -> None:
    from rosbags.rosbag1 import Writer

    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    _fill_rosbags_writer(writer, topics, True, progress, statics, pieces)


def write_imu_log(
    out: str | Path,
    fmt: str,
    topics: Mapping[str, TopicData],
    progress: Progress | None = None,
    replace: bool = False,
    tf_static: StaticTransforms = (),
    robot_description: str | None = None,
    later: Pieces | None = None,
) -> Path:
    """Write IMU topics to ``out`` in format ``fmt`` (one of :data:`FORMATS`), and (where
    given) ``tf_static`` as one ``/tf_static`` message and ``robot_description`` (a URDF) as
    one ``/robot_description`` message at the log's start. ``later``: the pieces that follow
    ``topics`` (a long drive, made as it is written) and the messages' total, where known.

    The log is built in a new temporary folder beside ``out`` and renamed into place once
    complete, so an interrupted write leaves no partial log. An existing ``out`` is an error;
    with ``replace``, it is replaced if it is a log (:func:`~imucal_cli.paths.recognised_log`),
    and nothing else ever is.
    """
    if fmt not in FORMATS:
        raise InputError(f"unknown log format {fmt!r} (expected one of: {', '.join(FORMATS)})")
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")
    refuse_existing(out, replace)
    work = Path(
        tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent)
    )  # ours alone
    tmp = work / out.name
    try:
        form = LOG_FORMATS[fmt]
        ros1 = form.encoding == "ros1"
        statics = _statics(tf_static, robot_description, topics, ros1)
        pieces = None if later is None else (itertools.chain([topics], later[0]), later[1])
        if form.container == "mcap":
            _write_mcap(tmp, topics, ros1, progress=progress, statics=statics, pieces=pieces)
        elif form.container == "rosbag1":
            _write_rosbag1(tmp, topics, progress, statics, pieces)
        else:
            _write_rosbag2(tmp, topics, str(form.storage), progress, statics, pieces)
        if out.exists() or out.is_symlink():
            refuse_existing(out, replace)  # (again: it may have appeared meanwhile)
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        tmp.rename(out)
    except (OSError, sqlite3.OperationalError) as exc:  # a full disk, mid-write
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputError(f"{out}: cannot write the log: {why}") from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out
