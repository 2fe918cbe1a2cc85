"""Probes of hostile and odd input (issue 28): every case runs ``imucal`` as its own process and
is held to one rule: exit 0 or 2 (2 with one line on stderr and no traceback), no file of the
user's changed, peak RSS at most 1 GB, and wall time within a bound set by the input's real
size (:data:`BOUND_S` plus :data:`BOUND_S_PER_MB` per MB of input files: the work a file can
ask for is bounded by its bytes, not by what its records claim).

Run through ``python benchmarks/faults.py --probes`` (markdown table on stdout). Bombs are built
here; each process runs with a 6 GiB address-space limit so that a regression cannot take the
machine down (it then shows as a failed case); its peak RSS is its own (:data:`LAUNCHER`).
"""

from __future__ import annotations

import bz2
import hashlib
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
import zstandard

from imucal_cli.documents import write_document
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.sim.writers import TopicData, write_imu_log
from imucal_cli.types import ImuStream

BOUND_S, BOUND_S_PER_MB = 30.0, 2.0
MAX_RSS_MB = 1000.0
#: Logs of the interrupted batch: it must still be running 2 s in (24 logs took 2.0 s).
BATCH_LOGS = 72
LIMIT_AS = 6 << 30
#: imucal run under a launcher that forks it with the address-space limit set, reaps it with
#: os.wait4 and writes its peak RSS (kB) to the file named first: a process started from this
#: one would count this one's memory in its peak (exec keeps the high-water mark of the memory
#: it replaces), a process forked from the small launcher does not.
LAUNCHER = """
import os, resource, signal, sys
rss_file, limit, argv = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
pid = os.fork()
if pid == 0:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    os.execv(sys.executable, [sys.executable, "-m", "imucal_cli.cli", *argv])
_, status, usage = os.wait4(pid, 0)
open(rss_file, "w").write(str(usage.ru_maxrss))
sys.exit(os.waitstatus_to_exitcode(status) % 256)
"""


@dataclass
class Case:
    name: str
    argv: list[str]  # imucal's arguments
    folder: Path
    outputs: set[str] = field(
        default_factory=set
    )  # files (relative to folder) the run may create or replace
    expect: int | None = None  # the exit code this case must give (None: 0 or 2)
    check: Callable[[subprocess.CompletedProcess], str] | None = None  # "" or what is wrong
    signal_after_s: float | None = None  # send ``sent`` to the group after this long
    sent: int = signal.SIGINT
    #: A folder (relative to ``folder``) held with an exclusive flock while the case runs: what
    #: another run writing into it at once holds.
    held: str | None = None


def _snapshot(folder: Path) -> dict[str, str]:
    """Every regular file's hash (a file over 64 MiB, a sparse terabyte: its size and mtime)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        if p.stat().st_size <= 64 << 20
        else f"{p.stat().st_size}:{p.stat().st_mtime_ns}"
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def _size_mb(folder: Path) -> float:
    """The input's real size: the blocks its files hold (a sparse terabyte holds none)."""
    return sum(p.stat().st_blocks * 512 for p in folder.rglob("*") if p.is_file()) / 1e6


