"""A truthful recorder for follow-mode tests: a simulated drive written into an MCAP file (or a
rosbag2 folder recording to mcap storage) at F times real time, as a recorder writes it: chunks
appended as they fill and flushed, the summary only at the end (or never, when it dies)."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

from imucal_cli.sim.writers import (
    _first_ns,
    _mcap_static,
    _merged,
    _msgdef,
    _Serialized,
    _statics,
)

IMU_SCHEMA = "sensor_msgs/msg/Imu"


class Recorder(threading.Thread):
    def __init__(
        self,
        path: Path,
        topics,
        factor: float,
        die_after_s: float | None = None,
        chunk_size: int = 64 << 10,
        tf_static=(),
    ) -> None:
        super().__init__(daemon=True)
        self.path, self.topics, self.factor, self.die_after_s, self.chunk_size = (
            path,
            topics,
            factor,
            die_after_s,
            chunk_size,
        )
        self.tf_static = tf_static  # written first, as a recorder gets the latched /tf_static
        self.finished = threading.Event()  # the summary written
        self.started_writing = threading.Event()

    def run(self) -> None:
        from mcap.writer import Writer

        msgdef, _ = _msgdef(False)
        blob = _Serialized(self.topics, False)
        with self.path.open("wb") as handle:
            writer = Writer(handle, chunk_size=self.chunk_size)
            writer.start(profile="ros2", library="recorder")
            schema = writer.register_schema(
                name=IMU_SCHEMA, encoding="ros2msg", data=msgdef.encode()
            )
            channels = {
                t: writer.register_channel(topic=t, message_encoding="cdr", schema_id=schema)
                for t in self.topics
            }
            for static in _statics(self.tf_static, None, self.topics, False):
                _mcap_static(writer, static, _first_ns(self.topics), False)
            handle.flush()
            self.started_writing.set()
            start_wall, start_log = time.monotonic(), None
            for log_ns, topic, i in _merged(self.topics):
                start_log = log_ns if start_log is None else start_log
                elapsed_log = (log_ns - start_log) * 1e-9
                if self.die_after_s is not None and elapsed_log > self.die_after_s:
                    handle.flush()
                    size = handle.tell()
                    handle.truncate(
                        size - 100
                    )  # the last chunk cut mid-write, no summary: a killed recorder
                    return
                wait = start_wall + elapsed_log / self.factor - time.monotonic()
                if wait > 0.005:
                    handle.flush()
                    time.sleep(wait)
                writer.add_message(
                    channel_id=channels[topic],
                    log_time=log_ns,
                    data=blob(topic, i),
                    publish_time=log_ns,
                )
            writer.finish()
        self.finished.set()


def record(path: Path, drive, factor: float, **options) -> Recorder:
    recorder = Recorder(path, drive.topics(), factor, **options)
    recorder.start()
    recorder.started_writing.wait(30)
    return recorder


class SqliteRecorder(threading.Thread):
    """A rosbag2 folder recorded to sqlite3 storage as ros2 bag does: the tables first, rows
    committed as they come (every 50 ms here), ``metadata.yaml`` only when it stops."""

    def __init__(self, folder: Path, topics, factor: float) -> None:
        super().__init__(daemon=True)
        self.folder, self.topics, self.factor = folder, topics, factor
        self.finished = threading.Event()
        self.started_writing = threading.Event()

    def run(self) -> None:
        import sqlite3

        blob = _Serialized(self.topics, False)
        self.folder.mkdir(exist_ok=True)
        connection = sqlite3.connect(
            self.folder / f"{self.folder.name}_0.db3", check_same_thread=False
        )
        connection.execute(
            "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
            "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL)"
        )
        connection.execute(
            "CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp "
            "INTEGER NOT NULL, data BLOB NOT NULL)"
        )
        ids = {topic: k + 1 for k, topic in enumerate(self.topics)}
        connection.executemany(
            "INSERT INTO topics VALUES (?, ?, ?, 'cdr', '')",
            [(i, t, IMU_SCHEMA) for t, i in ids.items()],
        )
        connection.commit()
        self.started_writing.set()
        start_wall, start_log, pending = time.monotonic(), None, []
        for log_ns, topic, i in _merged(self.topics):
            start_log = log_ns if start_log is None else start_log
            wait = start_wall + (log_ns - start_log) * 1e-9 / self.factor - time.monotonic()
            if wait > 0.05:
                connection.executemany(
                    "INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)", pending
                )
                connection.commit()
                pending = []
                time.sleep(wait)
            pending.append((ids[topic], log_ns, blob(topic, i)))
        connection.executemany(
            "INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)", pending
        )
        connection.commit()
        connection.close()
        (self.folder / "metadata.yaml").write_text(
            "rosbag2_bagfile_information: {version: 5, storage_identifier: sqlite3}\n"
        )
        self.finished.set()


def with_terminal_sigint(argv: list[str]) -> list[str]:
    """``argv`` run with SIGINT as a terminal gives it: a background job (a CI runner's
    included) starts its children with SIGINT ignored, and Python then takes no Ctrl-C. A
    launcher restores the default and execs ``argv`` (a default survives exec)."""
    restore = (
        "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
        "os.execv(sys.argv[1], sys.argv[1:])"
    )
    return [sys.executable, "-c", restore, *argv]
