"""Every log format, in one table (as rosbags' ``STORAGE_PLUGINS``): what ``open_log``
recognises, what ``batch`` strips from a log's name, what ``simulate --format`` writes, and
what the help says. Importing it imports nothing else (``imucal --help`` reads it).
"""

from __future__ import annotations

from dataclasses import dataclass

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"


@dataclass(frozen=True)
class LogFormat:
    name: str
    #: The file's suffix; None: a rosbag2 folder (its storage files inside).
    suffix: str | None
    #: The first bytes of the file (None: a folder).
    magic: bytes | None
    #: The reader of its container: ``mcap``, ``rosbag2`` or ``rosbag1`` (:mod:`.logs`).
    container: str
    #: The messages' serialisation: ``cdr`` (ROS 2) or ``ros1``.
    encoding: str
    #: A rosbag2 folder's storage (``sqlite3``, ``mcap``), else None.
    storage: str | None = None


FORMATS = {
    f.name: f
    for f in (
        LogFormat("mcap", ".mcap", MCAP_MAGIC, "mcap", "cdr"),
        LogFormat("mcap-ros1", ".mcap", MCAP_MAGIC, "mcap", "ros1"),
        LogFormat("rosbag2-sqlite3", None, None, "rosbag2", "cdr", "sqlite3"),
        LogFormat("rosbag2-mcap", None, None, "rosbag2", "cdr", "mcap"),
        LogFormat("rosbag1", ".bag", ROSBAG1_MAGIC, "rosbag1", "ros1"),
    )
}
#: The suffixes of log files (a rosbag2 folder's storage files among them).
LOG_SUFFIXES = (
    *dict.fromkeys(f.suffix for f in FORMATS.values() if f.suffix),
    ".db3",
)
#: The files a rosbag2 folder holds besides its ``metadata.yaml`` (its storage, with SQLite's
#: side files).
ROSBAG2_FILES = (".db3", ".mcap", ".db3-shm", ".db3-wal", ".db3-journal", ".zstd")


def by_suffix(suffix: str) -> LogFormat | None:
    """The first format whose files end in ``suffix`` (``.mcap``: plain MCAP)."""
    return next((f for f in FORMATS.values() if f.suffix == suffix.lower()), None)


def by_magic(head: bytes) -> LogFormat | None:
    """The format whose magic bytes ``head`` starts with."""
    return next((f for f in FORMATS.values() if f.magic and head.startswith(f.magic)), None)