def run_case(case: Case) -> dict:
    before = _snapshot(case.folder)
    bound = BOUND_S + BOUND_S_PER_MB * _size_mb(case.folder)
    start = time.perf_counter()
    # spawned (not forked: a fork's peak RSS would start at this process's), its own session,
    # its output in files; reaped here with os.wait4 for its own peak RSS
    out_path, err_path = (
        case.folder.parent / f".{case.folder.name}.out",
        case.folder.parent / f".{case.folder.name}.err",
    )
    rss_path = case.folder.parent / f".{case.folder.name}.rss"
    argv = [sys.executable, "-c", LAUNCHER, str(rss_path), str(LIMIT_AS), *case.argv]
    actions = [
        (os.POSIX_SPAWN_OPEN, 1, str(out_path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644),
        (os.POSIX_SPAWN_OPEN, 2, str(err_path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644),
    ]
    here = os.getcwd()
    held = None
    if case.held is not None:
        import fcntl

        held = os.open(case.folder / case.held, os.O_RDONLY)
        fcntl.flock(held, fcntl.LOCK_EX)
    os.chdir(case.folder)
    try:
        pid = os.posix_spawn(argv[0], argv, os.environ, file_actions=actions, setsid=True)
    finally:
        os.chdir(here)
    signalled = False
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        elapsed = time.perf_counter() - start
        if case.signal_after_s is not None and not signalled and elapsed > case.signal_after_s:
            os.killpg(pid, case.sent)
            signalled = True
        if elapsed > 2 * bound:
            os.killpg(pid, signal.SIGKILL)
        time.sleep(0.01)
    wall = time.perf_counter() - start
    if held is not None:
        os.close(held)
    code = os.waitstatus_to_exitcode(status)
    out, err = out_path.read_bytes(), err_path.read_bytes()
    out_path.unlink()
    err_path.unlink()
    rss_mb = float(rss_path.read_text()) / 1024 if rss_path.exists() else float("nan")
    rss_path.unlink(missing_ok=True)
    after = _snapshot(case.folder)
    changed = sorted(k for k, v in before.items() if after.get(k) != v and k not in case.outputs)
    created = sorted(k for k in after if k not in before and k not in case.outputs)
    stderr = err.decode("utf-8", "replace")
    lines = [line for line in stderr.splitlines() if line.strip()]
    problems = []
    if case.expect is not None and code != case.expect:
        problems.append(f"exit {code}, expected {case.expect}")
    elif case.expect is None and code not in (0, 2):
        problems.append(f"exit {code}")
    if "Traceback" in stderr:
        problems.append("traceback")
    if code == 2 and len([line for line in lines if line.startswith("imucal: error")]) != 1:
        problems.append(f"{len(lines)} lines on stderr")
    if changed:
        problems.append("changed: " + ", ".join(changed))
    if created:
        problems.append("created: " + ", ".join(created))
    if wall > bound:
        problems.append(f"over the {bound:.0f} s bound")
    if rss_mb > MAX_RSS_MB:
        problems.append(f"peak RSS {rss_mb:.0f} MB")
    if case.check is not None:
        why = case.check(subprocess.CompletedProcess(case.argv, code, out, err))
        if why:
            problems.append(why)
    first = next(
        (line for line in lines if line.startswith("imucal: error")), lines[-1] if lines else ""
    )
    return {
        "case": case.name,
        "exit": code,
        "wall": wall,
        "bound": bound,
        "rss": rss_mb,
        "message": first,
        "problems": problems,
    }


# ------------------------------------------------------------------ bombs, built here


def _mcap_record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _mcap_chunk(claimed: int, compression: str, data: bytes) -> bytes:
    body = (
        struct.pack("<QQQI", 0, 0, claimed, 0)
        + _string(compression)
        + struct.pack("<Q", len(data))
        + data
    )
    return _mcap_record(0x06, body)


def mcap_without_summary(path: Path, chunks: list[bytes]) -> Path:
    """An MCAP file as a killed recorder leaves it: magic, header, chunks, no summary."""
    path.write_bytes(
        b"\x89MCAP0\r\n" + _mcap_record(0x01, _string("ros2") + _string("probe")) + b"".join(chunks)
    )
    return path


def mcap_zstd_bomb(path: Path, chunks: int = 40) -> Path:
    """Chunks of 64 MiB of zeros, each about 2 kB of zstd: 2.5 GiB from 90 kB."""
    data = zstandard.ZstdCompressor(level=19).compress(bytes(64 << 20))
    return mcap_without_summary(path, [_mcap_chunk(64 << 20, "zstd", data)] * chunks)


def mcap_empty_records(path: Path) -> Path:
    """One chunk that claims 256 MiB, inside the bounds (about 250:1), of 29.8 M records: runs of
    60 empty Message records (9 bytes each) with a private record of one random byte between
    them. The record walk listed every offset as a Python int (1.7 GB)."""
    rng = np.random.default_rng(0)
    groups = (256 << 20) // (60 * 9 + 10)
    noise = rng.integers(0, 256, groups, dtype=np.uint8).tobytes()
    run, private = b"\x05" + bytes(8), b"\x80" + (1).to_bytes(8, "little")
    data = b"".join(run * 60 + private + noise[k : k + 1] for k in range(groups))
    chunk = _mcap_chunk(len(data), "zstd", zstandard.ZstdCompressor(level=3).compress(data))
    return mcap_without_summary(path, [chunk])


def mcap_tf_static_bomb(path: Path, drive, megabytes: int = 200) -> Path:
    """The drive's IMU topics with, first, one /tf_static message of ``megabytes`` MiB of junk
    transforms (2.38 M at 200), a chunk of its own compressed 800:1: deserialised whole it took
    2.5 GB before the transform cap counted."""
    from mcap.writer import CompressionType, Writer

    from imucal_cli.frames import TF_MSGTYPES, TF_TOPIC, tf_message, tf_typestore
    from imucal_cli.sim.writers import _msgdef, _Serialized
    from imucal_cli.types import Transform

    store = tf_typestore(False)

    def serialised(n: int) -> bytes:
        junk = tf_message(store, [("junk", "junk_child", Transform.identity())] * n, 1)
        return bytes(store.serialize_cdr(junk, TF_MSGTYPES[0]))

    one, two = serialised(1), serialised(2)
    size = len(two) - len(one)
    n = (megabytes << 20) // size
    # every 8th transform's x translation a random byte: about 800:1, as the file
    elements = np.frombuffer(two[len(one) :] * (n - 1), np.uint8).reshape(n - 1, size).copy()
    noise = np.random.default_rng(0).integers(0, 256, len(elements[::8]), dtype=np.uint8)
    elements[::8, size - 50] = noise
    bomb = one[:4] + n.to_bytes(4, "little") + one[8:] + elements.tobytes()
    topics = drive.topics()
    with path.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        writer.start(profile="ros2", library="probe")
        text, _ = store.generate_msgdef(TF_MSGTYPES[0], ros_version=2)
        schema = writer.register_schema(name=TF_MSGTYPES[0], encoding="ros2msg", data=text.encode())
        channel = writer.register_channel(topic=TF_TOPIC, message_encoding="cdr", schema_id=schema)
        writer.add_message(channel_id=channel, log_time=1, data=bomb, publish_time=1)
        imu = writer.register_schema(
            name="sensor_msgs/msg/Imu", encoding="ros2msg", data=_msgdef(False)[0].encode()
        )
        ids = {
            t: writer.register_channel(topic=t, message_encoding="cdr", schema_id=imu)
            for t in topics
        }
        blob = _Serialized(topics, False)
        for topic, data in topics.items():
            for i, stamp in enumerate(data.stream.t_ns.tolist()):
                writer.add_message(
                    channel_id=ids[topic], log_time=stamp, data=blob(topic, i), publish_time=stamp
                )
        writer.finish()
    return path


def sqlite3_recording(folder: Path, drive, other_rows: int) -> Path:
    """A rosbag2 folder still recording to sqlite3 (no metadata.yaml): ``other_rows`` rows of a
    topic nobody asked for first, then the drive's IMU messages."""
    import sqlite3

    from imucal_cli.sim.writers import _merged, _Serialized

    folder.mkdir()
    db = sqlite3.connect(folder / f"{folder.name}_0.db3")
    db.execute(
        "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
        "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL)"
    )
    db.execute(
        "CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp "
        "INTEGER NOT NULL, data BLOB NOT NULL)"
    )
    topics = drive.topics()
    ids = {topic: k + 2 for k, topic in enumerate(topics)}
    rows = [(1, "/camera/points", "sensor_msgs/msg/PointCloud2")]
    rows += [(i, t, "sensor_msgs/msg/Imu") for t, i in ids.items()]
    db.executemany("INSERT INTO topics VALUES (?, ?, ?, 'cdr', '')", rows)
    first = int(min(d.stream.t_ns[0] for d in topics.values()))
    db.executemany(
        "INSERT INTO messages(topic_id, timestamp, data) VALUES (1, ?, x'00000000')",
        ((first,) for _ in range(other_rows)),
    )
    blob = _Serialized(topics, False)
    db.executemany(
        "INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)",
        ((ids[t], log_ns, blob(t, i)) for log_ns, t, i in _merged(topics)),
    )
    db.commit()
    db.close()
    return folder


def mcap_claiming(path: Path, claimed: int, compression: str = "zstd", chunks: int = 40) -> Path:
    """Small real chunks each claiming ``claimed`` bytes."""
    data = (
        zstandard.ZstdCompressor().compress(bytes(1024))
        if compression == "zstd"
        else __import__("lz4.frame").frame.compress(bytes(1024))
    )
    return mcap_without_summary(path, [_mcap_chunk(claimed, compression, data)] * chunks)


def mcap_repeated_chunk_index(source: Path, path: Path, copies: int = 4096) -> Path:
    """A valid indexed MCAP whose summary lists its first chunk ``copies`` times."""
    from mcap.data_stream import RecordBuilder
    from mcap.reader import make_reader

    with source.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    data = source.read_bytes()
    (summary_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 20 - 9 + 9)
    builder = RecordBuilder()
    for schema in summary.schemas.values():
        schema.write(builder)
    for channel in summary.channels.values():
        channel.write(builder)
    first = sorted(summary.chunk_indexes, key=lambda i: i.chunk_start_offset)[0]
    for _ in range(copies):
        first.write(builder)
    body = builder.end()
    footer = _mcap_record(0x02, struct.pack("<QQI", summary_start, 0, 0))
    path.write_bytes(data[:summary_start] + bytes(body) + footer + b"\x89MCAP0\r\n")
    return path


def mcap_index_claiming(source: Path, path: Path, claimed: int) -> Path:
    """A valid indexed MCAP whose first chunk index (and chunk) claim ``claimed`` bytes."""
    from mcap.reader import make_reader

    with source.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    data = bytearray(source.read_bytes())
    first = sorted(summary.chunk_indexes, key=lambda i: i.chunk_start_offset)[0]
    old = struct.pack("<Q", first.uncompressed_size)
    for at in (
        first.chunk_start_offset + 9 + 16,
        data.index(struct.pack("<Q", first.compressed_size) + old) + 8,
    ):
        assert bytes(data[at : at + 8]) == old
        data[at : at + 8] = struct.pack("<Q", claimed)
    path.write_bytes(bytes(data))
    return path


def _ros1_record(fields: dict[str, bytes], data: bytes) -> bytes:
    header = b"".join(
        struct.pack("<I", len(k) + 1 + len(v)) + k.encode() + b"=" + v for k, v in fields.items()
    )
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(data)) + data


def ros1_bomb(path: Path, compression: str, claimed: int, data: bytes, chunks: int = 8) -> Path:
    """A ROS 1 bag without an index (index_pos 0: a recorder killed) whose chunks are bombs."""
    head = _ros1_record(
        {
            "op": b"\x03",
            "index_pos": struct.pack("<Q", 0),
            "conn_count": struct.pack("<I", 0),
            "chunk_count": struct.pack("<I", chunks),
        },
        b"",
    )
    head = head[:-4] + struct.pack("<I", 4096 - len(head)) + b" " * (4096 - len(head))
    chunk = _ros1_record(
        {"op": b"\x05", "compression": compression.encode(), "size": struct.pack("<I", claimed)},
        data,
    )
    path.write_bytes(b"#ROSBAG V2.0\n" + head + chunk * chunks)
    return path


def alias_bomb(path: Path, levels: int = 9) -> Path:
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    lines += [f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, levels + 1)]
    path.write_text("\n".join(lines) + "\n")
    return path


