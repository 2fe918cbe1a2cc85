"""ROS 1 bags (format 2.0), read through the bag's own index (its connection and chunk-info
records, then each chunk's index data as numpy arrays: ``rosbags``, a message at a time, took
10x a calibration); a bag whose index is missing or unusable (a killed recorder) is walked
record by record from the start up to the cut, which is a :class:`Loss`."""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from imucal_cli.io.base import LogReader, Loss, TopicInfo, decompress, in_blocks, interleaved
from imucal_cli.io.formats import ROSBAG1_MAGIC
from imucal_cli.io.imu_msg import RawBatch, gather

MAGIC = ROSBAG1_MAGIC
REPAIR = "`rosbag reindex FILE` rebuilds its index"
_U32 = struct.Struct("<I")
_INDEX_ENTRY = np.dtype([("sec", "<u4"), ("nsec", "<u4"), ("offset", "<u4")])
#: Chunks decoded together (as in :mod:`imucal_cli.io.mcap_log`; ROS 1 chunks hold 768 KiB).
GROUP_CHUNKS = 16


def _fields(header: bytes) -> dict[str, bytes]:
    out, pos = {}, 0
    while pos + 4 <= len(header):
        (n,) = _U32.unpack_from(header, pos)
        name, _, value = header[pos + 4 : pos + 4 + n].partition(b"=")
        out[name.decode("latin-1")] = value
        pos += 4 + n
    return out


def _record(buf: bytes | memoryview, pos: int) -> tuple[dict[str, bytes], int, int, int]:
    """The record at ``pos``: its header fields, where its data start, its data length and
    where the next record starts. ``ValueError`` where it runs past the buffer."""
    if pos + 4 > len(buf):
        raise ValueError("record header cut off")
    (header_len,) = _U32.unpack_from(buf, pos)
    if pos + 8 + header_len > len(buf):
        raise ValueError("record header cut off")
    fields = _fields(bytes(buf[pos + 4 : pos + 4 + header_len]))
    (data_len,) = _U32.unpack_from(buf, pos + 4 + header_len)
    start = pos + 8 + header_len
    if start + data_len > len(buf):
        raise ValueError("record data cut off")
    return fields, start, data_len, start + data_len


def _op(fields: dict[str, bytes]) -> int:
    return fields.get("op", b"\xff")[0]


