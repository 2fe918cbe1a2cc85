"""The vectorised decode path: bit-exact with the rosbags deserializer, on every container."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA
from rosbags.typesys import Stores, get_typestore

from imucal_cli.io.fastimu import RawBatch, decode_imu
from imucal_cli.io.logs import open_log, read_imu
from imucal_cli.io.writers import FORMATS, TopicData, write_imu_log
from imucal_cli.types import ImuStream

IMU = "sensor_msgs/msg/Imu"


def _messages(store, ros1: bool, rng, count: int):
    t = store.types
    out = []
    for i in range(count):
        frame = "f" * int(rng.integers(0, 20))  # every padding case of CDR
        header = {"stamp": t["builtin_interfaces/msg/Time"](sec=int(rng.integers(0, 2**31 - 1)), nanosec=int(rng.integers(0, 10**9))), "frame_id": frame}
        if ros1:
            header["seq"] = i
        v = rng.normal(size=6) * 10.0 ** rng.integers(-12, 6, size=6)
        vec = t["geometry_msgs/msg/Vector3"]
        msg = t[IMU](
            header=t["std_msgs/msg/Header"](**header),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.1, y=0.2, z=0.3, w=0.9),
            orientation_covariance=rng.normal(size=9),
            angular_velocity=vec(x=v[0], y=v[1], z=v[2]),
            angular_velocity_covariance=rng.normal(size=9),
            linear_acceleration=vec(x=v[3], y=v[4], z=v[5]),
            linear_acceleration_covariance=rng.normal(size=9),
        )
        out.append(msg)
    return out


@pytest.mark.parametrize("ros1", [False, True])
def test_decode_matches_rosbags_for_every_frame_id_length(ros1):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(5)
    messages = _messages(store, ros1, rng, 200)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    deserialize = store.deserialize_ros1 if ros1 else store.deserialize_cdr
    blobs = [bytes(serialize(m, IMU)) for m in messages]
    lengths = np.array([len(b) for b in blobs], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    batch = RawBatch("/imu", "ros1" if ros1 else "cdr", np.frombuffer(b"".join(blobs), np.uint8), starts, lengths, np.arange(200, dtype=np.int64))
    decoded = decode_imu(batch)
    assert len(decoded.undecoded) == 0
    for i, blob in enumerate(blobs):
        ref = deserialize(blob, IMU)
        assert decoded.stamp_ns[i] == ref.header.stamp.sec * 10**9 + ref.header.stamp.nanosec
        w, a = ref.angular_velocity, ref.linear_acceleration
        assert decoded.gyro[i].tobytes() == np.array([w.x, w.y, w.z]).tobytes()
        assert decoded.accel[i].tobytes() == np.array([a.x, a.y, a.z]).tobytes()
    assert set(decoded.frame_ids) == {m.header.frame_id for m in messages}


def test_unrecognised_layouts_are_left_to_the_generic_decoder():
    store = get_typestore(Stores.ROS2_HUMBLE)
    (msg,) = _messages(store, False, np.random.default_rng(1), 1)
    little = bytes(store.serialize_cdr(msg, IMU))
    big = bytes(store.serialize_cdr(msg, IMU, little_endian=False))
    blobs = [little, big, little[:40]]
    lengths = np.array([len(b) for b in blobs])
    batch = RawBatch("/imu", "cdr", np.frombuffer(b"".join(blobs), np.uint8), np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths, np.arange(3))
    decoded = decode_imu(batch)
    assert decoded.undecoded.tolist() == [1, 2] and len(decoded.stamp_ns) == 1


def _sample_streams(rng):
    t0 = 1_700_000_000_000_000_000
    base = ImuStream(t0 + np.arange(500) * 10_000_000, rng.normal(size=(500, 3)), rng.normal(size=(500, 3)), "base_link")
    lidar = ImuStream(t0 + 3_000_000 + np.arange(900) * 5_000_000, rng.normal(size=(900, 3)), rng.normal(size=(900, 3)), "front_left_top_imu")
    return {"/gnss/imu": TopicData(base, base.t_ns + 1_000_000), "/lidar/imu": TopicData(lidar, lidar.t_ns + 2_000_000)}


def _same(a, b):
    for topic in a:
        x, y = a[topic], b[topic]
        assert x.stream.t_ns.tobytes() == y.stream.t_ns.tobytes()
        assert x.stream.gyro.tobytes() == y.stream.gyro.tobytes()
        assert x.stream.accel.tobytes() == y.stream.accel.tobytes()
        assert x.stream.frame_id == y.stream.frame_id
        assert x.log_time_ns.tobytes() == y.log_time_ns.tobytes()
        assert x.stats.to_dict() == y.stats.to_dict()


@pytest.mark.parametrize("fmt", FORMATS)
def test_fast_path_is_used_and_equals_the_generic_path(tmp_path, fmt):
    topics = _sample_streams(np.random.default_rng(2))
    out = tmp_path / ("log.mcap" if fmt.startswith("mcap") else "log.bag" if fmt == "rosbag1" else "log")
    path = write_imu_log(out, fmt, topics)
    with open_log(path) as log:
        assert log.fast_batches(list(topics)) is not None
    fast, slow = read_imu(path, list(topics)), read_imu(path, list(topics), fast=False)
    _same(fast, slow)
    assert fast["/lidar/imu"].stream.gyro.tobytes() == topics["/lidar/imu"].stream.gyro.tobytes()


@pytest.mark.parametrize("name", ["ros1_rosbag.bag", "ros1_mcap_ros1_writer.mcap", "ros2_mcap_ros2_writer.mcap", "rosbag2_converted_sqlite3"])
def test_fast_path_on_logs_from_other_tools(name):
    with open_log(DATA / name) as log:
        assert log.fast_batches(["/imu/data"]) is not None
    _same(read_imu(DATA / name, ["/imu/data"]), read_imu(DATA / name, ["/imu/data"], fast=False))


@pytest.mark.parametrize("frame_id", ["", "a", "base_link", "front_left_top_imu", "seven77"])
def test_bulk_serialisation_is_byte_identical_with_rosbags(frame_id):
    from imucal_cli.io.bulkwrite import serialize_cdr, serialize_ros1

    rng = np.random.default_rng(len(frame_id))
    stream = ImuStream(1_700_000_000_123_456_789 + np.arange(20) * 10_000_000, rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), frame_id)
    for ros1, bulk in ((False, serialize_cdr(stream)), (True, serialize_ros1(stream))):
        store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        t = store.types
        for i in range(20):
            sec, nsec = divmod(int(stream.t_ns[i]), 10**9)
            header = {"stamp": t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), "frame_id": frame_id}
            if ros1:
                header["seq"] = i
            cov = np.zeros(9)
            cov_o = cov.copy()
            cov_o[0] = -1.0
            vec = t["geometry_msgs/msg/Vector3"]
            msg = t[IMU](
                header=t["std_msgs/msg/Header"](**header),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=cov_o,
                angular_velocity=vec(*stream.gyro[i]),
                angular_velocity_covariance=cov,
                linear_acceleration=vec(*stream.accel[i]),
                linear_acceleration_covariance=cov,
            )
            expected = bytes(store.serialize_ros1(msg, IMU) if ros1 else store.serialize_cdr(msg, IMU))
            assert bulk[i].tobytes() == expected


# --------------------------------------------------------------------------- sqlite3 pages


def _sqlite_varint(value: int) -> bytes:
    """SQLite's varint (https://www.sqlite.org/fileformat2.html#varint), as a reference."""
    value &= (1 << 64) - 1
    if value >= 1 << 56:
        tail = bytes([value & 0xFF])
        value >>= 8
        groups = [(value >> (7 * k)) & 0x7F for k in range(7, -1, -1)]
        return bytes(g | 0x80 for g in groups) + tail
    groups = []
    while True:
        groups.append(value & 0x7F)
        value >>= 7
        if not value:
            break
    groups.reverse()
    return bytes([g | 0x80 for g in groups[:-1]] + [groups[-1]])


