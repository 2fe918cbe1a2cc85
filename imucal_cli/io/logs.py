"""Opening every log a user has: :func:`open_log` picks the container's reader from the path
and the table of formats (:mod:`.formats`). Readers yield raw batches of one topic;
:mod:`.imu_msg` decodes them; :mod:`imucal_cli.reading` streams, screens and counts the samples.
"""

from __future__ import annotations

from pathlib import Path

from imucal_cli.errors import LogError
from imucal_cli.io.base import LogReader, Loss, TopicInfo
from imucal_cli.io.formats import by_magic, by_suffix
from imucal_cli.io.imu_msg import IMU_MSGTYPE
from imucal_cli.io.mcap_log import McapLog
from imucal_cli.io.rosbag1 import Ros1Log
from imucal_cli.io.rosbag2 import Rosbag2Log, SqliteRecording

__all__ = ["IMU_MSGTYPE", "LogReader", "Loss", "TopicInfo"]  # (the readers' words, re-exported)
__all__ += ["check_topics", "open_log", "open_recording"]


#: The reader of each container (:data:`imucal_cli.io.formats.FORMATS`); a rosbag2 folder is
#: known by being a folder.
READERS: dict[str, type[LogReader]] = {"mcap": McapLog, "rosbag1": Ros1Log}


def open_log(path: str | Path) -> LogReader:
    """Open a log for reading, picking the reader from the path. Raises :class:`LogError`."""
    path = Path(path)
    if not path.exists():
        raise LogError(str(path), "no such file or directory")
    if path.is_dir() or path.name == "metadata.yaml" or ".db3" in path.suffixes:
        return Rosbag2Log(path)
    try:
        with path.open("rb") as handle:
            head = handle.read(16)
    except OSError as exc:
        raise LogError(str(path), f"cannot open: {exc.strerror}") from None
    found = by_magic(head) or by_suffix(path.suffix)
    if found is not None and found.container in READERS:
        return READERS[found.container](path)
    raise LogError(
        str(path), "unknown log format (expected a .mcap file, a ROS 1 .bag or a rosbag2 folder)"
    )


def check_topics(log: LogReader, wanted: list[str]) -> dict[str, TopicInfo]:
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


def open_recording(path: Path) -> LogReader:
    """The reader of a recording in progress: an MCAP file, or a rosbag2 folder with one
    storage file (mcap, read as it grows; sqlite3, read as rows are committed)."""
    if path.is_dir():
        files = sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3"))
        if len(files) != 1:
            raise LogError(
                str(path),
                f"follow mode reads a rosbag2 folder with one storage file; it has {len(files)}",
            )
        return McapLog(files[0]) if files[0].suffix == ".mcap" else SqliteRecording(path, files[0])
    if not path.exists():
        raise LogError(str(path), "no such file or directory")
    return McapLog(path)
