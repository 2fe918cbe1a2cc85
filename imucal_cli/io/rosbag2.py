"""rosbag2 folders (sqlite3 or mcap storage), opened with ``rosbags``: its metadata, and its
messages one at a time, but for uncompressed mcap storage, which
:class:`~imucal_cli.io.mcap_log.McapLog` reads (6x faster, and up to a killed recorder's cut)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from imucal_cli.errors import LogError
from imucal_cli.io.base import MAX_RATIO, Batcher, LogReader, Loss, TopicInfo
from imucal_cli.io.imu_msg import RawBatch
from imucal_cli.io.mcap_log import McapLog

REINDEX = "`ros2 bag reindex FOLDER` rebuilds a missing or broken metadata.yaml"
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
            try:
                self._reader = Reader(self.path)
                self._reader.open()
            except Exception as exc:
                raise self.error(
                    f"cannot read the rosbag2 folder: {exc}; {REINDEX}; `sqlite3 FILE.db3 "
                    ".recover` salvages a damaged database"
                ) from None

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

    def batches(self, topics: Iterable[str]) -> Iterator[RawBatch]:
        wanted = set(topics)
        if self._reader is None:
            for log in self._storage:
                yield from log.batches(wanted)
            return
        connections = [c for c in self._reader.connections if c.topic in wanted]
        batcher = Batcher()
        try:
            for conn, timestamp, data in self._reader.messages(connections=connections):
                encoding = getattr(conn.ext, "serialization_format", "cdr")
                yield from batcher.add(conn.topic, encoding, int(timestamp), bytes(data))
        except Exception as exc:
            raise self.error(
                f"cannot read its messages: {exc}; `sqlite3 FILE.db3 .recover` salvages a damaged "
                "database"
            ) from None
        yield from batcher.rest()


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
        import sqlite3
        import time

        wanted, ids, last = set(topics), {}, 0  # type: ignore[var-annotated]
        while True:
            finished = (self.path / "metadata.yaml").is_file()  # before the read: no row is missed
            rows: list[tuple[int, int, int, bytes]] = []
            try:  # the wanted topics' rows only, a block at a time (10 M rows of another: 1.7 GB)
                with sqlite3.connect(f"file:{self.db}?mode=ro", uri=True, timeout=1.0) as db:
                    query = "SELECT id, name, serialization_format FROM topics"
                    ids = {t: (n, f) for t, n, f in db.execute(query) if n in wanted}
                    query = "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? AND "
                    query += f"topic_id IN ({','.join('?' * len(ids))}) ORDER BY id LIMIT ?"
                    rows = db.execute(query, (last, *ids, FOLLOW_ROWS)).fetchall() if ids else []
            except sqlite3.OperationalError:  # locked by the recorder, or no table yet: try again
                pass
            if rows:
                last = rows[-1][0]
                batcher = Batcher()
                for _, topic_id, stamp, data in rows:
                    if topic_id in ids:
                        yield from batcher.add(*ids[topic_id], int(stamp), bytes(data))
                yield from batcher.rest()
            elif finished or stop():
                return
            else:
                time.sleep(poll_s)