def test_sqlite_varints_decode_every_length():
    from imucal_cli.io.sqlitepages import _varints

    values = [0, 1, 127, 128, 16383, 16384, 2**21 - 1, 2**21, 2**28, 2**35 + 3, 2**42, 2**49 - 1, 2**56 - 1, 2**56, 2**63 - 1, -1, -(2**40)]
    encoded = [_sqlite_varint(v) for v in values]
    blob = b"".join(encoded) + bytes(16)
    at = np.concatenate([[0], np.cumsum([len(e) for e in encoded])[:-1]])
    value, length = _varints(np.frombuffer(blob, np.uint8), at)
    assert value.tolist() == values
    assert length.tolist() == [len(e) for e in encoded]


def _sqlite_log(tmp_path, rng):
    topics = _sample_streams(rng)
    return write_imu_log(tmp_path / "log", "rosbag2-sqlite3", topics), topics


def _count_page_groups(monkeypatch):
    from imucal_cli.io import sqlitepages

    groups = []
    rows = sqlitepages.MessagePages.rows

    def spy(self, *args, **kwargs):
        for item in rows(self, *args, **kwargs):
            groups.append(len(item.starts))
            yield item

    monkeypatch.setattr(sqlitepages.MessagePages, "rows", spy)
    return groups


def test_sqlite_pages_are_read_directly_and_equal_sqlite(tmp_path, monkeypatch):
    path, topics = _sqlite_log(tmp_path, np.random.default_rng(11))
    groups = _count_page_groups(monkeypatch)
    monkeypatch.setattr("imucal_cli.io.sqlitepages.GROUP_BYTES", 3 * 4096)
    fast = read_imu(path, list(topics))
    assert sum(groups) == 1400 and len(groups) > 3  # every row, from the pages
    _same(fast, read_imu(path, list(topics), fast=False))


