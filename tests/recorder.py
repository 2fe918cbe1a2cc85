"""A truthful recorder for follow-mode tests: a simulated drive written into an MCAP file (or a
rosbag2 folder recording to mcap storage) at F times real time, as a recorder writes it: chunks
appended as they fill and flushed, the summary only at the end (or never, when it dies)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from imucal_cli.sim.writers import _messages, _msgdef, _serialized

IMU_SCHEMA = "sensor_msgs/msg/Imu"


class Recorder(threading.Thread):
    def __init__(self, path: Path, topics, factor: float, die_after_s: float | None = None, chunk_size: int = 64 << 10) -> None:
        super().__init__(daemon=True)
        self.path, self.topics, self.factor, self.die_after_s, self.chunk_size = path, topics, factor, die_after_s, chunk_size
        self.finished = threading.Event()  # the summary written
        self.started_writing = threading.Event()

    def run(self) -> None:
        from mcap.writer import Writer

        msgdef, _ = _msgdef(False)
        blobs = _serialized(self.topics, False)
        with self.path.open("wb") as handle:
            writer = Writer(handle, chunk_size=self.chunk_size)
            writer.start(profile="ros2", library="recorder")
            schema = writer.register_schema(name=IMU_SCHEMA, encoding="ros2msg", data=msgdef.encode())
            channels = {t: writer.register_channel(topic=t, message_encoding="cdr", schema_id=schema) for t in self.topics}
            handle.flush()
            self.started_writing.set()
            start_wall, start_log = time.monotonic(), None
            for log_ns, topic, i in _messages(self.topics):
                start_log = log_ns if start_log is None else start_log
                elapsed_log = (log_ns - start_log) * 1e-9
                if self.die_after_s is not None and elapsed_log > self.die_after_s:
                    handle.flush()
                    size = handle.tell()
                    handle.truncate(size - 100)  # the last chunk cut mid-write, no summary: a killed recorder
                    return
                wait = start_wall + elapsed_log / self.factor - time.monotonic()
                if wait > 0.005:
                    handle.flush()
                    time.sleep(wait)
                writer.add_message(channel_id=channels[topic], log_time=log_ns, data=blobs[topic][i].tobytes(), publish_time=log_ns)
            writer.finish()
        self.finished.set()


def record(path: Path, drive, factor: float, **options) -> Recorder:
    recorder = Recorder(path, drive.topics(), factor, **options)
    recorder.start()
    recorder.started_writing.wait(30)
    return recorder
