"""Writing ``sensor_msgs/Imu`` logs in every format imucal reads (for the simulator and tests).

Serialisation is done by ``rosbags`` (CDR and ROS 1), containers by the ``mcap`` writer (plain
MCAP) and the ``rosbags`` writers (rosbag2 sqlite3/mcap, ROS 1 bag).
"""

from __future__ import annotations

import heapq
import shutil
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.errors import InputError
from imucal_cli.io.logs import IMU_MSGTYPE
from imucal_cli.types import ImuStream

#: ``--format`` names: plain MCAP with ROS 2 CDR, plain MCAP with ROS 1 encoding, rosbag2
#: directories with sqlite3 or mcap storage, ROS 1 bag.
FORMATS = ("mcap", "mcap-ros1", "rosbag2-sqlite3", "rosbag2-mcap", "rosbag1")


@dataclass(frozen=True)
class TopicData:
    """One IMU topic to write: the samples and the time each reached the recorder."""

    stream: ImuStream
    log_time_ns: np.ndarray | None = None  # defaults to the stamps


def _messages(topics: Mapping[str, TopicData]) -> Iterator[tuple[int, str, int]]:
    """``(log_time_ns, topic, index)`` over all topics, merged in log-time order."""

    def one(topic: str, data: TopicData) -> Iterator[tuple[int, str, int]]:
        log_ns = data.stream.t_ns if data.log_time_ns is None else data.log_time_ns
        order = np.argsort(log_ns, kind="stable")
        for i in order:
            yield int(log_ns[i]), topic, int(i)

    return heapq.merge(*(one(t, d) for t, d in topics.items()))


class _ImuSerializer:
    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        t = self.typestore.types
        self._Imu = t[IMU_MSGTYPE]
        self._Header = t["std_msgs/msg/Header"]
        self._Time = t["builtin_interfaces/msg/Time"]
        self._Quaternion = t["geometry_msgs/msg/Quaternion"]
        self._Vector3 = t["geometry_msgs/msg/Vector3"]
        # REP-145: orientation not provided -> orientation_covariance[0] = -1.
        self._orientation_cov = np.zeros(9)
        self._orientation_cov[0] = -1.0
        self._zero_cov = np.zeros(9)
        self._seq = 0

    def message(self, stream: ImuStream, i: int) -> Any:
        stamp = int(stream.t_ns[i])
        sec, nanosec = divmod(stamp, 1_000_000_000)
        header_args: dict[str, Any] = {
            "stamp": self._Time(sec=sec, nanosec=nanosec),
            "frame_id": stream.frame_id,
        }
        if self.ros1:
            header_args["seq"] = self._seq
            self._seq += 1
        g = stream.gyro[i]
        a = stream.accel[i]
        return self._Imu(
            header=self._Header(**header_args),
            orientation=self._Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=self._orientation_cov,
            angular_velocity=self._Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2])),
            angular_velocity_covariance=self._zero_cov,
            linear_acceleration=self._Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
            linear_acceleration_covariance=self._zero_cov,
        )

    def serialize(self, stream: ImuStream, i: int) -> bytes:
        msg = self.message(stream, i)
        if self.ros1:
            return bytes(self.typestore.serialize_ros1(msg, IMU_MSGTYPE))
        return bytes(self.typestore.serialize_cdr(msg, IMU_MSGTYPE))

    def msgdef(self) -> str:
        text, _ = self.typestore.generate_msgdef(IMU_MSGTYPE, ros_version=1 if self.ros1 else 2)
        return text


def _write_mcap(path: Path, topics: Mapping[str, TopicData], ros1: bool) -> None:
    from mcap.writer import CompressionType, Writer

    serializer = _ImuSerializer(ros1)
    with path.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD)
        writer.start(profile="ros1" if ros1 else "ros2", library="imucal")
        schema_id = writer.register_schema(
            name="sensor_msgs/Imu" if ros1 else IMU_MSGTYPE,
            encoding="ros1msg" if ros1 else "ros2msg",
            data=serializer.msgdef().encode(),
        )
        channels = {
            topic: writer.register_channel(
                topic=topic, message_encoding="ros1" if ros1 else "cdr", schema_id=schema_id
            )
            for topic in topics
        }
        sequence = dict.fromkeys(topics, 0)
        for log_ns, topic, i in _messages(topics):
            stream = topics[topic].stream
            writer.add_message(
                channel_id=channels[topic],
                log_time=log_ns,
                data=serializer.serialize(stream, i),
                publish_time=log_ns,
                sequence=sequence[topic],
            )
            sequence[topic] += 1
        writer.finish()


def _write_rosbag2(path: Path, topics: Mapping[str, TopicData], storage: str) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    serializer = _ImuSerializer(ros1=False)
    writer = Writer(path, version=9, storage_plugin=plugin)
    writer.open()
    try:
        connections = {
            topic: writer.add_connection(topic, IMU_MSGTYPE, typestore=serializer.typestore)
            for topic in topics
        }
        for log_ns, topic, i in _messages(topics):
            writer.write(connections[topic], log_ns, serializer.serialize(topics[topic].stream, i))
    finally:
        writer.close()


def _write_rosbag1(path: Path, topics: Mapping[str, TopicData]) -> None:
    from rosbags.rosbag1 import Writer

    serializer = _ImuSerializer(ros1=True)
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    writer.open()
    try:
        connections = {
            topic: writer.add_connection(topic, IMU_MSGTYPE, typestore=serializer.typestore)
            for topic in topics
        }
        for log_ns, topic, i in _messages(topics):
            writer.write(connections[topic], log_ns, serializer.serialize(topics[topic].stream, i))
    finally:
        writer.close()


def write_imu_log(out: str | Path, fmt: str, topics: Mapping[str, TopicData]) -> Path:
    """Write IMU topics to ``out`` in format ``fmt`` (one of :data:`FORMATS`).

    The log is built beside ``out`` under a temporary name and renamed into place once
    complete, so an interrupted write leaves no partial log. An existing ``out`` is replaced.
    """
    if fmt not in FORMATS:
        raise InputError(f"unknown log format {fmt!r} (expected one of: {', '.join(FORMATS)})")
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")
    tmp = out.with_name(f".{out.name}.partial")
    _remove(tmp)
    try:
        if fmt in ("mcap", "mcap-ros1"):
            _write_mcap(tmp, topics, ros1=fmt == "mcap-ros1")
        elif fmt == "rosbag1":
            _write_rosbag1(tmp, topics)
        else:
            _write_rosbag2(tmp, topics, storage=fmt.removeprefix("rosbag2-"))
            _rename_rosbag2_storage(tmp, out.name)
        _remove(out)
        tmp.rename(out)
    except BaseException:
        _remove(tmp)
        raise
    return out


def _rename_rosbag2_storage(folder: Path, name: str) -> None:
    """rosbags names the storage file after the (temporary) folder; name it after the final one."""
    import yaml

    metadata_path = folder / "metadata.yaml"
    metadata = yaml.safe_load(metadata_path.read_text())
    info = metadata["rosbag2_bagfile_information"]
    renamed = []
    for relative in info["relative_file_paths"]:
        old = folder / relative
        new_name = name + old.name.removeprefix(folder.name)
        old.rename(folder / new_name)
        renamed.append(new_name)
    info["relative_file_paths"] = renamed
    for entry, new_name in zip(info.get("files", []), renamed, strict=False):
        entry["path"] = new_name
    metadata_path.write_text(yaml.safe_dump(metadata, sort_keys=False))


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