def test_sqlite_pages_hand_over_to_sqlite_where_the_layout_is_unexpected(tmp_path, monkeypatch):
    """A row on overflow pages halfway: the rows before come from the pages, the rest from
    SQLite, and together they are exactly what SQLite reads."""
    import sqlite3

    path, topics = _sqlite_log(tmp_path, np.random.default_rng(12))
    (db,) = sorted(path.glob("*.db3"))
    with sqlite3.connect(db) as connection:
        connection.execute("INSERT INTO topics (id, name, type, serialization_format, offered_qos_profiles, type_description_hash) VALUES (99, '/big', 'std_msgs/msg/String', 'cdr', '', '')")
        rows = connection.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id").fetchall()
        connection.execute("DELETE FROM messages")
        half = len(rows) // 2
        connection.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)", rows[:half])
        connection.execute("INSERT INTO messages VALUES (?, 99, 0, ?)", (rows[half - 1][0] + 1, bytes(20000)))
        connection.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)", [(r[0] + 1, *r[1:]) for r in rows[half:]])
    groups = _count_page_groups(monkeypatch)
    monkeypatch.setattr("imucal_cli.io.sqlitepages.GROUP_BYTES", 2 * 4096)
    fast = read_imu(path, list(topics))
    assert 0 < sum(groups) < 1400  # some rows from the pages, the rest through SQLite
    _same(fast, read_imu(path, list(topics), fast=False))
    assert sum(len(r.stream.t_ns) for r in fast.values()) == 1400