def with_topics(
    drive, change: Callable[[str, TopicData], TopicData | None]
) -> dict[str, TopicData]:
    out = {}
    for topic, data in drive.topics().items():
        changed = change(topic, data)
        if changed is not None:
            out[topic] = changed
    return out


def shifted(data: TopicData, from_fraction: float, by_ns: int) -> TopicData:
    t = data.stream.t_ns.copy()
    t[int(len(t) * from_fraction) :] += by_ns
    log = data.log_time_ns.copy() if data.log_time_ns is not None else t.copy()
    log[int(len(log) * from_fraction) :] += by_ns
    return TopicData(ImuStream(t, data.stream.gyro, data.stream.accel, data.stream.frame_id), log)


def cut(data: TopicData, seconds: float) -> TopicData:
    keep = data.stream.t_ns < data.stream.t_ns[0] + int(seconds * 1e9)
    s = data.stream
    return TopicData(
        ImuStream(s.t_ns[keep], s.gyro[keep], s.accel[keep], s.frame_id),
        data.log_time_ns[keep] if data.log_time_ns is not None else None,
    )


def nan_fraction(data: TopicData, fraction: float) -> TopicData:
    rng = np.random.default_rng(0)
    gyro = data.stream.gyro.copy()
    gyro[rng.random(len(gyro)) < fraction, 0] = np.nan
    s = data.stream
    order_free = ImuStream.__new__(ImuStream)
    for name, value in (
        ("t_ns", s.t_ns),
        ("gyro", gyro),
        ("accel", s.accel),
        ("frame_id", s.frame_id),
    ):
        object.__setattr__(order_free, name, value)
    return TopicData(order_free, data.log_time_ns)


