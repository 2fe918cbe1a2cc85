"""MCAP files, read with the ``mcap`` library: through the summary's chunk and message indexes
(read as numpy arrays) where a file has them, only the chunks of wanted channels; else record
by record. A file cut off mid-write is read to the cut, and the cut is a :class:`Loss`; a chunk
that does not decompress is one too."""

from __future__ import annotations

import os
import struct
import sys
import time
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from io import BytesIO
from pathlib import Path
from typing import BinaryIO, ClassVar

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Schema
from mcap.summary import Summary

from imucal_cli.io.base import (
    MAX_CHUNK_BYTES,
    MAX_RATIO,
    LogReader,
    Loss,
    TopicInfo,
    check_chunk_size,
    decompress,
    interleaved,
)
from imucal_cli.io.formats import MCAP_MAGIC
from imucal_cli.io.imu_msg import RawBatch, gather

MAGIC = MCAP_MAGIC
#: Decompressed bytes of chunks decoded together: fewer, larger batches for the calibrator,
#: whose cost is partly per batch (benchmarks/kernels.py, docs/performance.md).
GROUP_BYTES = 8 << 20
_RECORD = struct.Struct("<BQ")  # opcode, length
_FOOTER_OP, _SCHEMA_OP, _CHANNEL_OP = 0x02, 0x03, 0x04
_MESSAGE_OP, _CHUNK_OP, _DATA_END_OP = 0x05, 0x06, 0x0F
#: A Chunk record up to its compression's name: opcode, length, start and end time, size, CRC.
_CHUNK_HEAD = struct.Struct("<BQQQQII")
_MESSAGE_RECORD = np.dtype(  # a Message record up to its data
    {
        "names": ["opcode", "length", "channel", "sequence", "log_time", "publish_time"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
    }
)
_MESSAGE_HEADER = _MESSAGE_RECORD.itemsize  # 31 bytes before a message's data
REPAIR = "`mcap recover FILE -o FIXED.mcap` rewrites what is readable"

MESSAGE_HEAD = 2 + 4 + 8 + 8  # a Message record's channel id, sequence, log and publish times


class ChunkTable:
    """The summary's chunk indexes as arrays, in file order, each a ``ChunkIndex`` again as it
    is read: the ``mcap`` library's objects take about 750 bytes a chunk (20 MB for a day of
    1 MB chunks), and reading holds them while the whole log is read."""

    FIELDS: ClassVar[tuple[str, ...]] = ("chunk_length", "chunk_start_offset", "compressed_size")
    FIELDS += ("message_end_time", "message_index_length", "message_start_time")
    FIELDS += ("uncompressed_size",)

    def __init__(self, indexes: Sequence[ChunkIndex]) -> None:
        ordered = sorted(indexes, key=lambda i: i.chunk_start_offset)
        rows = [[getattr(i, f) for f in self.FIELDS] for i in ordered]
        self.values = np.array(rows, dtype=np.uint64).reshape(-1, len(self.FIELDS))
        self.compressions = [sys.intern(i.compression) for i in ordered]
        self.channels = sorted({c for i in ordered for c in i.message_index_offsets})
        rows = [[i.message_index_offsets.get(c, -1) for c in self.channels] for i in ordered]
        self.offsets = np.array(rows, dtype=np.int64).reshape(len(ordered), len(self.channels))

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.FIELDS.index(name)].astype(np.int64)

    def __iter__(self) -> Iterator[ChunkIndex]:
        for row, compression in enumerate(self.compressions):  # (ints made as they are read)
            fields = dict(zip(self.FIELDS, self.values[row].tolist(), strict=True))
            offsets = self.offsets[row].tolist()
            found = {c: o for c, o in zip(self.channels, offsets, strict=True) if o >= 0}
            yield ChunkIndex(**fields, compression=compression, message_index_offsets=found)