def test_sqlite_with_a_write_ahead_log_is_read_through_sqlite(tmp_path, monkeypatch):
    path, topics = _sqlite_log(tmp_path, np.random.default_rng(13))
    (db,) = sorted(path.glob("*.db3"))
    (tmp_path / "log" / (db.name + "-wal")).write_bytes(b"\x00" * 64)
    groups = _count_page_groups(monkeypatch)
    fast = read_imu(path, list(topics))
    assert groups == []
    assert sum(len(r.stream.t_ns) for r in fast.values()) == 1400


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_fast_path_reads_mcap_chunks_of_every_compression(tmp_path, compression, monkeypatch):
    """Chunks decompressed straight into the group buffer (zstd), copied into it (lz4, none),
    many groups read ahead in the thread: the same as the generic path."""
    from imucal_cli.io.writers import _write_mcap

    monkeypatch.setattr("imucal_cli.io.fastimu.GROUP_BYTES", 16384)
    topics = _sample_streams(np.random.default_rng(3))
    path = tmp_path / f"{compression}.mcap"
    _write_mcap(path, topics, ros1=False, compression=compression, chunk_size=4096)
    with open_log(path) as log:
        assert log.fast_batches(list(topics)) is not None
    _same(read_imu(path, list(topics)), read_imu(path, list(topics), fast=False))


