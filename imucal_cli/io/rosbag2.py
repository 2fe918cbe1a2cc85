"""rosbag2 folders (sqlite3 or mcap storage): uncompressed mcap storage read by
:class:`~imucal_cli.io.mcap_log.McapLog` (6x faster than ``rosbags``, and up to a killed
recorder's cut), uncompressed sqlite3 storage with the ``sqlite3`` module (``rosbags`` counts
every topic's messages when it opens a file, a scan of the whole database each time), anything
compressed through ``rosbags``, one message at a time."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterable, Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

from imucal_cli.errors import LogError
from imucal_cli.io.base import MAX_RATIO, LogReader, Loss, TopicInfo, in_blocks
from imucal_cli.io.imu_msg import RawBatch
from imucal_cli.io.mcap_log import McapLog

REINDEX = "`ros2 bag reindex FOLDER` rebuilds a missing or broken metadata.yaml"
RECOVER = "`sqlite3 FILE.db3 .recover` salvages a damaged database"
_UNREADABLE = "cannot read the rosbag2 folder: {}; " + REINDEX + "; " + RECOVER
FOLLOW_ROWS = 65536  # rows a recording is read in


def bag_folder(path: Path) -> Path:
    """The bag folder of a path given as the folder or as its ``metadata.yaml``; a
    :class:`LogError` that says what to give for anything else."""
    if path.is_file() and path.name == "metadata.yaml":
        return path.parent
    if path.is_dir():
        return path
    raise LogError(
        str(path), f"a rosbag2 storage file: give its bag folder ({path.parent}) instead"
    )


def _metadata(folder: Path) -> tuple[dict[str, Any] | None, str]:
    """The folder's bag information, or None and why not."""
    import yaml

    try:
        info = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    except FileNotFoundError:
        return None, "it has no metadata.yaml"
    except Exception as exc:
        return None, f"its metadata.yaml does not read ({type(exc).__name__}: {exc})"
    return (
        (info, "")
        if isinstance(info, dict)
        else (None, "its metadata.yaml holds no bag information")
    )


class Rosbag2Log(LogReader):
    """A rosbag2 folder. Uncompressed mcap storage is read file by file as MCAP (also where
    ``metadata.yaml`` is missing, as a killed recorder leaves it); everything else through
    ``rosbags``."""

    def __init__(self, path: Path) -> None:
        super().__init__(bag_folder(path))
        info, why = _metadata(self.path)
        mcaps = sorted(self.path.glob("*.mcap"))
        self._reader: Any = None
        self._storage: list[McapLog] = []
        #: Uncompressed sqlite3 storage: each file with its topics (id: name, type, format).
        self._sqlite: list[tuple[Path, dict[int, tuple[str, str, str]]]] = []
        self._counts: dict[str, int] = {}
        if info is None:
            if not mcaps:
                raise self.error(f"not a readable rosbag2 folder: {why}; {REINDEX}")
            self.losses.append(
                Loss(f"{why}: its {len(mcaps)} mcap storage file(s) read directly", lost=False)
            )
            self.format_name = "rosbag2-mcap"
            self._storage = [McapLog(f) for f in mcaps]
            return
        relative = info.get("relative_file_paths") or []
        if not isinstance(relative, list) or not all(isinstance(p, str) for p in relative):
            raise self.error(
                f"metadata.yaml: relative_file_paths is not a list of file names; {REINDEX}"
            )
        files = [self.path / Path(p).name for p in relative]
        if info.get("storage_identifier") == "mcap" and not info.get("compression_format"):
            self.format_name = "rosbag2-mcap"
            missing = [f.name for f in files if not f.is_file()]
            if missing:
                raise self.error(f"storage file {missing[0]} of metadata.yaml is missing")
            self._storage = [McapLog(f) for f in files]
        else:
            from rosbags.rosbag2 import Reader

            if any(f.exists() and not f.is_file() for f in files):  # (a FIFO blocks sqlite)
                raise self.error("a storage file is not a regular file (a FIFO?)")
            if info.get("compression_mode") == "file":
                self._inflatable(files)
            self.format_name = f"rosbag2-{info.get('storage_identifier', '?')}"
            if info.get("storage_identifier") == "sqlite3" and not info.get("compression_format"):
                try:
                    self._sqlite = [(f, _sqlite_topics(f)) for f in files]
                except Exception as exc:
                    raise self.error(_UNREADABLE.format(exc)) from None
                self._counts = _metadata_counts(info)
                return
            try:
                self._reader = Reader(self.path)
                self._reader.open()
            except Exception as exc:
                raise self.error(_UNREADABLE.format(exc)) from None

    def _inflatable(self, files: list[Path]) -> None:
        """A file-compressed bag, which rosbags inflates whole into TMPDIR (130 kB: 4 GiB): each
        file's size decompressed to nowhere first, held to MAX_RATIO times its own and the room."""
        import shutil
        import tempfile

        import zstandard

        room, inflated = shutil.disk_usage(tempfile.gettempdir()).free, zstandard.ZstdDecompressor()
        for path in files:
            size, limit = 0, min(MAX_RATIO * path.stat().st_size, room) if path.is_file() else 0
            try:
                with path.open("rb") as f, inflated.stream_reader(f) as z:
                    while size <= limit and (piece := z.read(1 << 20)):
                        size += len(piece)
            except (OSError, zstandard.ZstdError) as exc:
                raise self.error(f"{path.name} does not decompress: {exc}") from None
            if size > limit:
                raise self.error(f"{path.name} decompresses to more than {limit:,} bytes")

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
        for log in self._storage:
            log.close()

    def topics(self) -> dict[str, TopicInfo]:
        if self._sqlite:
            return self._sqlite_info()
        out: dict[str, TopicInfo] = {}
        if self._reader is None:
            for log in self._storage:
                for topic, info in log.topics().items():
                    count = info.count + (out[topic].count if topic in out else 0)
                    out[topic] = TopicInfo(topic, info.msgtype, count, info.encoding)
                self.losses.extend(x for x in log.losses if x.lost)
            return out
        for conn in self._reader.connections:
            count = int(conn.msgcount) + (out[conn.topic].count if conn.topic in out else 0)
            out[conn.topic] = TopicInfo(
                conn.topic, conn.msgtype, count, getattr(conn.ext, "serialization_format", "cdr")
            )
        return out

    def _sqlite_info(self) -> dict[str, TopicInfo]:
        """The sqlite3 files' topics, counted as ``metadata.yaml`` counts them (what ``ros2 bag
        info`` prints; a scan of every file to count them took 2 CPU-s an hour of five IMUs)."""
        found = {name: (t, fmt) for _, topics in self._sqlite for name, t, fmt in topics.values()}
        return {n: TopicInfo(n, t, self._counts.get(n, 0), f) for n, (t, f) in found.items()}

    def _sqlite_batches(self, wanted: set[str]) -> Iterator[RawBatch]:
        """The wanted topics' messages, file by file in time order (as ``rosbags`` reads them),
        a block of rows at a time."""
        for path, found in self._sqlite:
            ids = _wanted(found, wanted)
            if not ids:
                continue
            with _connect(path) as db:
                query = "SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({}) "
                marks = ",".join("?" * len(ids))
                yield from in_blocks(
                    db.execute(query.format(marks) + "ORDER BY timestamp", (*ids,)), ids
                )

    def batches(self, topics: Iterable[str]) -> Iterator[RawBatch]:
        wanted = set(topics)
        if self._sqlite:
            try:
                yield from self._sqlite_batches(wanted)
            except Exception as exc:
                raise self.error(f"cannot read its messages: {exc}; {RECOVER}") from None
            return
        if self._reader is None:
            for log in self._storage:
                yield from log.batches(wanted)
            return
        connections = [c for c in self._reader.connections if c.topic in wanted]
        topic_of = {
            c.id: (c.topic, getattr(c.ext, "serialization_format", "cdr")) for c in connections
        }
        try:  # (rosbags reads every topic for no connection)
            messages = self._reader.messages(connections=connections) if connections else ()
            yield from in_blocks(((c.id, int(t), data) for c, t, data in messages), topic_of)
        except Exception as exc:
            raise self.error(f"cannot read its messages: {exc}; {RECOVER}") from None