class Ros1Log(LogReader):
    format_name = "rosbag1"

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self._file: BinaryIO = path.open("rb")
        self._size = self._file.seek(0, 2)
        self._file.seek(0)
        if self._file.read(len(MAGIC)) != MAGIC:
            self._file.close()
            raise self.error("not a ROS 1 bag (bad magic bytes; only format 2.0 is read)")
        self.connections: dict[int, tuple[str, str]] = {}  # conn id -> (topic, type)
        self.counts: dict[int, int] = {}
        self.chunks: list[tuple[int, dict[int, int]]] = []  # (position, messages per conn)
        try:
            self._read_index()
        except Exception as exc:
            self.chunks = []
            self.losses.append(
                Loss(f"its index cannot be used ({exc}): read record by record", lost=False)
            )
            self._walk_counts()

    def close(self) -> None:
        self._file.close()

    def _read_index(self) -> None:
        head = self._read(len(MAGIC), 4096 + 8)
        fields, _, _, _ = _record(head, 0)
        (index_pos,) = struct.unpack("<Q", fields["index_pos"])
        if not len(MAGIC) < index_pos < self._size:
            raise ValueError(
                f"index_pos {index_pos} is outside the file (cut off while recording?)"
            )
        tail = self._read(index_pos, self._size - index_pos)
        pos, seen = 0, set()
        while pos < len(tail):
            fields, start, length, pos = _record(tail, pos)
            if _op(fields) == 0x07:
                self._connection(fields, tail[start : start + length])
            elif _op(fields) == 0x06:
                (chunk_pos,) = struct.unpack("<Q", fields["chunk_pos"])
                if (
                    not len(MAGIC) <= chunk_pos < index_pos or chunk_pos in seen
                ):  # (each chunk read once: bounded work)
                    raise ValueError(
                        f"the index names a chunk at byte {chunk_pos} "
                        f"{'twice' if chunk_pos in seen else 'outside the chunks'}"
                    )
                seen.add(chunk_pos)
                entries = np.frombuffer(tail, "<u4", length // 4, start).reshape(-1, 2)
                per_conn = {int(c): int(n) for c, n in entries}
                self.chunks.append((chunk_pos, per_conn))
                for c, n in per_conn.items():
                    self.counts[c] = self.counts.get(c, 0) + n
        if not self.connections:
            raise ValueError("the index lists no connection")

    def _connection(self, fields: dict[str, bytes], data: bytes) -> None:
        (conn,) = _U32.unpack(fields["conn"])
        info = _fields(data)
        topic = fields.get("topic", info.get("topic", b"")).decode("utf-8", "replace")
        self.connections[conn] = (topic, info.get("type", b"").decode("utf-8", "replace"))

    def _read(self, offset: int, size: int) -> bytes:
        self._file.seek(offset)
        return self._file.read(size)

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for conn, (topic, msgtype) in self.connections.items():
            count = self.counts.get(conn, 0) + (out[topic].count if topic in out else 0)
            out[topic] = TopicInfo(topic, msgtype, count, "ros1")
        return out

    def batches(self, topics: Iterable[str]) -> Iterator[RawBatch]:
        wanted = {c for c, (t, _) in self.connections.items() if t in set(topics)}
        if not self.chunks:
            yield from self._walk(wanted)
            return
        chunks = [chunk for chunk in self.chunks if wanted & chunk[1].keys()]
        groups = [chunks[i : i + GROUP_CHUNKS] for i in range(0, len(chunks), GROUP_CHUNKS)]
        for group in groups:
            yield from interleaved(self._group_batches(group, *self._group(group, wanted), wanted))

    def _group_batches(
        self,
        group: list[tuple[int, dict[int, int]]],
        data: np.ndarray,
        entries: dict[int, np.ndarray],
        wanted: set[int],
    ) -> list[RawBatch]:
        """The wanted messages of a group of decompressed chunks, a batch per connection."""
        batches = []
        for conn, e in entries.items():
            at = e["offset"].astype(np.int64)
            header_len = gather(data, at, 4, "<u4").ravel().astype(np.int64)
            inside = at + 8 + header_len <= len(data)
            length = (
                gather(data, np.where(inside, at + 4 + header_len, 0), 4, "<u4")
                .ravel()
                .astype(np.int64)
            )
            if not inside.all() or (at + 8 + header_len + length > len(data)).any():
                if len(group) == 1:
                    self._lose_chunk(
                        group[0], ValueError("an index entry does not point at a message")
                    )
                    return []
                # find the chunk at fault: read the group's chunks one by one
                return [
                    b
                    for chunk in group
                    for b in self._group_batches([chunk], *self._group([chunk], wanted), wanted)
                ]
            times = e["sec"].astype(np.int64) * 1_000_000_000 + e["nsec"]
            topic = self.connections[conn][0]
            batches.append(RawBatch(topic, "ros1", data, at + 8 + header_len, length, times))
        return batches

    def _group(
        self, group: list[tuple[int, dict[int, int]]], wanted: set[int]
    ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Chunks decompressed into one buffer, with their index entries of the wanted
        connections (offsets into that buffer). A chunk that does not read is a :class:`Loss`."""
        parts: list[bytes] = []
        entries: dict[int, list[np.ndarray]] = {}
        size = 0
        for chunk in group:
            chunk_pos, per_conn = chunk
            try:
                fields, start, length, _ = self._header(chunk_pos)
                (claimed,) = _U32.unpack(fields["size"])
                data = decompress(
                    fields["compression"].decode("latin-1"),
                    self._read(chunk_pos + start, length),
                    claimed,
                )
                index = self._read(
                    chunk_pos + start + length, sum(128 + 12 * n for n in per_conn.values())
                )
                pos, found = 0, {}
                for _ in per_conn:
                    f, s, n, pos = _record(index, pos)
                    if _op(f) != 0x04:
                        raise ValueError("the chunk is not followed by its index data")
                    e = np.frombuffer(index, _INDEX_ENTRY, n // 12, s).copy()
                    if len(e) and int(e["offset"].max()) + 8 > len(data):
                        raise ValueError("an index entry points past the chunk's end")
                    found[_U32.unpack(f["conn"])[0]] = e
            except Exception as exc:
                self._lose_chunk(chunk, exc)
                continue
            for conn, e in found.items():
                if conn in wanted:
                    e["offset"] += size
                    entries.setdefault(conn, []).append(e)
            parts.append(data)
            size += len(data)
        buffer = np.frombuffer(b"".join(parts), dtype=np.uint8)
        return buffer, {c: np.concatenate(e) for c, e in entries.items()}

    def _lose_chunk(self, chunk: tuple[int, dict[int, int]], exc: Exception) -> None:
        """A chunk that does not read: a :class:`Loss`, its messages counted from the index."""
        messages: dict[str, int] = {}
        for conn, n in chunk[1].items():
            topic = self.connections.get(conn, (f"connection {conn}", ""))[0]
            messages[topic] = messages.get(topic, 0) + n
        self.losses.append(
            Loss(f"chunk does not read ({exc}); {REPAIR}", chunk[0], messages=messages)
        )

    def _header(self, pos: int, op: int | None = 0x05) -> tuple[dict[str, bytes], int, int, int]:
        """The header of the record at ``pos`` (of opcode ``op``, a chunk by default): its
        fields, where its data start and their length (from ``pos``), and its end."""
        head = self._read(pos, 4096)
        (header_len,) = _U32.unpack_from(head, 0)
        if header_len + 8 > len(head):
            head = self._read(pos, header_len + 8)
        fields = _fields(head[4 : 4 + header_len])
        if op is not None and _op(fields) != op:
            raise ValueError("the index does not point at a chunk")
        (data_len,) = _U32.unpack_from(head, 4 + header_len)
        return fields, 8 + header_len, data_len, 8 + header_len + data_len

    # ----------------------------------------------------------------- without an index

    def _walk_records(self) -> Iterator[tuple[int, int, bytes]]:
        """Every message record ``(conn, time_ns, data)`` from the start, connections noted on
        the way; the first record that does not read ends the walk with a :class:`Loss`. The
        file is read record by record, not mapped (a file that shrinks while mapped would kill
        the process with SIGBUS)."""
        pos = len(MAGIC)
        try:
            while pos < self._size:
                record = self._top_record(pos)
                yield from self._records(record, [0])
                pos += len(record)
        except Exception as exc:
            why = f"the bag is cut off or damaged here ({exc}); what follows is lost; {REPAIR}"
            self.losses.append(Loss(why, pos, self._size - pos))

    def _top_record(self, pos: int) -> bytes:
        """The whole top-level record at ``pos`` (``ValueError`` where the file ends first)."""
        end = self._header(pos, op=None)[3]
        if pos + end > self._size:
            raise ValueError("record cut off")
        return self._read(pos, end)

    def _records(
        self, buf: bytes, at: list[int], top: bool = True
    ) -> Iterator[tuple[int, int, bytes]]:
        """The message records of ``buf`` from ``at[0]`` (kept at the next record), those of
        its chunks decompressed and walked too (a chunk inside a chunk is damage: it would
        multiply what a few bytes decompress to); connections noted on the way."""
        while at[0] < len(buf):
            fields, start, length, after = _record(buf, at[0])
            op = _op(fields)
            if op == 0x05 and not top:
                raise ValueError("a chunk inside a chunk")
            if op == 0x05:
                data = decompress(
                    fields["compression"].decode("latin-1"),
                    buf[start : start + length],
                    _U32.unpack(fields["size"])[0],
                )
                yield from self._records(data, [0], top=False)
            elif op == 0x07:
                self._connection(fields, buf[start : start + length])
            elif op == 0x02:
                yield self._message(fields, buf[start : start + length])
            at[0] = after

    @staticmethod
    def _message(fields: dict[str, bytes], data: bytes) -> tuple[int, int, bytes]:
        (conn,) = _U32.unpack(fields["conn"])
        sec, nsec = struct.unpack("<II", fields["time"])
        return conn, sec * 1_000_000_000 + nsec, data

    def _walk_counts(self) -> None:
        for conn, _, _ in self._walk_records():
            self.counts[conn] = self.counts.get(conn, 0) + 1
        if not self.connections:
            raise self.error(f"cannot read the bag: no connection record found; {REPAIR}")

    def _walk(self, wanted: set[int]) -> Iterator[RawBatch]:
        losses = list(self.losses)
        topic_of = {c: (self.connections[c][0], "ros1") for c in wanted}
        yield from in_blocks((row for row in self._walk_records() if row[0] in wanted), topic_of)
        self.losses = losses  # the walk for the counts noted them already