def _write_ros1_bag(path, frame_ids_by_topic, count, rng):
    """A ROS 1 bag (lz4 chunks of about 4 KiB) with ``count`` Imu messages a topic at 100 Hz,
    topic ``k``'s message ``i`` with frame id ``frame_ids_by_topic[k][i % len(...)]``, and a
    String topic in between."""
    from rosbags.rosbag1 import Writer

    store = get_typestore(Stores.ROS1_NOETIC)
    messages = _messages(store, True, rng, count)
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    writer.chunk_threshold = 4096
    with writer:
        imus = [writer.add_connection(f"/imu{k}", IMU, typestore=store) for k in range(len(frame_ids_by_topic))]
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for i, msg in enumerate(messages):
            msg.header.stamp = store.types["builtin_interfaces/msg/Time"](sec=1 + i // 100, nanosec=10_000_000 * (i % 100))
            vec = store.types["geometry_msgs/msg/Vector3"]
            msg.angular_velocity, msg.linear_acceleration = vec(*rng.normal(size=3)), vec(*rng.normal(size=3) * 5.0)  # plausible: kept
            for k, (connection, frames) in enumerate(zip(imus, frame_ids_by_topic, strict=True)):
                msg.header.frame_id = frames[i % len(frames)]
                writer.write(connection, 1_000_000_000 + 10_000_000 * i + k, bytes(store.serialize_ros1(msg, IMU)))
            writer.write(chatter, 1_000_000_000 + 10_000_000 * i + 5, bytes(store.serialize_ros1(store.types["std_msgs/msg/String"](data="x" * (i % 7)), "std_msgs/msg/String")))
    return [f"/imu{k}" for k in range(len(frame_ids_by_topic))]


@pytest.mark.parametrize("frame_ids", [[["imu"], ["front_left_top_imu"]], [["imu"], ["a", "base_link", ""]]])
def test_ros1_bags_with_many_small_chunks_equal_the_generic_path(tmp_path, monkeypatch, frame_ids):
    """Many chunks a group, a String topic between the IMU ones, one frame id a topic or
    several of different lengths (their records then differ in size): the generic path's
    result bit for bit, the topic's frame id the first message's."""
    monkeypatch.setattr("imucal_cli.io.fastimu.GROUP_BYTES", 16384)
    path = tmp_path / "log.bag"
    topics = _write_ros1_bag(path, frame_ids, 300, np.random.default_rng(4))
    fast = read_imu(path, topics)
    _same(fast, read_imu(path, topics, fast=False))
    assert [len(fast[t].stream.t_ns) for t in topics] == [300, 300]
    assert [fast[t].stream.frame_id for t in topics] == [frames[0] for frames in frame_ids]


def test_ros1_index_larger_than_expected_is_read_on(tmp_path, monkeypatch):
    """A chunk's index data is read with the chunk, as much as its chunk info says; where it is
    longer (or the estimate wrong), the rest is read after: the same messages."""
    from imucal_cli.io import fastimu

    path = tmp_path / "log.bag"
    topics = _write_ros1_bag(path, [["imu"], ["lidar_imu"]], 200, np.random.default_rng(6))
    expected = read_imu(path, topics)
    init = fastimu.Ros1Bag.__init__

    def no_estimate(self, handle):
        init(self, handle)
        self.index_bytes = [0] * len(self.index_bytes)

    monkeypatch.setattr(fastimu.Ros1Bag, "__init__", no_estimate)
    _same(read_imu(path, topics), expected)


@pytest.mark.parametrize("fmt", ["rosbag1", "mcap"])
def test_lz4_chunks_read_alike_without_liblz4(tmp_path, monkeypatch, fmt):
    """LZ4 chunks decompressed in place through liblz4 or, where it cannot be loaded, through
    python-lz4 and a copy: the same samples, and the generic path's."""
    from imucal_cli.io import lz4frames
    from imucal_cli.io.writers import _write_mcap

    monkeypatch.setattr("imucal_cli.io.fastimu.GROUP_BYTES", 16384)
    if fmt == "rosbag1":
        path = tmp_path / "log.bag"
        topics = _write_ros1_bag(path, [["imu"], ["lidar_imu"]], 300, np.random.default_rng(8))
    else:
        path = tmp_path / "log.mcap"
        topics = list(_sample_streams(np.random.default_rng(8)))
        _write_mcap(path, _sample_streams(np.random.default_rng(8)), ros1=False, compression="lz4", chunk_size=4096)
    with_lib = read_imu(path, topics)
    monkeypatch.setattr(lz4frames, "_liblz4", lambda: None)
    _same(read_imu(path, topics), with_lib)
    _same(with_lib, read_imu(path, topics, fast=False))


@pytest.mark.parametrize("order", [("op", "ver", "conn", "count"), ("count", "conn", "ver", "op"), ("conn", "op", "count", "extra", "ver")])
def test_ros1_index_headers_read_as_the_generic_header_parser_reads_them(order):
    """The index data records' header (read once a connection a chunk) in any field order,
    with fields it does not know: what the general record header parser finds."""
    import struct

    from imucal_cli.io.fastimu import _ros1_header, _ros1_index_header

    values = {"op": b"\x04", "ver": struct.pack("<I", 1), "conn": struct.pack("<I", 7), "count": struct.pack("<I", 123456), "extra": b"op=\x05"}
    fields = b"".join(struct.pack("<I", len(name) + 1 + len(values[name])) + name.encode() + b"=" + values[name] for name in order)
    record = b"junk" + struct.pack("<I", len(fields)) + fields + b"data"
    generic, end = _ros1_header(record, 4)
    assert _ros1_index_header(record, 4) == (generic["op"][0], struct.unpack("<I", generic["conn"])[0], struct.unpack("<I", generic["count"])[0], end)
    with pytest.raises(KeyError):  # an index record without its connection
        missing = b"".join(struct.pack("<I", len(n) + 1 + len(values[n])) + n.encode() + b"=" + values[n] for n in order if n != "conn")
        _ros1_index_header(struct.pack("<I", len(missing)) + missing, 0)


def _write_two_imus(path, fmt, count, rng, short_at=None):
    """A ROS 1 bag (lz4 chunks of about 4 KiB) or an MCAP (zstd chunks of 4 KiB, CDR) with two
    Imu topics at 100 Hz; message ``short_at`` of ``/imu1`` cut to 40 bytes (no layout holds
    it: the generic decoder rejects it too)."""
    ros1 = fmt == "rosbag1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    messages = _messages(store, ros1, rng, count)
    vec = store.types["geometry_msgs/msg/Vector3"]

    def blobs():
        for i, msg in enumerate(messages):
            msg.header.stamp = store.types["builtin_interfaces/msg/Time"](sec=1 + i // 100, nanosec=10_000_000 * (i % 100))
            msg.angular_velocity, msg.linear_acceleration = vec(*rng.normal(size=3)), vec(*rng.normal(size=3) * 5.0)
            for k, frame in enumerate(["base_link", "front_left_top_imu"]):
                msg.header.frame_id = frame
                blob = bytes(serialize(msg, IMU))
                yield k, 1_000_000_000 + 10_000_000 * i + k, blob[:40] if (k, i) == (1, short_at) else blob

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        writer.set_compression(Writer.CompressionFormat.LZ4)
        writer.chunk_threshold = 4096
        with writer:
            connections = [writer.add_connection(f"/imu{k}", IMU, typestore=store) for k in range(2)]
            for k, log_ns, blob in blobs():
                writer.write(connections[k], log_ns, blob)
    else:
        from mcap.writer import CompressionType, Writer

        from imucal_cli.io.writers import _msgdef

        with path.open("wb") as handle:
            writer = Writer(handle, compression=CompressionType.ZSTD, chunk_size=4096)
            writer.start(profile="ros2", library="imucal tests")
            schema = writer.register_schema(name=IMU, encoding="ros2msg", data=_msgdef(False)[0].encode())
            channels = [writer.register_channel(topic=f"/imu{k}", message_encoding="cdr", schema_id=schema) for k in range(2)]
            for k, log_ns, blob in blobs():
                writer.add_message(channel_id=channels[k], log_time=log_ns, data=blob, publish_time=log_ns)
            writer.finish()
    return ["/imu0", "/imu1"]


def _counting_decode_imu(monkeypatch):
    """Count the batches decoded by decode_imu (the topic-by-topic path), not chunk by chunk."""
    from imucal_cli.io import fastimu

    calls = []
    decode = fastimu.decode_imu

    def counted(batch):
        calls.append(batch.topic)
        return decode(batch)

    monkeypatch.setattr(fastimu, "decode_imu", counted)
    return calls


@pytest.mark.parametrize("fmt", ["rosbag1", "mcap"])
def test_chunks_are_decoded_as_they_are_decompressed(tmp_path, monkeypatch, fmt):
    """A log of the common layout: every group decoded chunk by chunk, none topic by topic,
    and the generic path's result bit for bit."""
    monkeypatch.setattr("imucal_cli.io.fastimu.GROUP_BYTES", 16384)
    path = tmp_path / ("log.bag" if fmt == "rosbag1" else "log.mcap")
    topics = _write_two_imus(path, fmt, 400, np.random.default_rng(8))
    calls = _counting_decode_imu(monkeypatch)
    fast = read_imu(path, topics)
    assert calls == []
    _same(fast, read_imu(path, topics, fast=False))
    assert [len(fast[t].stream.t_ns) for t in topics] == [400, 400]
    assert [fast[t].stream.frame_id for t in topics] == ["base_link", "front_left_top_imu"]


@pytest.mark.parametrize("fmt", ["rosbag1", "mcap"])
def test_a_group_with_a_message_of_another_layout_is_decoded_topic_by_topic(tmp_path, monkeypatch, fmt):
    """One message no layout holds: its group is decoded topic by topic (decode_imu leaves the
    message to the generic decoder, which rejects it too), the others chunk by chunk; the
    generic path's result and counts bit for bit."""
    monkeypatch.setattr("imucal_cli.io.fastimu.GROUP_BYTES", 16384)
    path = tmp_path / ("log.bag" if fmt == "rosbag1" else "log.mcap")
    topics = _write_two_imus(path, fmt, 400, np.random.default_rng(9), short_at=250)
    calls = _counting_decode_imu(monkeypatch)
    fast = read_imu(path, topics)
    assert sorted(set(calls)) == topics and len(calls) == 2  # one group, both its topics
    _same(fast, read_imu(path, topics, fast=False))
    assert fast["/imu1"].stats.decode_errors == 1
    assert [len(fast[t].stream.t_ns) for t in topics] == [400, 399]