def _connect(path: Path, timeout: float = 5.0) -> closing[sqlite3.Connection]:
    """``path`` opened read-only (its name percent-encoded in the URI), closed after use."""
    return closing(sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=timeout))


def _topics_table(db: sqlite3.Connection) -> dict[int, tuple[str, str, str]]:
    """A storage file's topics table: id -> (name, type, serialization format)."""
    rows = db.execute("SELECT id, name, type, serialization_format FROM topics").fetchall()
    return {int(i): (str(name), str(msgtype), str(fmt)) for i, name, msgtype, fmt in rows}


def _sqlite_topics(path: Path) -> dict[int, tuple[str, str, str]]:
    with _connect(path) as db:
        return _topics_table(db)


def _wanted(found: dict[int, tuple[str, str, str]], wanted: set[str]) -> dict[int, tuple[str, str]]:
    """The ids of the ``wanted`` topics of a topics table, each with its name and format."""
    return {i: (name, fmt) for i, (name, _, fmt) in found.items() if name in wanted}


def _metadata_counts(info: dict[str, Any]) -> dict[str, int]:
    """The message count per topic ``metadata.yaml`` gives (an entry not whole is left out)."""
    out: dict[str, int] = {}
    for entry in info.get("topics_with_message_count") or []:
        try:
            name, count = str(entry["topic_metadata"]["name"]), int(entry["message_count"])
        except (TypeError, KeyError, ValueError):
            continue
        out[name] = out.get(name, 0) + count
    return out


class SqliteRecording(LogReader):
    """A rosbag2 folder recording to sqlite3 storage (follow mode): rows read as they are
    committed, until the recorder writes ``metadata.yaml`` (it does when it stops)."""

    format_name = "rosbag2-sqlite3 (recording)"

    def __init__(self, folder: Path, db: Path) -> None:
        super().__init__(folder)
        self.db = db

    def follow(
        self, topics: Iterable[str], stop: Callable[[], bool], poll_s: float = 0.05
    ) -> Iterator[RawBatch]:
        import time

        wanted, last = set(topics), 0
        ids: dict[int, tuple[str, str]] = {}
        while True:
            finished = (self.path / "metadata.yaml").is_file()  # before the read: no row is missed
            rows: list[tuple[int, int, int, bytes]] = []
            try:  # the wanted topics' rows only, a block at a time (10 M rows of another: 1.7 GB)
                with _connect(self.db, timeout=1.0) as db:
                    ids = _wanted(_topics_table(db), wanted)
                    query = "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? AND "
                    query += f"topic_id IN ({','.join('?' * len(ids))}) ORDER BY id LIMIT ?"
                    rows = db.execute(query, (last, *ids, FOLLOW_ROWS)).fetchall() if ids else []
            except sqlite3.OperationalError:  # locked by the recorder, or no table yet: try again
                pass
            if rows:
                last = rows[-1][0]
                yield from in_blocks(((i, int(t), d) for _, i, t, d in rows if i in ids), ids)
            elif finished or stop():
                return
            else:
                time.sleep(poll_s)