# ------------------------------------------------------------------ the cases


def cases(work: Path) -> list[Case]:
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=7))
    config_doc = drive.config_document()
    base_topic, sensor_topic = list(drive.topics())[:2]
    out: list[Case] = []

    def folder(name: str) -> Path:
        path = work / name.replace(" ", "_").replace("/", "_")
        path.mkdir(parents=True)
        write_document(path / "config.yaml", config_doc)
        return path

    def log_in(
        path: Path, name: str = "d.mcap", fmt: str = "mcap", topics: dict | None = None
    ) -> Path:
        return write_imu_log(path / name, fmt, topics if topics is not None else drive.topics())

    def add(name: str, argv: list[str], path: Path, **kw) -> None:
        out.append(Case(name, argv, path, **kw))

    # 1-3 data loss
    f = folder("simulate into a folder")
    (f / "work").mkdir()
    (f / "work" / "thesis.tex").write_text("years of work")
    add("simulate DIR (an existing folder)", ["simulate", "work", "--duration", "2"], f, expect=2)
    add(
        "simulate DIR --force (not a log)",
        ["simulate", "work", "--duration", "2", "--force"],
        f,
        expect=2,
    )
    (f / "inner").mkdir()
    add(
        "simulate .. (the parent folder)",
        ["simulate", "..", "--duration", "2", "--force"],
        f / "inner",
        expect=2,
    )
    f = folder("batch of bags as metadata")
    for name in ("d1", "d2"):
        log_in(f, name, "rosbag2-mcap")
    add(
        "batch d1/metadata.yaml d2/metadata.yaml --out-dir .",
        ["batch", "d1/metadata.yaml", "d2/metadata.yaml", "-c", "config.yaml", "--out-dir", "."],
        f,
        outputs={"d1.yaml", "d2.yaml", "summary.csv", "summary.json"},
        expect=0,
    )
    f = folder("output is an input")
    log_in(f, "bag", "rosbag2-mcap")
    add(
        "calibrate bag/metadata.yaml -o bag/metadata.yaml",
        ["calibrate", "bag/metadata.yaml", "-c", "config.yaml", "-o", "bag/metadata.yaml"],
        f,
        expect=2,
    )
    add(
        "calibrate -o CONFIG",
        ["calibrate", "bag", "-c", "config.yaml", "-o", "config.yaml"],
        f,
        expect=2,
    )
    add(
        "segments -o inside the bag",
        ["segments", "bag", "-c", "config.yaml", "-o", "bag/x.yaml"],
        f,
        expect=2,
    )
    # 4-5 injection
    f = folder("frame injection")
    doc = dict(config_doc, base=dict(config_doc["base"], frame="x; touch pwned"))
    write_document(f / "evil.yaml", doc)
    log_in(f)
    add("base.frame 'x; touch pwned'", ["calibrate", "d.mcap", "-c", "evil.yaml"], f, expect=2)
    first = next(iter(config_doc["sensors"]))
    doc = dict(config_doc, sensors={"front\nleft": config_doc["sensors"][first]})
    write_document(f / "newline.yaml", doc)
    add("sensor name with a newline", ["check-config", "newline.yaml"], f, expect=2)
    f = folder("terminal escapes")
    evil = "/imu\x1b]0;owned\x07\x1b[2K\rcalibration ok"
    log_in(f, topics={(evil if t == base_topic else t): d for t, d in drive.topics().items()})
    add(
        "topic name with terminal escapes: inspect",
        ["inspect", "d.mcap"],
        f,
        expect=0,
        check=lambda r: "ESC on stdout" if b"\x1b" in r.stdout else "",
    )
    add(
        "topic name with terminal escapes: calibrate",
        ["calibrate", "d.mcap", "-c", "config.yaml"],
        f,
        expect=2,
        check=lambda r: "ESC on stderr" if b"\x1b" in r.stderr else "",
    )
    # 6-8 bombs
    f = folder("mcap bombs")
    mcap_zstd_bomb(f / "zstd.mcap")
    add(
        f"MCAP, no summary, zstd bomb ({(f / 'zstd.mcap').stat().st_size // 1000} kB -> 2.5 GiB)",
        ["inspect", "zstd.mcap"],
        f,
    )
    mcap_claiming(f / "claims.mcap", 6 << 30)
    add(
        "MCAP, no summary, chunks claiming 6 GiB",
        ["calibrate", "claims.mcap", "-c", "config.yaml"],
        f,
        expect=2,
    )
    mcap_claiming(f / "lz4.mcap", 8 << 30, "lz4")
    add("MCAP, no summary, lz4 chunks claiming 8 GiB", ["inspect", "lz4.mcap"], f)
    small = simulate_drive(DriveOptions(scenario="aggressive", duration_s=3.0, seed=7))
    source = write_imu_log(f / "small.mcap", "mcap", small.topics())
    mcap_repeated_chunk_index(source, f / "repeated.mcap")
    add(
        "indexed MCAP, 4096 chunk indexes on one chunk",
        ["calibrate", "repeated.mcap", "-c", "config.yaml"],
        f,
        expect=2,
    )
    mcap_index_claiming(source, f / "index-8g.mcap", 8 << 30)
    add(
        "indexed MCAP, a chunk and its index claiming 8 GiB",
        ["calibrate", "index-8g.mcap", "-c", "config.yaml"],
        f,
        expect=2,
    )
    f = folder("ros1 bombs")
    ros1_bomb(f / "bz2.bag", "bz2", 64 << 20, bz2.compress(bytes(64 << 20)))
    add(
        f"ROS 1 bag, bz2 chunks of 64 MiB zeros ({(f / 'bz2.bag').stat().st_size} bytes)",
        ["inspect", "bz2.bag"],
        f,
    )
    ros1_bomb(
        f / "lz4.bag", "lz4", 0xFFFFFFF0, __import__("lz4.frame").frame.compress(bytes(1 << 20))
    )
    add("ROS 1 bag, lz4 chunks claiming 4 GiB", ["inspect", "lz4.bag"], f)
    # 9 YAML
    f = folder("yaml bombs")
    log_in(f)
    alias_bomb(f / "bomb.yaml")
    (f / "deep.yaml").write_text("[" * 500 + "]" * 500 + "\n")
    (f / "big.yaml").write_text("base: {topic: /a}\nsensors: {}\n# " + "x" * (10 << 20) + "\n")
    for name in ("bomb", "deep", "big"):
        add(f"config: {name}.yaml", ["calibrate", "d.mcap", "-c", f"{name}.yaml"], f, expect=2)
    add("truth: bomb.yaml", ["evaluate", "bomb.yaml", "bomb.yaml"], f, expect=2)
    add(
        "reference: deep.yaml",
        ["batch", "d.mcap", "-c", "config.yaml", "--reference", "deep.yaml", "--out-dir", "o"],
        f,
        expect=2,
    )
    # 10 stamps' span
    for label, jump in (("10 days", 10 * 86400), ("1 year", 365 * 86400)):
        f = folder(f"clock jump {label}")
        log_in(
            f,
            topics=with_topics(
                drive,
                lambda t, d, jump=jump: shifted(d, 0.5, jump * 10**9) if t == base_topic else d,
            ),
        )
        add(f"inspect, base clock jumps {label} mid-log", ["inspect", "d.mcap"], f, expect=0)
        for command in ("biases", "segments", "calibrate"):
            add(
                f"{command}, base clock jumps {label} mid-log",
                [command, "d.mcap", "-c", "config.yaml"],
                f,
                expect=0,
            )
    # 11 config numbers
    f = folder("config numbers")
    log_in(f)
    for key, section, value in (
        ("window_s", "segments", 1e-6),
        ("resample_hz", "calibration", 1e5),
        ("resample_hz", "calibration", 1e9),
        ("rotation_floor_deg", None, 1e300),
    ):
        doc = dict(config_doc)
        if section:
            doc[section] = {key: value}
        else:
            doc["sensors"] = {n: dict(s, **{key: value}) for n, s in config_doc["sensors"].items()}
        name = f"{key}-{value:g}.yaml"
        write_document(f / name, doc)
        add(f"{key}: {value:g}", ["calibrate", "d.mcap", "-c", name], f, expect=2)
    doc = dict(
        config_doc,
        sensors={
            n: dict(
                s,
                T_imu_lidar=dict(
                    s["T_imu_lidar"],
                    translation=[v * 1000 for v in s["T_imu_lidar"]["translation"]],
                ),
            )
            for n, s in config_doc["sensors"].items()
        },
    )
    write_document(f / "mm.yaml", doc)
    add("T_imu_lidar translation in mm", ["calibrate", "d.mcap", "-c", "mm.yaml"], f, expect=2)
    # 12 a topic that stops
    long = simulate_drive(DriveOptions(scenario="aggressive", duration_s=600.0, seed=8))
    f = folder("topic stops")
    write_document(f / "config.yaml", long.config_document())
    stopping = list(long.topics())[1]
    log_in(f, topics=with_topics(long, lambda t, d: cut(d, 120.0) if t == stopping else d))
    add(
        "a lidar IMU stops after 120 s of 600 s",
        ["calibrate", "d.mcap", "-c", "config.yaml", "--json"],
        f,
        expect=0,
        check=lambda r: (
            "" if b"sent nothing from" in r.stdout else "no warning names the stopped topic"
        ),
    )
    # 13 tracebacks
    f = folder("tracebacks")
    log_in(f, "bag", "rosbag2-sqlite3")
    meta = f / "bag" / "metadata.yaml"
    info = yaml.safe_load(meta.read_text())
    info["rosbag2_bagfile_information"]["relative_file_paths"] = 7
    meta.write_text(yaml.safe_dump(info))
    add("rosbag2 relative_file_paths not a list", ["inspect", "bag"], f, expect=2)
    (f / "file").write_text("")
    add(
        "batch --out-dir that is a file",
        ["batch", "bag", "-c", "config.yaml", "--out-dir", "file"],
        f,
        expect=2,
    )
    write_document(
        f / "ref.yaml",
        {
            "sensors": {
                first: {
                    "rotation_std_deg": 3,
                    "T_base_lidar": {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1]},
                }
            }
        },
    )
    add(
        "--reference with a number where a list belongs",
        ["batch", "bag", "-c", "config.yaml", "--reference", "ref.yaml", "--out-dir", "o2"],
        f,
        expect=2,
    )
    est = {
        "base_frame": "base_link",
        "base_imu_rate_hz": 100.0,
        "base_imu_noise": "loud",
        "sensors": {
            first: {
                "status": "ok",
                "lidar_frame": "l",
                "T_base_lidar": {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1]},
                "T_base_imu": {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1]},
                "imu_rate_hz": 100.0,
            }
        },
    }
    write_document(f / "est.yaml", est)
    add(
        "kalibr export with a malformed imu_noise",
        ["export", "est.yaml", "-f", "kalibr"],
        f,
        expect=2,
    )
    # 14 fleet
    f = folder("fleet")
    for day in ("2024.01.05", "2024.01.06"):
        log_in(f, f"{day}.mcap")
    add(
        "batch of 2024.01.05.mcap and 2024.01.06.mcap",
        ["batch", "2024.01.05.mcap", "2024.01.06.mcap", "-c", "config.yaml", "--out-dir", "out"],
        f,
        outputs={
            "out/2024.01.05.yaml",
            "out/2024.01.06.yaml",
            "out/summary.csv",
            "out/summary.json",
        },
        expect=0,
    )
    add(
        "a second batch into the same --out-dir",
        ["batch", "2024.01.05.mcap", "-c", "config.yaml", "--out-dir", "out"],
        f,
        expect=2,
    )
    # interrupts: a Ctrl-C (exit 130) and a SIGTERM (143, issue 49) alike: no partial file,
    # nothing of the user's changed, the logs a batch finished summarised (issue 49, item 13)
    for sent, name, code in ((signal.SIGINT, "Ctrl-C", 130), (signal.SIGTERM, "SIGTERM", 143)):
        f = folder(f"interrupts by {name}")
        add(
            f"{name} during simulate (a 900 s drive)",
            ["simulate", "long.mcap", "--duration", "900", "--sensors", "4"],
            f,
            expect=code,
            signal_after_s=3.0,
            sent=sent,
        )
        first_log = log_in(f, "d0.mcap")
        for k in range(1, BATCH_LOGS):
            shutil.copyfile(first_log, f / f"d{k}.mcap")
        logs_and_jobs = [f"d{k}.mcap" for k in range(BATCH_LOGS)]
        logs_and_jobs += ["-c", "config.yaml", "--out-dir", "out", "--jobs", "2"]
        add(
            f"{name} during batch --jobs 2 ({BATCH_LOGS} logs)",
            ["batch", *logs_and_jobs],
            f,
            expect=code,
            signal_after_s=2.0,
            sent=sent,
            outputs={f"out/d{k}.yaml" for k in range(BATCH_LOGS)}
            | {"out/summary.csv", "out/summary.json"},
        )
    # issue 48, item 6: no file the user did not name in this run is replaced
    f = folder("files nobody named")
    log_in(f)
    (f / "mine.yaml").write_text("# my hand-written config\n")
    add("init -o an existing config", ["init", "d.mcap", "-o", "mine.yaml"], f, expect=2)
    log_in(f, "other", "rosbag2-mcap")
    for command in (["init", "d.mcap"], ["calibrate", "d.mcap", "-c", "config.yaml"]):
        add(
            f"{command[0]} -o the metadata of a bag not read",
            [*command, "-o", "other/metadata.yaml"],
            f,
            expect=2,
        )
    from imucal_cli.api import calibrate_streams
    from imucal_cli.outputs import calibration_document

    write_document(
        f / "est.yaml",
        calibration_document(calibrate_streams(drive.streams(), drive.config()), "d.mcap"),
    )
    (f / "robot.launch.xml").write_text("<launch><!-- mine --></launch>\n")
    add(
        "export tf-static-ros2 -o robot.sh beside a hand-written robot.launch.xml",
        ["export", "est.yaml", "-f", "tf-static-ros2", "-o", "robot.sh", "--allow-not-ok"],
        f,
        expect=2,
    )
    (f / "out").mkdir()
    add(
        "batch into an --out-dir another batch holds",
        ["batch", "d.mcap", "-c", "config.yaml", "--out-dir", "out"],
        f,
        expect=2,
        held="out",
    )
    # issue 48, item 7: a log's names never write keys into init's config, nor reach a terminal
    f = folder("names from a log")
    tree = [
        (parent, f"{parent[:9]}\n    prior_T_base_imu: {{translation: [9, 9, 9]}}\n    lidar", T)
        if child.endswith("lidar")
        else (parent, child, T)
        for parent, child, T in simulate_drive(
            DriveOptions(scenario="aggressive", duration_s=60.0, seed=7, tf_static=True)
        ).static_transforms()
    ]
    topics = dict(drive.topics()) | {"/evil\x1b]0;pwned\x07/imu": drive.topics()[sensor_topic]}
    write_imu_log(f / "d.mcap", "mcap", topics, tf_static=tree)

    def no_injected_key(result: subprocess.CompletedProcess, f: Path = f) -> str:
        if b"\x1b" in result.stdout or b"\x1b" in result.stderr:
            return "an escape reached the terminal"
        text = (f / "init.yaml").read_text() if (f / "init.yaml").exists() else result.stdout
        document = yaml.safe_load(text)
        priors = [s.get("prior_T_base_imu") for s in document["sensors"].values()]
        return (
            "a key written by the log"
            if any(p and p.get("translation") == [9, 9, 9] for p in priors)
            else ""
        )

    add(
        "init on a log whose frame names hold YAML",
        ["init", "d.mcap"],
        f,
        expect=0,
        check=no_injected_key,
    )
    add(
        "init -o on a log whose frame names hold YAML",
        ["init", "d.mcap", "-o", "init.yaml"],
        f,
        expect=0,
        outputs={"init.yaml"},
        check=no_injected_key,
    )
    # issue 49: what the priors, follow mode and signals let through
    f = folder("simulate an hour")
    add(
        "simulate --duration 3600 --sensors 4 (made as written)",
        ["simulate", "hour.mcap", "--duration", "3600", "--sensors", "4"],
        f,
        expect=0,
        outputs={"hour.mcap", "hour.truth.yaml", "hour.config.yaml"},
    )
    f = folder("urdf not a file")
    log_in(f)
    minimal = {
        "base": {k: config_doc["base"][k] for k in ("topic", "frame")},
        "sensors": {
            n: {k: s[k] for k in ("imu_topic", "lidar_frame")}
            for n, s in config_doc["sensors"].items()
        },
    }
    write_document(f / "min.yaml", minimal)
    os.mkfifo(f / "fifo.urdf")
    with (f / "sparse.urdf").open("wb") as handle:
        handle.truncate(1 << 40)
    for urdf in ("/dev/zero", "fifo.urdf", "sparse.urdf"):
        add(
            f"calibrate --urdf {urdf}",
            ["calibrate", "d.mcap", "-c", "min.yaml", "--urdf", urdf],
            f,
            expect=2,
        )
    f = folder("tf_static bomb")
    write_document(f / "min.yaml", minimal)
    mcap_tf_static_bomb(f / "d.mcap", drive)
    for command in (["calibrate", "d.mcap", "-c", "min.yaml"], ["init", "d.mcap"]):
        add(f"a /tf_static message of 200 MiB (2.4 M transforms): {command[0]}", command, f)
    f = folder("sqlite3 recording")
    sqlite3_recording(f / "rec", drive, 2_000_000)
    add(
        "follow a sqlite3 recording with 2 M rows of another topic",
        ["calibrate", "rec", "-c", "config.yaml", "--follow", "--timeout", "20"],
        f,
        expect=0,
    )
    f = folder("urdf values")
    write_document(f / "min.yaml", minimal)
    log_in(f)
    tree_urdf = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=60.0, seed=7, tf_static=True)
    ).urdf()
    first_xyz = tree_urdf.split('<origin xyz="', 1)[1].split('"', 1)[0]
    for name, value in (("nan", "nan 0 0"), ("huge", "1e308 1e308 0")):
        (f / f"{name}.urdf").write_text(
            tree_urdf.replace(f'xyz="{first_xyz}"', f'xyz="{value}"', 1)
        )
        add(
            f"URDF origin {value}",
            ["calibrate", "d.mcap", "-c", "min.yaml", "--urdf", f"{name}.urdf"],
            f,
            expect=2,
            check=lambda r: "" if b"RuntimeWarning" not in r.stderr else "numpy warned",
        )
    (f / "robot.urdf").write_text(tree_urdf)
    follow = ["--timeout", "20", "-o", "f.json"]

    def took_urdf(result: subprocess.CompletedProcess, f: Path = f) -> str:
        used = (f / "f.json").exists() and '"urdf"' in (f / "f.json").read_text()
        return "" if used else "the URDF was not used"

    add(
        "calibrate --follow --urdf (a finished recording with no /tf_static)",
        [*["calibrate", "d.mcap", "-c", "min.yaml", "--follow", "--urdf", "robot.urdf"], *follow],
        f,
        expect=0,
        outputs={"f.json"},
        check=took_urdf,
    )
    f = folder("tree")
    tree_drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=60.0, seed=7, tf_static=True)
    )
    write_document(f / "min.yaml", minimal)
    tree = tree_drive.static_transforms()
    write_imu_log(
        f / "loop.mcap",
        "mcap",
        drive.topics(),
        tf_static=[*tree, (tree[2][1], "base_link", tree[2][2])],
    )
    write_imu_log(
        f / "parents.mcap",
        "mcap",
        drive.topics(),
        tf_static=[*tree, ("odom", tree[2][1], tree[2][2])],
    )
    junk = [(f"junk{k}", f"junk{k}_child", tree[0][2]) for k in range(10_000)]
    write_imu_log(f / "capped.mcap", "mcap", drive.topics(), tf_static=junk + tree)
    for name in ("loop", "parents", "capped"):
        add(f"/tf_static: {name}", ["calibrate", f"{name}.mcap", "-c", "min.yaml"], f, expect=2)
    f = folder("yaml scalars")
    text = yaml.safe_dump(config_doc).replace("min_duration_s: 2.0", "min_duration_s: 2001-13-45")
    (f / "date.yaml").write_text(text)
    add("config holding the date 2001-13-45", ["check-config", "date.yaml"], f, expect=2)
    f = folder("empty record")
    data = log_in(f).read_bytes()
    (f / "d.mcap").unlink()
    # no summary, a Message record of 9 bytes after the header
    footer = len(data) - 8 - (1 + 8 + 8 + 8 + 4)
    (summary_start,) = struct.unpack_from("<Q", data, footer + 9)
    (header_length,) = struct.unpack_from("<Q", data, 9)
    at = 8 + 9 + header_length
    bare = data[:summary_start] + struct.pack("<BQQQI", 0x02, 20, 0, 0, 0) + data[-8:]
    (f / "empty.mcap").write_bytes(bare[:at] + struct.pack("<BQ", 0x05, 0) + bare[at:])
    add(
        "summary-less MCAP with an empty Message record",
        ["inspect", "empty.mcap"],
        f,
        expect=0,
        check=lambda r: "" if b"damaged" not in r.stderr else "said damaged",
    )
    f = folder("empty records")
    mcap_empty_records(f / "e.mcap")
    for command in (["inspect"], ["calibrate", "-c", "config.yaml"]):
        add(
            f"summary-less MCAP, a chunk of 29.8 M empty records: {command[0]}",
            [command[0], "e.mcap", *command[1:]],
            f,
        )
    f = folder("file-compressed bag")
    bag = log_in(f, "bag", "rosbag2-sqlite3")
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    for name in info["relative_file_paths"]:
        (bag / name).unlink()
        (bag / f"{name}.zstd").write_bytes(zstandard.ZstdCompressor().compress(bytes(200 << 20)))
    info |= {
        "relative_file_paths": [f"{n}.zstd" for n in info["relative_file_paths"]],
        "compression_format": "zstd",
        "compression_mode": "file",
    }
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    add("rosbag2 file-compressed bomb (200 MiB)", ["inspect", "bag"], f, expect=2)
    f = folder("follow garbage")
    data = log_in(f).read_bytes()
    footer = data.rindex(b"\x02" + (20).to_bytes(8, "little"))
    end = data.rindex(b"\x0f", 0, int.from_bytes(data[footer + 9 : footer + 17], "little"))
    garbage = bytes([0x42]) + (10**12).to_bytes(8, "little") + bytes(4 << 20)
    (f / "d.mcap").write_bytes(data[:end] + garbage)
    add(
        "follow a recording with garbage appended",
        ["calibrate", "d.mcap", "-c", "config.yaml", "--follow", "--timeout", "20"],
        f,
        expect=0,
        check=lambda r: "" if b"damaged" in r.stderr else "the damage is not said",
    )
    f = folder("init many channels")
    many = dict(drive.topics())
    for k in range(200):
        many[f"/lidar/extra_{k}/imu"] = many[sensor_topic]
    log_in(f, topics=many)
    add(
        "init on a log of 203 IMU channels",
        ["init", "d.mcap", "--base", base_topic],
        f,
        expect=0,
        check=lambda r: "" if r.stderr.count(b"\n") <= 42 else "unbounded lines",
    )
    # 15 damage said
    f = folder("damage said")
    log = log_in(f)
    data = log.read_bytes()
    (f / "half.mcap").write_bytes(data[: len(data) // 2])
    add(
        "biases on a log cut at 50%",
        ["biases", "half.mcap", "-c", "config.yaml"],
        f,
        expect=0,
        check=lambda r: (
            "" if b"warning" in r.stderr and b"cut off" in r.stderr else "the cut is not said"
        ),
    )
    log_in(
        f,
        "nan.mcap",
        topics=with_topics(drive, lambda t, d: nan_fraction(d, 0.3) if t == sensor_topic else d),
    )
    add(
        "30% NaN on one sensor",
        ["calibrate", "nan.mcap", "-c", "config.yaml", "--json"],
        f,
        expect=0,
        check=lambda r: "" if b"not finite" in r.stdout else "the dropped samples are not said",
    )
    return out


def probes(work: Path, only: str = "") -> bool:
    rows = []
    start = time.perf_counter()
    for case in cases(work):
        if only not in case.name:
            continue
        rows.append(run_case(case))
        shutil.rmtree(case.folder / "o", ignore_errors=True)
    print(f"## Probes of hostile input ({len(rows)} cases, {time.perf_counter() - start:.0f} s)\n")
    print(
        "Rule: exit 0 or 2 (2: one line, no traceback), no file of the user's changed, peak RSS "
        f"<= {MAX_RSS_MB:.0f} MB, "
        f"wall <= {BOUND_S:g} s + {BOUND_S_PER_MB:g} s per MB of input.\n"
    )
    print(
        "| case | exit | wall s | bound s | peak RSS MB | first error or last line on stderr | "
        "verdict |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        message = r["message"].replace("|", "/")
        message = message if len(message) <= 140 else message[:137] + "..."
        verdict = "ok" if not r["problems"] else "FAIL: " + "; ".join(r["problems"])
        print(
            f"| {r['case']} | {r['exit']} | {r['wall']:.1f} | {r['bound']:.0f} | {r['rss']:.0f} | "
            f"{message} | {verdict} |"
        )
    failed = sum(bool(r["problems"]) for r in rows)
    print(f"\nCases failing the rule: {failed} of {len(rows)}.\n")
    sys.stdout.flush()
    return failed == 0