class McapLog(LogReader):
    format_name = "mcap"

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self._file: BinaryIO = path.open("rb")
        if self._file.read(len(MAGIC)) != MAGIC:
            self._file.close()
            raise self.error("not an MCAP file (bad magic bytes)")
        self._chunks = ChunkTable(())
        self._summary = self._usable_summary()
        self._scanned: tuple[dict[int, Channel], dict[int, Schema], dict[int, int]] | None = None

    def close(self) -> None:
        self._file.close()

    def _usable_summary(self) -> Summary | None:
        """The summary, where it indexes every chunk's messages and names their channels."""
        try:
            self._file.seek(0)
            summary = make_reader(self._file).get_summary()
        except Exception:
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        table = ChunkTable(summary.chunk_indexes)
        summary.chunk_indexes.clear()  # (the table holds what reading needs)
        start, size = table.column("chunk_start_offset"), table.column("uncompressed_size")
        end = start + table.column("chunk_length")
        indexed = np.all((table.offsets >= 0).any(axis=1) | (size == 0))
        # each chunk once and inside the file: what a read decompresses is bounded by the file
        placed = start[0] >= len(MAGIC) and np.all(start[1:] >= end[:-1])
        placed = placed and end[-1] <= os.fstat(self._file.fileno()).st_size
        if not (indexed and placed and set(table.channels) <= summary.channels.keys()):
            return None
        self._chunks = table
        return summary

    # ----------------------------------------------------------------- topics

    def _channels(self) -> tuple[dict[int, Channel], dict[int, Schema], dict[int, int]]:
        """Channels, schemas and message counts per channel id."""
        if self._summary is not None:
            s = self._summary
            counts = dict(s.statistics.channel_message_counts) if s.statistics is not None else {}
            try:
                for index in self._chunks if not counts else ():
                    for channel_id, entries in self._message_indexes(
                        index, set(index.message_index_offsets)
                    ).items():
                        counts[channel_id] = counts.get(channel_id, 0) + len(entries)
                return dict(s.channels), dict(s.schemas), counts
            except (ValueError, struct.error):  # a damaged message index: the records themselves
                self._summary = None
        if self._scanned is None:
            channels: dict[int, Channel] = {}
            schemas: dict[int, Schema] = {}
            counts = {}
            for data, at in self._walk(channels, schemas, note=True):
                ids, n = np.unique(gather(data, at + 9, 2, "<u2"), return_counts=True)
                for channel_id, k in zip(ids.tolist(), n.tolist(), strict=True):
                    counts[channel_id] = counts.get(channel_id, 0) + k
            lost = [x for x in self.losses if x.lost]
            if not channels and lost:
                raise self.error(f"no channel could be read: {lost[0].reason}")
            self._scanned = channels, schemas, counts
        return self._scanned

    def topics(self) -> dict[str, TopicInfo]:
        channels, schemas, counts = self._channels()
        out: dict[str, TopicInfo] = {}
        for channel_id, channel in channels.items():
            schema, before = schemas.get(channel.schema_id), out.get(channel.topic)
            count = counts.get(channel_id, 0) + (before.count if before else 0)
            out[channel.topic] = TopicInfo(
                channel.topic, schema.name if schema else "", count, channel.message_encoding
            )
        return out

    # ----------------------------------------------------------------- messages

    def batches(self, topics: Iterable[str]) -> Iterator[RawBatch]:
        wanted = set(topics)
        if self._summary is None:
            channels: dict[int, Channel] = {}
            for data, at in self._walk(channels, {}, note=False):
                yield from _channel_batches(data, at, channels, wanted)
            return
        ids = {c: (ch.topic, ch.message_encoding) for c, ch in self._summary.channels.items()}
        ids = {c: found for c, found in ids.items() if found[0] in wanted}
        for group in _groups(iter(self._chunks), set(ids)):
            yield from interleaved(self._chunk_batches(*self._group(group, set(ids)), ids))

    def follow(
        self, topics: Iterable[str], stop: Callable[[], bool], poll_s: float = 0.05
    ) -> Iterator[RawBatch]:
        """A file still being written (follow mode): the wanted messages of each record as it
        completes, waiting ``poll_s`` for more; ends at the footer, or when ``stop()`` says."""
        channels: dict[int, Channel] = {}
        for data, at in self._walk(channels, {}, note=True, stop=stop, poll_s=poll_s):
            yield from _channel_batches(data, at, channels, set(topics))

    def _record_at(self, pos: int, waiting: bool = False) -> tuple[int, int, bytes] | None:
        """The top-level record at ``pos``: its opcode, its length and as much of it as the
        file holds now; ``None`` before a whole opcode and length. Read, not mapped: a file
        that shrinks while mapped would kill the process (SIGBUS)."""
        self._file.seek(pos)
        head = self._file.read(9)
        if len(head) < 9:
            return None
        opcode, length = _RECORD.unpack(head)
        size = os.fstat(self._file.fileno()).st_size
        if waiting and size < pos + 9 + length:  # (cut off, followed: read once all there)
            return opcode, length, head
        return opcode, length, head + self._file.read(max(0, min(length, size - pos - 9)))

    def _walk(
        self,
        channels: dict[int, Channel],
        schemas: dict[int, Schema],
        note: bool,
        stop: Callable[[], bool] | None = None,
        poll_s: float = 0.05,
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The file's records from its start: per chunk (and per top-level message) the data
        and the offsets of its Message records; channels and schemas collected on the way,
        their bodies parsed by the library. A record cut off ends the walk (a :class:`Loss`
        where ``note``); a chunk cut off gives what decompresses of it. With ``stop`` (a file
        still being written), a record cut off is waited for until ``stop()`` says."""
        pos, messages, last_ns, in_cut = len(MAGIC), 0, None, -1
        try:
            while True:
                opcode, length, data = self._record_at(pos, stop is not None) or (-1, 0, b"")
                if opcode in (_FOOTER_OP, _DATA_END_OP):
                    return
                cut = opcode < 0 or len(data) < 9 + length
                if opcode == 0 or 0x10 <= opcode < 0x80:  # reserved: no record, but damage
                    raise ValueError(f"a record of reserved opcode {opcode:#04x} at byte {pos}")
                if cut and stop is not None:
                    if stop():
                        return
                    time.sleep(poll_s)
                    continue
                if cut and opcode != _CHUNK_OP:
                    break
                inner, found = self._messages_of(data, 0, channels, schemas, note)
                if len(found):
                    messages += len(found)
                    last_ns = int(gather(inner, found + 15, 8, "<u8")[-1, 0])
                    yield inner, found
                if cut:
                    in_cut = len(found)
                    break
                pos += 9 + length
            if note and pos < (size := os.fstat(self._file.fileno()).st_size):
                why = f"the file is cut off after {messages} messages; what follows is lost"
                if in_cut >= 0:  # (the file ends in a chunk, what decodes of it read: the rest)
                    why = f"the chunk from byte {pos} is cut off after {in_cut} of its messages"
                    pos, size = size, pos + 9 + length
                self.losses.append(Loss(f"{why}; {REPAIR}", pos, size - pos, last_ns, None))
        except Exception as exc:
            if note:
                size = os.fstat(self._file.fileno()).st_size
                why = f"the file is damaged after {messages} messages ({type(exc).__name__}: {exc})"
                why += f"; what follows is lost; {REPAIR}"
                self.losses.append(Loss(why, pos, size - pos, last_ns, None))
        finally:
            if note and stop is None and not self.losses:
                why = "the file has no usable summary and indexes: read record by record"
                self.losses.append(Loss(why, lost=False))

    def _messages_of(
        self,
        data: bytes,
        pos: int,
        channels: dict[int, Channel],
        schemas: dict[int, Schema],
        note: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The top-level record at ``pos``: its records (a chunk's decompressed, as much of a
        cut-off or damaged chunk as decodes: a whole chunk that does not is a :class:`Loss`
        where ``note``; any other record itself) and the offsets of their messages."""
        opcode, length = _RECORD.unpack_from(data, pos)
        if opcode == _CHUNK_OP:
            chunk = Chunk.read(
                ReadDataStream(BytesIO(memoryview(data)[pos + 9 : pos + 9 + length]))
            )
            size, kind = chunk.uncompressed_size, chunk.compression
            try:
                check_chunk_size(size, len(chunk.data), kind)  # (before the room is made)
                inner = decompress(kind, chunk.data, size, out=np.empty(size, dtype=np.uint8))
            except Exception as exc:  # cut off or damaged: the prefix that decodes
                if note and pos + 9 + length <= len(data):
                    why = f"chunk does not read ({exc}); what decodes of it is read; {REPAIR}"
                    span = (chunk.message_start_time, chunk.message_end_time)
                    self.losses.append(Loss(why, pos, 9 + length, *span))
                limit = min(
                    chunk.uncompressed_size, MAX_CHUNK_BYTES, MAX_RATIO * max(len(chunk.data), 1)
                )
                inner = np.frombuffer(
                    decompress(chunk.compression, chunk.data, limit, prefix=True), dtype=np.uint8
                )
        else:
            inner = np.frombuffer(data, np.uint8, 9 + length, pos)
        return inner, self._records(inner, channels, schemas)

    @staticmethod
    def _records(
        data: np.ndarray, channels: dict[int, Channel], schemas: dict[int, Schema]
    ) -> np.ndarray:
        """The offsets of the Message records in ``data`` (records end to end, as in a
        chunk), channels and schemas noted. A record cut off ends the list."""
        raw = data.data
        offsets = array("q")  # (8 bytes an offset: a chunk holds millions of records)
        pos, size = 0, len(data)
        unpack = _RECORD.unpack_from
        while pos + 9 <= size:
            opcode, length = unpack(raw, pos)
            end = pos + 9 + length
            if end > size:
                break
            if opcode == _MESSAGE_OP and length >= MESSAGE_HEAD:  # (shorter: no message)
                offsets.append(pos)
            elif opcode == _CHANNEL_OP:
                channel = Channel.read(ReadDataStream(BytesIO(raw[pos + 9 : end])))
                channels[channel.id] = channel
            elif opcode == _SCHEMA_OP:
                schema = Schema.read(ReadDataStream(BytesIO(raw[pos + 9 : end])))
                schemas[schema.id] = schema
            pos = end
        return np.frombuffer(offsets, dtype=np.int64) if offsets else np.zeros(0, np.int64)

    def _message_indexes(self, index: ChunkIndex, channel_ids: set[int]) -> dict[int, np.ndarray]:
        """The message index entries (log time, offset in the chunk) of some channels of a chunk."""
        offsets = {c: o for c, o in index.message_index_offsets.items() if c in channel_ids}
        if not offsets:
            return {}
        begin = min(offsets.values())
        end = index.chunk_start_offset + index.chunk_length + index.message_index_length
        self._file.seek(begin)
        region = self._file.read(end - begin)
        out = {}
        for channel_id, offset in offsets.items():
            at = offset - begin
            opcode, _, cid, nbytes = struct.unpack_from("<BQHI", region, at)
            if opcode != 0x07 or cid != channel_id or at + 15 + nbytes > len(region):
                raise ValueError(
                    f"message index of channel {channel_id} at byte {offset} is damaged"
                )
            out[channel_id] = np.frombuffer(region, "<u8", nbytes // 8, at + 15).reshape(-1, 2)
        return out

    def _group(
        self, group: list[ChunkIndex], channel_ids: set[int]
    ) -> tuple[list[ChunkIndex], np.ndarray, dict[int, np.ndarray]]:
        """Chunks decompressed into one buffer, with their wanted message index entries
        (offsets into that buffer): one gather per field, channel and group, not per chunk.
        A chunk that does not read is a :class:`Loss`; the others are kept."""
        believed = [
            min(index.uncompressed_size, MAX_CHUNK_BYTES, MAX_RATIO * max(index.compressed_size, 1))
            for index in group
        ]
        buffer = np.empty(sum(believed), dtype=np.uint8)
        entries: dict[int, list[np.ndarray]] = {}
        kept, size = [], 0
        for index in group:
            try:
                found = self._message_indexes(index, channel_ids)
                kind, records = self._chunk(index, found)  # (its size is its index's)
                out = buffer[size : size + index.uncompressed_size]
                decompress(kind, records, index.uncompressed_size, out=out)
            except Exception as exc:
                self._lose_chunk(index, exc)
                continue
            for channel_id, e in found.items():
                entries.setdefault(channel_id, []).append(e[:, 1].astype(np.int64) + size)
            kept.append(index)
            size += index.uncompressed_size
        return kept, buffer[:size], {c: np.concatenate(e) for c, e in entries.items()}

    def _chunk(self, index: ChunkIndex, found: dict[int, np.ndarray]) -> tuple[str, memoryview]:
        """The compression and records (a view of the read: mcap's reader copies them) of the
        chunk an index points at, its sizes and message index entries checked."""
        self._file.seek(index.chunk_start_offset)
        data = memoryview(self._file.read(index.chunk_length))
        opcode, length, _, _, size, _, name = _CHUNK_HEAD.unpack_from(data, 0)
        at = _CHUNK_HEAD.size + name  # the records' length, then the records
        (packed,) = struct.unpack_from("<Q", data, at)  # (struct.error where cut off)
        if opcode != _CHUNK_OP or at + 8 + packed > min(9 + length, len(data)):
            raise ValueError("the chunk index does not point at a whole chunk")
        kind = bytes(data[_CHUNK_HEAD.size : at]).decode()
        check_chunk_size(size, packed, kind)
        if (size, packed) != (index.uncompressed_size, index.compressed_size):
            raise ValueError(f"the chunk's sizes {size}/{packed} are not its index's")
        if any(len(e) and int(e[:, 1].max()) + _MESSAGE_HEADER > size for e in found.values()):
            raise ValueError("a message index points past the chunk's end")
        return kind, data[at + 8 : at + 8 + packed]

    def _lose_chunk(self, index: ChunkIndex, exc: Exception) -> None:
        """A chunk that does not read: a :class:`Loss`, its messages counted from its index."""
        assert self._summary is not None
        try:
            found = self._message_indexes(index, set(index.message_index_offsets))
            counted: dict[str, int] = {}
            for channel_id, e in found.items():
                topic = self._summary.channels[channel_id].topic
                counted[topic] = counted.get(topic, 0) + len(e)
            messages: dict[str, int] | None = counted
        except Exception:
            messages = None
        where = (index.chunk_start_offset, index.chunk_length)
        span = (index.message_start_time, index.message_end_time)
        self.losses.append(Loss(f"chunk does not read ({exc}); {REPAIR}", *where, *span, messages))

    def _chunk_batches(
        self,
        group: list[ChunkIndex],
        data: np.ndarray,
        entries: dict[int, np.ndarray],
        ids: dict[int, tuple[str, str]],
    ) -> list[RawBatch]:
        """The wanted messages of a decompressed chunk, a batch per channel, found through
        their message index entries (checked against the records they point at)."""
        batches = []
        for channel_id, at in entries.items():
            if not len(at):
                continue
            head = gather(data, at, _MESSAGE_HEADER, _MESSAGE_RECORD).ravel()
            length = head["length"].astype(np.int64)
            if (
                (head["opcode"] != _MESSAGE_OP).any()
                or (head["channel"] != channel_id).any()
                or (length < 22).any()
                or (at + 9 + length > len(data)).any()
            ):
                if len(group) == 1:
                    self._lose_chunk(
                        group[0], ValueError("a message index does not point at its messages")
                    )
                    return []
                # find the chunk at fault: read the group's chunks one by one
                return [
                    b
                    for index in group
                    for b in self._chunk_batches(*self._group([index], set(ids)), ids)
                ]
            times = head["log_time"].astype(np.int64)
            batches.append(
                RawBatch(*ids[channel_id], data, at + _MESSAGE_HEADER, length - 22, times)
            )
        return batches


def _channel_batches(
    data: np.ndarray, at: np.ndarray, channels: dict[int, Channel], wanted: set[str]
) -> Iterator[RawBatch]:
    """The Message records at ``at`` in ``data``, a batch per wanted channel."""
    of = gather(data, at + 9, 2, "<u2").ravel()
    for channel_id in np.unique(of):
        channel = channels.get(int(channel_id))
        if channel is None or channel.topic not in wanted:
            continue
        mine = at[of == channel_id]
        size = gather(data, mine + 1, 8, "<u8").ravel().astype(np.int64) - 22
        log_times = gather(data, mine + 15, 8, "<u8").ravel().astype(np.int64)
        topic, encoding = channel.topic, channel.message_encoding
        yield RawBatch(topic, encoding, data, mine + _MESSAGE_HEADER, size, log_times)


def _groups(chunks: Iterator[ChunkIndex], channel_ids: set[int]) -> Iterator[list[ChunkIndex]]:
    """The chunks holding a wanted channel, in groups of about :data:`GROUP_BYTES` decompressed."""
    group: list[ChunkIndex] = []
    size = 0
    for index in chunks:
        if not channel_ids & index.message_index_offsets.keys():
            continue
        group.append(index)
        size += index.uncompressed_size
        if size >= GROUP_BYTES:
            yield group
            group, size = [], 0
    if group:
        yield group
