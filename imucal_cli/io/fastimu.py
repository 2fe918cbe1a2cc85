"""Vectorised decoding of ``sensor_msgs/Imu`` and bulk readers of the log containers.

Decoding one message at a time through a generic deserializer costs 10-20 us in Python. The
``Imu`` layout is fixed except for the length of ``header.frame_id``, so many messages at once
can be decoded with numpy: gather the bytes of each field at its offset and view them as
numbers. The readers here hand over whole decompressed chunks (MCAP, ROS 1) or row batches
(rosbag2 sqlite3) with the position of every message in them, taken from the container's own
indexes, so no Python object is made per message.

Everything a layout check does not recognise (big-endian CDR, a message shorter than its layout,
compressed rosbag2 storage, an MCAP without message indexes) is left to the generic path.
"""

from __future__ import annotations

import os
import sqlite3
import struct
import threading
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO, TypeVar

import numpy as np

if TYPE_CHECKING:
    from imucal_cli.io.sqlitepages import MessagePages

T = TypeVar("T")

_U32 = struct.Struct("<I")
_SEEK_LOCK = threading.Lock()  # for handles without a file descriptor (no pread)

#: Bytes after the variable-length frame id: orientation (4 f64), its covariance (9),
#: angular velocity (3), covariance (9), linear acceleration (3), covariance (9).
_TAIL = 8 * (4 + 9 + 3 + 9 + 3 + 9)
_GYRO_AFTER_FRAME = 8 * (4 + 9)
_ACCEL_AFTER_FRAME = 8 * (4 + 9 + 3 + 9)
_CDR_HEAD = np.dtype(
    [("encapsulation", "<u2"), ("options", "<u2"), ("sec", "<i4"), ("nsec", "<u4"), ("frame_len", "<u4")]
)
_ROS1_HEAD = np.dtype([("seq", "<u4"), ("sec", "<u4"), ("nsec", "<u4"), ("frame_len", "<u4")])
#: An entry of a ROS 1 index data record: a message's receive time and offset in its chunk.
_ROS1_INDEX_ENTRY = np.dtype([("sec", "<u4"), ("nsec", "<u4"), ("offset", "<u4")])
#: Bytes of a ROS 1 message record that must lie inside its chunk at its index's offset.
_ROS1_RECORD_START = 8
#: Most bytes of a ROS 1 chunk's index data read together with the chunk.
_ROS1_MAX_INDEX_READ = 1 << 22
#: Largest decompressed chunk believed (bytes; MCAP or ROS 1): a bigger size in an index or a
#: chunk's header is damage.
_MAX_CHUNK = 1 << 30
#: Bytes of decompressed chunks decoded together. Smaller groups pay the decoder's per-call
#: cost (about 400 numpy calls a group) more often, larger ones gather from memory that has
#: left the caches (the 1 h ROS 1 bag of ``benchmarks/throughput.py``, two threads, fastest of
#: 8 alternating runs: 1 MiB 5.3 s, 4 MiB 1.8 s, 16 MiB 0.90 s, 32 MiB 1.11 s, 64 MiB 1.03 s).
#: Since chunks are gathered as they are decompressed (:class:`_WarmDecode`), the size only
#: spreads the per-group and per-batch costs: 8-64 MiB within the machine's noise (on another,
#: faster machine; fastest of 5: 0.55-0.77 s in one thread, 0.65-0.73 s in two).
GROUP_BYTES = 16 << 20
#: Groups of chunks (or of sqlite3 rows) read ahead of the one being consumed, beyond one
#: a decode thread.
READ_AHEAD_GROUPS = 2
#: Threads that read, decompress, check and decode groups of MCAP and ROS 1 chunks side by
#: side (zstd, lz4, the CRC, the file reads and numpy's gathers run outside the GIL); 0 reads
#: them in the consumer's thread (as the reader process of ``calibrate`` does: see
#: :mod:`imucal_cli.io.prefetch`).
#:
#: The threads hand the GIL to each other at numpy steps (about 10 000 context switches an
#: hour of log, and 30-40% more CPU than one thread), yet are the fastest arrangement measured
#: on two cores (the 1 h ROS 1 bag, fastest of 8 alternating runs): a forked second process
#: taking groups from a shared counter, its arrays sent over a pipe, was no faster (1.15 s
#: against 1.13 s; the MCAP 2.03 s against 1.70 s: this process, which also consumes, and the
#: copy-on-write faults after the fork bound it), nor were decompression-only threads feeding
#: the decoding in this thread (1.17-1.32 s against 0.97 s: this thread bounds it).
#: With the chunks gathered as they are decompressed, the ROS 1 bag decodes about as fast in
#: one thread as in two (0.53-0.58 s against 0.51-0.66 s, the two using 0.9-1.1 s of CPU
#: against 0.55); the MCAP, whose zstd runs outside the GIL, is faster in two (0.70-0.84 s
#: against 1.12-1.37 s).
DECODE_THREADS = 2
#: The interpreter's switch interval while reading ahead (s): the reading thread takes the GIL
#: back after every read, decompression and CRC, and would wait the default 5 ms each time.
READ_AHEAD_SWITCH_S = 0.0005
#: How many messages of a batch have their frame id read (evenly spread, the first included).
FRAME_ID_SAMPLES = 64


@dataclass(frozen=True)
class RawBatch:
    """Serialized messages of one topic inside one buffer."""

    topic: str
    encoding: str  # "cdr" or "ros1"
    buffer: np.ndarray  # uint8
    starts: np.ndarray  # int64, first byte of each message's data
    lengths: np.ndarray  # int64
    log_time_ns: np.ndarray  # int64
    #: The first 16 bytes of every message (``_CDR_HEAD`` or ``_ROS1_HEAD``) when the reader
    #: gathered them with its record headers; only for batches whose messages all hold them.
    head: np.ndarray | None = None
    #: The batch decoded already, where the reader decodes in its worker threads.
    decoded: DecodedBatch | None = None

    def messages(self) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log_time_ns, serialized message)`` one at a time (for the generic path)."""
        buf = self.buffer
        for start, length, log_ns in zip(self.starts.tolist(), self.lengths.tolist(), self.log_time_ns.tolist(), strict=True):
            yield self.topic, int(log_ns), bytes(buf[start : start + length])


def _ahead(items: Iterator[T]) -> Iterator[T]:
    """``items`` produced :data:`READ_AHEAD_GROUPS` ahead in a thread (inline when it is 0)."""
    from imucal_cli.io.prefetch import queued

    return queued(items, READ_AHEAD_GROUPS, READ_AHEAD_SWITCH_S) if READ_AHEAD_GROUPS > 0 else iter(items)


def _decoded_groups(
    read: Callable[[T, list | None], Iterable[RawBatch]], groups: Iterable[T], losses: list | None
) -> Iterator[RawBatch]:
    """The batches of every group, read (``read(group, lost)``: what of it cannot be read goes
    to ``lost``, or raises where that is None) and decoded by :data:`DECODE_THREADS` threads,
    in the groups' order; each group's losses are added to ``losses`` at its turn."""
    from imucal_cli.io.prefetch import ordered_map

    def one(group: T) -> tuple[list[RawBatch], list | None]:
        lost = None if losses is None else []
        return [batch if batch.decoded is not None else replace(batch, decoded=decode_imu(batch)) for batch in read(group, lost)], lost

    for batches, lost in ordered_map(one, groups, DECODE_THREADS, READ_AHEAD_GROUPS, READ_AHEAD_SWITCH_S):
        if losses is not None and lost:
            losses.extend(lost)
        yield from batches


def _pread(handle: BinaryIO, offset: int, size: int) -> bytes:
    """``size`` bytes at ``offset`` without moving the handle (threads share it)."""
    if hasattr(os, "pread"):
        try:
            fd = handle.fileno()
        except (AttributeError, OSError, ValueError):
            pass
        else:
            parts = []
            while size > 0:
                part = os.pread(fd, size, offset)
                if not part:
                    break
                parts.append(part)
                offset += len(part)
                size -= len(part)
            return parts[0] if len(parts) == 1 else b"".join(parts)
    with _SEEK_LOCK:
        handle.seek(offset)
        return handle.read(size)


def pack_blobs(blobs: Sequence[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Serialized messages in one buffer: ``(buffer, starts, lengths)``."""
    lengths = np.fromiter(map(len, blobs), dtype=np.int64, count=len(blobs))
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    return np.frombuffer(b"".join(blobs), dtype=np.uint8), starts, lengths


@dataclass(frozen=True)
class DecodedBatch:
    topic: str
    stamp_ns: np.ndarray  # int64
    log_time_ns: np.ndarray
    gyro: np.ndarray  # (n, 3)
    accel: np.ndarray  # (n, 3)
    frame_ids: list[str]
    undecoded: np.ndarray  # indices into the batch left to the generic decoder


def bytes_at(buffer: np.ndarray, positions: np.ndarray, nbytes: int) -> np.ndarray:
    """Bytes ``positions[i] .. positions[i] + nbytes`` of every position: an (n, nbytes) uint8
    array.

    The buffer is seen as overlapping ``nbytes``-long records, one starting at every byte (a
    strided view, no copy), so each field costs one index per position, not one per byte.
    """
    records = np.ndarray(shape=(len(buffer) - nbytes + 1,), dtype=f"V{nbytes}", buffer=buffer, strides=(1,))
    return records[positions].view(np.uint8).reshape(len(positions), nbytes)


def _gather(buffer: np.ndarray, positions: np.ndarray, nbytes: int, dtype: str | np.dtype) -> np.ndarray:
    """:func:`bytes_at` viewed as ``dtype``: an (n, nbytes / itemsize) array."""
    return bytes_at(buffer, positions, nbytes).view(dtype)


def decode_imu(batch: RawBatch) -> DecodedBatch:
    """Decode ``sensor_msgs/Imu`` messages of a batch; bit-exact with the rosbags deserializer.

    CDR (ROS 2): 4-byte little-endian encapsulation header, then ``stamp`` (int32 sec, uint32
    nanosec), ``frame_id`` (uint32 length with the NUL, bytes), padding to 8 (counted from the
    end of the encapsulation header), then the float64 fields. ROS 1: ``seq``, ``stamp`` (uint32
    sec, nsec), ``frame_id`` (uint32 length, bytes), then the float64 fields, unpadded.
    """
    buf, starts, lengths = batch.buffer, batch.starts, batch.lengths
    n = len(starts)
    if batch.encoding not in ("cdr", "ros1"):
        raise ValueError(f"unsupported encoding {batch.encoding!r}")
    # the first 16 bytes hold everything before the frame id: one gather
    head_dtype = _CDR_HEAD if batch.encoding == "cdr" else _ROS1_HEAD
    ok = (lengths >= 16) & (starts >= 0) & (starts + lengths <= len(buf))
    all_ok = bool(ok.all())
    if all_ok and batch.head is not None:
        head = batch.head
    elif all_ok:
        head = _gather(buf, starts, 16, head_dtype).ravel()
    else:
        head = np.zeros(n, dtype=head_dtype)
        if ok.any():
            head[ok] = _gather(buf, starts[ok], 16, head_dtype).ravel()
    frame_len = head["frame_len"].astype(np.int64)
    if batch.encoding == "cdr":
        ok &= head["encapsulation"] == 0x0100  # bytes 00 01: CDR, little endian
        floats_at = (frame_len + 19) // 8 * 8  # after the body's 12 bytes and the frame id, to 8
        needed = 4 + floats_at + _TAIL
        frame_start, frame_chars = starts + 16, frame_len - 1
        floats_abs = starts + 4 + floats_at
    else:
        needed = 16 + frame_len + _TAIL
        frame_start, frame_chars = starts + 16, frame_len
        floats_abs = starts + 16 + frame_len
    ok &= (lengths >= needed) & (frame_chars >= 0)
    all_ok = bool(ok.all())
    index = np.arange(n) if all_ok else np.flatnonzero(ok)

    frame_ids: list[str] = []
    if not len(index):
        stamp, gyro, accel = np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    else:
        used = head if all_ok else head[index]
        stamp = used["sec"].astype(np.int64) * 1_000_000_000 + used["nsec"]
        at = floats_abs if all_ok else floats_abs[index]
        gyro, accel = _vectors(buf, at)
        frame_ids = _frame_ids(buf, frame_start, frame_chars, index)
    return DecodedBatch(
        batch.topic,
        stamp,
        batch.log_time_ns if all_ok else batch.log_time_ns[index],
        np.asarray(gyro, dtype=np.float64),
        np.asarray(accel, dtype=np.float64),
        frame_ids,
        np.zeros(0, dtype=np.int64) if all_ok else np.flatnonzero(~ok),
    )


def _vectors(buffer: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angular velocities and accelerations, (n, 3) each and contiguous, of the messages
    whose floats begin at ``at`` (the orientation's first byte): a gather each. One gather
    from the angular velocity to the end of the acceleration (the 72 bytes of covariance
    between them coming along) reads a message's cache lines once, but its columns must then
    be copied out, strided: for the 2 800 messages of a chunk, 22 us in two gathers against
    34 us in one and the two copies."""
    return _gather(buffer, at + _GYRO_AFTER_FRAME, 24, "<f8"), _gather(buffer, at + _ACCEL_AFTER_FRAME, 24, "<f8")


def _frame_ids(buf: np.ndarray, frame_start: np.ndarray, frame_chars: np.ndarray, index: np.ndarray | None) -> list[str]:
    """The frame ids of the messages ``index`` (non-empty; None: all; ``frame_start`` and
    ``frame_chars`` give every message's frame id bytes), in the order the messages have them, as the generic
    path finds them. Frame ids are metadata, not measurements: an even sample of
    :data:`FRAME_ID_SAMPLES` messages of each frame id length is read, the first message always
    (the topic's frame id is its)."""
    if index is None:
        index, lengths_used = np.arange(len(frame_chars)), frame_chars
    else:
        lengths_used = frame_chars[index]
    groups = [lengths_used[0]] if lengths_used.min() == lengths_used.max() else np.unique(lengths_used)
    found: list[tuple[int, np.ndarray]] = []  # (first message seen with it, frame id bytes)
    for length in groups:
        group = index if len(groups) == 1 else index[lengths_used == length]
        if length == 0:
            found.append((int(group[0]), np.zeros(0, dtype=np.uint8)))
            continue
        sample = group[:: max(1, len(group) // FRAME_ID_SAMPLES)]
        names = _gather(buf, frame_start[sample], int(length), "u1").reshape(len(sample), -1)
        # one frame id per topic is the rule: check it cheaply, sort only otherwise
        if np.all(names == names[0]):
            found.append((int(sample[0]), names[0]))
        else:
            unique, first = np.unique(names, axis=0, return_index=True)
            found.extend(zip(sample[first].tolist(), unique, strict=True))
    frame_ids: list[str] = []
    for _, row in sorted(found, key=lambda item: item[0]):
        try:
            name = bytes(row).decode("utf-8")
        except UnicodeDecodeError:
            name = bytes(row).decode("latin-1")
        if name not in frame_ids:
            frame_ids.append(name)
    return frame_ids


def _records_inside(chunks: list[tuple[list[np.ndarray], int]], header: int) -> bool:
    """Whether every record offset of the chunks (per chunk: its index's offsets, an array a
    channel, and its decompressed size) leaves the record's first ``header`` bytes inside its
    chunk: ``offset + header <= size``."""
    parts = [(offsets, size) for arrays, size in chunks for offsets in arrays if len(offsets)]
    if not parts:
        return True
    offsets = np.concatenate([offsets for offsets, _ in parts]).astype(np.uint64)
    sizes = np.repeat(np.array([size for _, size in parts], dtype=np.uint64), [len(offsets) for offsets, _ in parts])
    # in uint64 (MCAP's offsets): the sum could wrap past 2**64, the difference cannot
    return bool(np.all(sizes >= header)) and bool(np.all(offsets <= sizes - np.uint64(header)))


class _WarmDecode:
    """Decodes the messages of a group of chunks chunk by chunk, each chunk right after it is
    decompressed, while its bytes are still in the core's cache: the messages of all wanted
    sources (connections or channels) of a chunk are gathered together, then copied to their
    source's arrays, so a chunk costs a couple of dozen numpy calls.

    Gathering from a group's buffer once it is all decompressed (16 MiB, larger than a core's
    cache) costs 45-60 ns a message and field from memory, against 6-14 ns from the cache (the
    1 h ROS 1 bag of ``benchmarks/throughput.py``). The checks of :func:`decode_imu` are made
    for the whole group at the end; where anything is not the common layout (a record header
    of another length, a message shorter than its layout, big-endian CDR), :meth:`batches`
    returns None and the group is decoded source by source as before, by :func:`decode_imu`,
    which leaves what it does not recognise to the generic path.

    ``container`` is ``"ros1"`` (message data records) or ``"mcap"`` (message records);
    ``sources`` the wanted connections or channels with their topics, in the order their
    batches are given; ``counts`` the most messages each has in the group (from the indexes).
    """

    def __init__(self, container: str, encoding: str, sources: dict[int, str], counts: dict[int, int]) -> None:
        self.container, self.encoding = container, encoding
        self.sources = [(source, topic) for source, topic in sources.items() if counts.get(source)]
        self.counts = [counts[source] for source, _ in self.sources]
        self.prefix: np.dtype | None = None  # a record's first bytes, to the message's 16th
        self.data_at = 0  # bytes from a record's start to its message's first byte
        self.raw: list[np.ndarray] = []  # per source: each message's record prefix, as bytes
        self.gyro = [np.empty((n, 3)) for n in self.counts]
        self.accel = [np.empty((n, 3)) for n in self.counts]
        self.pieces: list[list[tuple[np.ndarray, int]]] = [[] for _ in self.counts]  # (index entries, chunk start)
        self.filled = [0] * len(self.counts)
        self.failed = False

    def _layout(self, buffer: np.ndarray, first: int) -> bool:
        """Set the record layout from the first record (at ``first``); False where it is not
        the common one."""
        head = _CDR_HEAD if self.encoding == "cdr" else _ROS1_HEAD
        if self.container == "ros1":
            # writers give every message record the same header length: op, conn and time
            header_len = int(np.frombuffer(buffer, "<u4", 1, first)[0]) if 0 <= first <= len(buffer) - 4 else -1
            if not 0 < header_len < 4096:
                return False
            fields = [("header_len", "<u4"), ("header", f"V{header_len}"), ("data_len", "<u4"), ("head", head)]
            self.data_at = 8 + header_len
        else:
            fields = [("op", "u1"), ("length", "<u8"), ("rest", f"V{_MCAP_MESSAGE_HEADER - 9}"), ("head", head)]
            self.data_at = _MCAP_MESSAGE_HEADER
        self.prefix = np.dtype(fields)
        self.raw = [np.empty((n, self.prefix.itemsize), dtype=np.uint8) for n in self.counts]
        return True

    def _offsets(self, entries: np.ndarray) -> np.ndarray:
        """The record offsets in their chunk of index entries (ROS 1's, or MCAP's rows)."""
        return entries["offset"] if self.container == "ros1" else entries[:, 1]

    def add(self, buffer: np.ndarray, begins: int, positions: dict[int, np.ndarray]) -> None:
        """The messages of the chunk just decompressed into ``buffer`` at ``begins``, by its
        index (per source: ROS 1 index entries, or MCAP (log time, offset) rows)."""
        if self.failed:
            return
        parts = [(k, entries) for k, (source, _) in enumerate(self.sources) if len(entries := positions.get(source, ()))]
        if not parts:
            return
        offset = np.concatenate([self._offsets(entries) for _, entries in parts]).astype(np.int64)
        offset += begins
        try:
            if any(self.filled[k] + len(entries) > self.counts[k] for k, entries in parts):
                raise ValueError("more messages than the group's indexes say")
            if self.prefix is None and not self._layout(buffer, int(offset[0])):
                raise ValueError("not the common record layout")
            assert self.prefix is not None
            raw = _gather(buffer, offset, self.prefix.itemsize, "u1")
            frame_len = raw[:, -4:].view("<u4")[:, 0].astype(np.int64)  # the head's last field
            if self.encoding == "cdr":  # after the body's 12 bytes and the frame id, to 8
                floats = (frame_len + 19) // 8 * 8 + (4 + self.data_at)
            else:
                floats = frame_len + (16 + self.data_at)
            floats += offset
            gyro, accel = _vectors(buffer, floats)  # as decode_imu
        except (IndexError, ValueError):  # past the buffer's end, or another layout
            self.failed = True
            return
        at = 0
        for k, entries in parts:
            lo, n = self.filled[k], len(entries)
            self.raw[k][lo : lo + n] = raw[at : at + n]
            self.gyro[k][lo : lo + n] = gyro[at : at + n]
            self.accel[k][lo : lo + n] = accel[at : at + n]
            # the entries' plain view (ROS 1's three uint32 a message): joined faster than fields
            self.pieces[k].append((entries.view("<u4").reshape(n, 3) if self.container == "ros1" else entries, begins))
            self.filled[k] = lo + n
            at += n

    def batches(self, buffer: np.ndarray) -> list[RawBatch] | None:
        """The batches of the group, a source each, decoded; None where the group must be
        decoded as before (see the class's docstring)."""
        if self.failed:
            return None
        out = []
        for k, (_, topic) in enumerate(self.sources):
            n = self.filled[k]
            if not n:
                continue
            assert self.prefix is not None
            records = self.raw[k][:n].view(self.prefix).ravel()
            pieces = self.pieces[k]
            entries = pieces[0][0] if len(pieces) == 1 else np.concatenate([entries for entries, _ in pieces])
            begins = np.repeat(np.array([b for _, b in pieces], dtype=np.int64), [len(e) for e, _ in pieces])
            starts = entries[:, -1].astype(np.int64) + begins + self.data_at  # (offset: the last column)
            if self.container == "ros1":  # (sec, nsec, offset)
                if not np.all(records["header_len"] == self.data_at - 8):
                    return None
                lengths = records["data_len"].astype(np.int64)
                log_ns = entries[:, 0].astype(np.int64) * 1_000_000_000 + entries[:, 1]
            else:  # (log time, offset)
                lengths = records["length"].astype(np.int64) - (_MCAP_MESSAGE_HEADER - 9)
                log_ns = entries[:, 0].astype(np.int64)
            head = records["head"]
            frame_len = head["frame_len"].astype(np.int64)
            # decode_imu's checks
            if self.encoding == "cdr":
                if not np.all(head["encapsulation"] == 0x0100):
                    return None
                needed, frame_chars = 4 + (frame_len + 19) // 8 * 8 + _TAIL, frame_len - 1
            else:
                needed, frame_chars = 16 + frame_len + _TAIL, frame_len
            if not (np.all(lengths >= needed) and np.all(frame_chars >= 0) and int((starts + lengths).max()) <= len(buffer)):
                return None
            stamp = head["sec"].astype(np.int64) * 1_000_000_000 + head["nsec"]
            decoded = DecodedBatch(
                topic, stamp, log_ns, self.gyro[k][:n], self.accel[k][:n],
                _frame_ids(buffer, starts + 16, frame_chars, None), np.zeros(0, dtype=np.int64),
            )
            out.append(RawBatch(topic, self.encoding, buffer, starts, lengths, log_ns, decoded=decoded))
        return out


# --------------------------------------------------------------------------- MCAP

_MCAP_MESSAGE_HEADER = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log, publish
_MCAP_OP_MESSAGE_INDEX = 0x07


def _copy_into(records: bytes | memoryview, out: memoryview) -> int:
    """As much of ``records`` as ``out`` holds, copied in; returns the length of ``records``."""
    n = min(len(records), len(out))
    out[:n] = records[:n]
    return len(records)


def _decompress_into(compression: str, data: bytes | memoryview, out: memoryview) -> int:
    """Decompress ``data`` into ``out``; returns the size decompressed (more than ``len(out)``
    when it does not fit). zstd and lz4 write in place; the others are copied."""
    if compression == "":
        return _copy_into(data, out)
    if compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(data)
        done = 0
        while done < len(out):
            got = reader.readinto(out[done:])
            if not got:
                break
            done += got
        if done == len(out) and reader.read(1):
            return done + 1  # more than the header says
        return done
    if compression == "lz4":
        from imucal_cli.io.lz4frames import decompress_into

        return decompress_into(data, np.frombuffer(out, dtype=np.uint8))
    raise ValueError(f"unsupported chunk compression {compression!r}")


class McapChunks:
    """Bulk access to an MCAP file's chunks through its summary and message indexes."""

    def __init__(self, handle: BinaryIO) -> None:
        from mcap.reader import SeekingReader

        self.handle = handle
        self.summary = SeekingReader(handle).get_summary()

    @property
    def usable(self) -> bool:
        """Chunked, with chunk and message indexes (what every indexed writer makes)."""
        s = self.summary
        return bool(s and s.chunk_indexes and all(c.message_index_offsets for c in s.chunk_indexes))

    def read_chunk(self, chunk_index: object, out: memoryview | None = None) -> memoryview:
        """The decompressed records of one chunk, written into ``out`` when given (it must hold
        the chunk's uncompressed size), and checked against the chunk's size and CRC."""
        ci = chunk_index
        raw = _pread(self.handle, ci.chunk_start_offset, ci.chunk_length)  # type: ignore[attr-defined]
        # opcode(1) length(8) start(8) end(8) uncompressed_size(8) crc(4) compression(str) records(u64 + bytes)
        pos = 1 + 8 + 8 + 8
        uncompressed_size, crc = struct.unpack_from("<QI", raw, pos)
        pos += 8 + 4
        (name_len,) = struct.unpack_from("<I", raw, pos)
        compression = raw[pos + 4 : pos + 4 + name_len].decode()
        pos += 4 + name_len
        (records_len,) = struct.unpack_from("<Q", raw, pos)
        pos += 8
        if pos + records_len > len(raw):
            raise ValueError("chunk cut off")
        if out is None:
            out = memoryview(bytearray(uncompressed_size))
        if len(out) != uncompressed_size:
            raise ValueError(f"the chunk index says {len(out)} bytes, the chunk {uncompressed_size}")
        written = _decompress_into(compression, memoryview(raw)[pos : pos + records_len], out)
        if written != uncompressed_size:
            raise ValueError(f"decompressed to {written} bytes, the header says {uncompressed_size}")
        if crc and zlib.crc32(out) != crc:
            raise ValueError("CRC mismatch")
        return out

    def message_positions(self, chunk_index: object, channel_ids: set[int]) -> dict[int, np.ndarray]:
        """Per channel: (n, 2) uint64 of (log_time, offset in the chunk's records)."""
        ci = chunk_index
        offsets = {c: o for c, o in ci.message_index_offsets.items() if c in channel_ids}  # type: ignore[attr-defined]
        if not offsets:
            return {}
        start = min(ci.message_index_offsets.values())  # type: ignore[attr-defined]
        block = _pread(self.handle, start, ci.message_index_length)  # type: ignore[attr-defined]
        out = {}
        for channel, offset in offsets.items():
            pos = offset - start
            if block[pos] != _MCAP_OP_MESSAGE_INDEX:
                raise ValueError("message index record expected")
            (length,) = struct.unpack_from("<I", block, pos + 1 + 8 + 2)
            entries = np.frombuffer(block, dtype="<u8", count=length // 8, offset=pos + 1 + 8 + 2 + 4)
            out[channel] = entries.reshape(-1, 2)
        return out

    def batches(
        self, wanted: dict[int, tuple[str, str]], losses: list | None = None, group_bytes: int | None = None
    ) -> Iterator[RawBatch]:
        """Raw batches of the wanted channels (channel id -> (topic, encoding)).

        Consecutive chunks are decompressed into one buffer and decoded together, up to
        ``group_bytes`` of records, so that the per-call cost of the vectorised decoder is spread
        over many messages. A chunk that does not decompress or fails its CRC is skipped and
        recorded in ``losses`` with the exact message counts of its index.
        """
        def read(group: list[tuple[object, dict[int, np.ndarray]]], lost: list | None) -> Iterable[RawBatch]:
            buffer, pending, decoded = self._read_group(group, wanted, lost)
            return decoded if decoded is not None else self._group(buffer, pending, wanted)

        yield from _decoded_groups(read, self._groups(wanted, group_bytes or GROUP_BYTES), losses)

    def _groups(self, wanted: dict[int, tuple[str, str]], group_bytes: int) -> Iterator[list[tuple[object, dict[int, np.ndarray]]]]:
        """Consecutive chunks with wanted messages, with their message positions, up to
        ``group_bytes`` of records a group."""
        assert self.summary is not None
        ids = set(wanted)
        chunks = sorted(self.summary.chunk_indexes, key=lambda c: (c.message_start_time, c.chunk_start_offset))
        group: list[tuple[object, dict[int, np.ndarray]]] = []
        size = 0
        for ci in chunks:
            if not ids & set(ci.message_index_offsets):
                continue
            positions = self.message_positions(ci, ids)
            if not any(len(p) for p in positions.values()):
                continue
            group.append((ci, positions))
            size += ci.uncompressed_size
            if size >= group_bytes:
                yield group
                group, size = [], 0
        if group:
            yield group

    def _read_group(
        self, group: list[tuple[object, dict[int, np.ndarray]]], wanted: dict[int, tuple[str, str]], losses: list | None
    ) -> tuple[np.ndarray, list[tuple[int, dict[int, np.ndarray]]], list[RawBatch] | None]:
        """The group's chunks decompressed side by side into one buffer, where each begins with
        its message positions, and their batches decoded where the whole group could be decoded
        chunk by chunk (see _WarmDecode; None otherwise)."""
        from imucal_cli.io.salvage import Loss

        sizes = [ci.uncompressed_size for ci, _ in group]  # type: ignore[attr-defined]
        buffer = np.empty(sum(n for n in sizes if n <= _MAX_CHUNK), dtype=np.uint8)
        view = memoryview(buffer)
        # every message index offset must lie inside its chunk: checked for the whole group at
        # once, and chunk by chunk only where that finds one outside
        inside = _records_inside([(_mcap_offsets(positions), n) for (_, positions), n in zip(group, sizes, strict=True)], _MCAP_MESSAGE_HEADER)
        encodings = {encoding for _, encoding in wanted.values()}
        warm = None
        if inside and len(encodings) == 1:
            counts: dict[int, int] = {}
            for _, positions in group:
                for channel, entries in positions.items():
                    counts[channel] = counts.get(channel, 0) + len(entries)
            warm = _WarmDecode("mcap", encodings.pop(), {c: topic for c, (topic, _) in wanted.items()}, counts)
        pending: list[tuple[int, dict[int, np.ndarray]]] = []
        at = 0
        for (ci, positions), n in zip(group, sizes, strict=True):
            try:
                if n > _MAX_CHUNK:
                    raise ValueError(f"implausible uncompressed size {n}")
                if not inside and not _records_inside([(_mcap_offsets(positions), n)], _MCAP_MESSAGE_HEADER):
                    raise ValueError("message index offsets past the chunk's end")
                self.read_chunk(ci, view[at : at + n])
            except Exception as exc:  # noqa: BLE001 - a damaged chunk is lost, the others are read
                if losses is None:
                    raise
                counts = {wanted[c][0]: len(p) for c, p in positions.items() if len(p)}
                losses.append(Loss(f"chunk that cannot be read ({exc})", ci.chunk_start_offset, ci.chunk_length, ci.message_start_time, ci.message_end_time, counts))  # type: ignore[attr-defined]
                continue
            if warm is not None:
                warm.add(buffer, at, positions)
            pending.append((at, positions))
            at += n
        return buffer[:at], pending, warm.batches(buffer[:at]) if warm is not None else None

    @staticmethod
    def _group(buffer: np.ndarray, pending: list[tuple[int, dict[int, np.ndarray]]], wanted: dict[int, tuple[str, str]]) -> Iterator[RawBatch]:
        for channel, (topic, encoding) in wanted.items():
            parts = [(e, b) for b, positions in pending if len(e := positions.get(channel, ()))]
            if not parts:
                continue
            offset = np.concatenate([e[:, 1].astype(np.int64) + b for e, b in parts])
            log_ns = np.concatenate([e[:, 0].astype(np.int64) for e, _ in parts])
            # the record's length and the message's first 16 bytes in one gather, where they fit
            head_dtype = _CDR_HEAD if encoding == "cdr" else _ROS1_HEAD
            records = np.dtype([("op", "u1"), ("length", "<u8"), ("rest", f"V{_MCAP_MESSAGE_HEADER - 9}"), ("head", head_dtype)])
            head = None
            if len(offset) and int(offset.max()) + records.itemsize <= len(buffer):
                both = _gather(buffer, offset, records.itemsize, "u1").view(records).ravel()
                record_len, head = both["length"].astype(np.int64), both["head"]
            else:
                record_len = _gather(buffer, offset + 1, 8, "<u8").ravel().astype(np.int64)
            data_len = record_len - (_MCAP_MESSAGE_HEADER - 9)
            if head is not None and not np.all(data_len >= 16):
                head = None
            yield RawBatch(topic, encoding, buffer, offset + _MCAP_MESSAGE_HEADER, data_len, log_ns, head)


def _mcap_offsets(positions: dict[int, np.ndarray]) -> list[np.ndarray]:
    """The record offsets of a chunk's message index entries ((log time, offset) rows), a channel each."""
    return [entries[:, 1] for entries in positions.values()]


def mcap_batches(path: Path, topics: Iterable[str], losses: list | None = None) -> Iterator[RawBatch] | None:
    """Fast batches of an indexed MCAP file, or None when it has no usable indexes."""
    handle = path.open("rb")
    try:
        chunks = McapChunks(handle)
    except Exception:
        handle.close()
        return None
    if not chunks.usable:
        handle.close()
        return None
    assert chunks.summary is not None
    wanted_topics = set(topics)
    wanted = {
        cid: (ch.topic, "ros1" if ch.message_encoding == "ros1" else ch.message_encoding)
        for cid, ch in chunks.summary.channels.items()
        if ch.topic in wanted_topics and ch.message_encoding in ("cdr", "ros1")
    }

    def generate() -> Iterator[RawBatch]:
        try:
            yield from chunks.batches(wanted, losses)
        finally:
            handle.close()

    return generate()


# --------------------------------------------------------------------------- rosbag2 sqlite3


def sqlite_batches(
    db_paths: list[Path], topics: Iterable[str], batch_rows: int = 65536, losses: list | None = None
) -> Iterator[RawBatch]:
    """Row batches of rosbag2 sqlite3 storage files (uncompressed messages). Where a damaged
    file stops the query, what was read is kept and the rest recorded in ``losses``.

    The rows are fetched and packed a batch ahead in a thread (SQLite steps outside the GIL)
    while the batches before are decoded.
    """
    for names, buffer, starts, lengths, topic_ids, times in _ahead(_sqlite_packed(db_paths, set(topics), batch_rows, losses)):
        for tid, name in names.items():
            pick = topic_ids == tid
            if pick.all():
                yield RawBatch(name, "cdr", buffer, starts, lengths, times)
            elif pick.any():
                yield RawBatch(name, "cdr", buffer, starts[pick], lengths[pick], times[pick])


def _message_pages(connection: sqlite3.Connection, db_path: Path) -> MessagePages | None:
    """The page reader of the file's ``messages`` table when its schema is rosbag2's, else None."""
    from imucal_cli.io.sqlitepages import MessagePages, PageLayoutError

    if not hasattr(os, "preadv"):  # positioned reads (not on Windows): SQLite reads it
        return None
    try:
        columns = connection.execute("PRAGMA table_info(messages)").fetchall()
        root = connection.execute("SELECT rootpage FROM sqlite_master WHERE type = 'table' AND name = 'messages'").fetchone()
    except sqlite3.DatabaseError:
        return None
    layout = [(name, str(kind).upper(), pk) for _, name, kind, _, _, pk in columns]
    if root is None or layout[:4] != [("id", "INTEGER", 1), ("topic_id", "INTEGER", 0), ("timestamp", "INTEGER", 0), ("data", "BLOB", 0)] or len(layout) != 4:
        return None
    try:
        return MessagePages(db_path, int(root[0]))
    except (PageLayoutError, OSError):
        return None


def _sqlite_packed(
    db_paths: list[Path], wanted: set[str], batch_rows: int, losses: list | None
) -> Iterator[tuple[dict[int, str], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    from imucal_cli.io.salvage import Loss
    from imucal_cli.io.sqlitepages import PageLayoutError

    for db_path in db_paths:
        # made and used in the reading thread; closed wherever the generator ends
        connection = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, check_same_thread=False)
        connection.text_factory = lambda raw: raw.decode("utf-8", errors="replace")  # damaged text stays readable
        try:
            rows = connection.execute("SELECT id, name, serialization_format FROM topics").fetchall()
            names = {tid: name for tid, name, fmt in rows if name in wanted and fmt == "cdr"}
            if not names:
                continue
            last_rowid = 0
            pages = _message_pages(connection, db_path)
            if pages is not None:
                try:
                    for group in pages.rows(set(names)):
                        last_rowid = group.last_rowid
                        yield names, group.buffer, group.starts, group.lengths, group.topic_ids, group.timestamps
                    continue
                except PageLayoutError:
                    pass  # read on from the last whole group through SQLite
                finally:
                    pages.close()
            marks = ",".join("?" * len(names))
            cursor = connection.execute(
                f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) AND id > ?",  # noqa: S608
                [*names, last_rowid],
            )
            while True:
                try:
                    chunk = cursor.fetchmany(batch_rows)
                except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
                    if losses is None:
                        raise
                    losses.append(Loss(f"rows of {db_path.name} that cannot be read ({exc})", 0, 0))
                    break
                if not chunk:
                    break
                id_column, time_column, blobs = zip(*chunk)
                topic_ids = np.fromiter(id_column, dtype=np.int64, count=len(chunk))
                times = np.fromiter(time_column, dtype=np.int64, count=len(chunk))
                buffer, starts, lengths = pack_blobs(blobs)
                yield names, buffer, starts, lengths, topic_ids, times
        finally:
            connection.close()


# --------------------------------------------------------------------------- ROS 1 bag


def _ros1_header(data: bytes, pos: int) -> tuple[dict[str, bytes], int]:
    """Parse a record header at ``pos``; return its fields and the position after it."""
    (length,) = struct.unpack_from("<I", data, pos)
    pos += 4
    end = pos + length
    fields = {}
    while pos < end:
        (flen,) = struct.unpack_from("<I", data, pos)
        field = data[pos + 4 : pos + 4 + flen]
        name, _, value = field.partition(b"=")
        fields[name.decode()] = value
        pos += 4 + flen
    return fields, end


def _ros1_index_header(data: bytes, pos: int) -> tuple[int, int, int, int]:
    """The op, connection and count of an index data record's header at ``pos`` (op 0 where
    it has none: not such a record), and the position after it; :func:`_ros1_header` for the
    three fields it needs, without a dict (a chunk's index has one record a connection)."""
    (length,) = _U32.unpack_from(data, pos)
    pos += 4
    end = pos + length
    op, conn, count = 0, None, None
    while pos < end:
        (flen,) = _U32.unpack_from(data, pos)
        name_at = pos + 4
        pos = name_at + flen
        if data[name_at : name_at + 3] == b"op=":
            if flen <= 3:
                raise IndexError("op field without a value")
            op = data[name_at + 3]
        elif data[name_at : name_at + 5] == b"conn=" and flen == 9:
            (conn,) = _U32.unpack_from(data, name_at + 5)
        elif data[name_at : name_at + 6] == b"count=" and flen == 10:
            (count,) = _U32.unpack_from(data, name_at + 6)
    if op == 0x04 and (conn is None or count is None):
        raise KeyError("conn" if conn is None else "count")
    return op, conn or 0, count or 0, end


class _ChunkLost(Exception):  # internal signal: a chunk that cannot be read
    def __init__(self, reason: str, nbytes: int, start_ns: int | None, end_ns: int | None, counts: dict[str, int]) -> None:
        super().__init__(reason)
        self.reason, self.nbytes, self.start_ns, self.end_ns, self.counts = reason, nbytes, start_ns, end_ns, counts


class Ros1Bag:
    """Bulk access to an indexed ROS 1 bag (format 2.0): chunks and their index data."""

    def __init__(self, handle: BinaryIO) -> None:
        self.handle = handle
        handle.seek(0)
        if handle.read(13) != b"#ROSBAG V2.0\n":
            raise ValueError("not a ROS 1 bag v2.0")
        head = handle.read(4096)
        fields, _ = _ros1_header(head, 0)
        self.index_pos = struct.unpack("<Q", fields["index_pos"])[0]
        self.conn_count = struct.unpack("<I", fields["conn_count"])[0]
        self.chunk_count = struct.unpack("<I", fields["chunk_count"])[0]
        if self.index_pos == 0:
            raise ValueError("bag has no index")
        handle.seek(self.index_pos)
        index = handle.read()
        pos = 0
        self.topics: dict[int, str] = {}
        self.types: dict[int, str] = {}
        self.counts: dict[int, int] = {}
        self.chunk_positions: list[int] = []
        #: Per chunk: an upper bound of the bytes of the index data records after it (from
        #: the message counts of its chunk info), read with the chunk in one go.
        self.index_bytes: list[int] = []
        while pos < len(index):
            fields, pos = _ros1_header(index, pos)
            (data_len,) = struct.unpack_from("<I", index, pos)
            data = index[pos + 4 : pos + 4 + data_len]
            pos += 4 + data_len
            op = fields.get("op", b"\x00")[0]
            if op == 0x07:  # connection
                conn = struct.unpack("<I", fields["conn"])[0]
                self.topics[conn] = fields["topic"].decode()
                inner, _ = _ros1_header(struct.pack("<I", len(data)) + data, 0)
                self.types[conn] = inner.get("type", b"").decode()
            elif op == 0x06:  # chunk info: position, then (connection, count) pairs
                self.chunk_positions.append(struct.unpack("<Q", fields["chunk_pos"])[0])
                pairs = np.frombuffer(data, dtype="<u4").reshape(-1, 2)
                # per connection: its record's header (about 50 bytes), data length, entries;
                # bounded (a damaged count could claim anything: more is read when needed)
                expected = int(pairs[:, 1].astype(np.int64).sum()) * _ROS1_INDEX_ENTRY.itemsize + 128 * len(pairs)
                self.index_bytes.append(min(expected, _ROS1_MAX_INDEX_READ))
                for conn, count in pairs.tolist():
                    self.counts[conn] = self.counts.get(conn, 0) + count
        if len(self.topics) != self.conn_count or len(self.chunk_positions) != self.chunk_count:
            raise ValueError(
                f"index incomplete ({len(self.topics)} of {self.conn_count} connections, "
                f"{len(self.chunk_positions)} of {self.chunk_count} chunks)"
            )

    def batches(self, topics: Iterable[str], losses: list | None = None, group_bytes: int | None = None) -> Iterator[RawBatch]:
        """Raw batches of the wanted topics; consecutive chunks are decoded together, up to
        ``group_bytes``, so the vectorised decoder's per-call cost is spread over many messages.
        A chunk that cannot be read is skipped and recorded in ``losses`` (counts from its index)."""
        wanted = {c: t for c, t in self.topics.items() if t in set(topics)}

        def read(group: list[tuple[int, bytes, int]], lost: list | None) -> list[RawBatch]:
            return self._read_group(group, wanted, lost)

        yield from _decoded_groups(read, self._groups(group_bytes or GROUP_BYTES), losses)

    def _groups(self, group_bytes: int) -> Iterator[list[tuple[int, bytes, int]]]:
        """Consecutive chunks, each as its position, the first bytes there (its header, read
        once here) and the size of its index data, up to ``group_bytes`` of records (the sizes
        their headers give) a group."""
        group: list[tuple[int, bytes, int]] = []
        size = 0
        for chunk_pos, index_bytes in zip(self.chunk_positions, self.index_bytes, strict=True):
            head = _pread(self.handle, chunk_pos, 4096)
            group.append((chunk_pos, head, index_bytes))
            try:
                fields, _ = _ros1_header(head, 0)
                size += struct.unpack("<I", fields["size"])[0]
            except Exception:  # noqa: BLE001, S110 - damage: met again, and recorded, where it is read
                pass
            if size >= group_bytes:
                yield group
                group, size = [], 0
        if group:
            yield group

    def _read_group(self, group: list[tuple[int, bytes, int]], wanted: dict[int, str], losses: list | None) -> list[RawBatch]:
        """The raw batches of a group of chunks, decompressed side by side into one buffer; a
        chunk that cannot be read is recorded in ``losses`` (raised where that is None)."""
        from imucal_cli.io.salvage import Loss

        def lose(chunk_pos: int, exc: Exception) -> None:
            if losses is None:
                if isinstance(exc, _ChunkLost):
                    raise ValueError(exc.reason) from None
                raise exc
            if isinstance(exc, _ChunkLost):
                losses.append(Loss(f"chunk that cannot be read ({exc.reason})", chunk_pos, exc.nbytes, exc.start_ns, exc.end_ns, exc.counts))
            else:  # a damaged chunk header or index
                losses.append(Loss(f"chunk that cannot be read ({type(exc).__name__}: {exc})", chunk_pos, 0))

        chunks: list[tuple[int, _StoredChunk]] = []
        for chunk_pos, head, index_bytes in group:
            try:
                chunk = self._read_chunk(chunk_pos, wanted, head, index_bytes)
                if chunk is not None and not chunk.size_plausible():  # before making room for it
                    raise chunk.lost("chunk size mismatch", wanted)
                if chunk is not None:
                    chunks.append((chunk_pos, chunk))
            except Exception as exc:  # noqa: BLE001 - recorded (or raised) by lose
                lose(chunk_pos, exc)
        if not chunks:
            return []
        buffer = np.empty(sum(chunk.size for _, chunk in chunks), dtype=np.uint8)
        # where every index offset lies inside its chunk (the rule), each chunk is decoded
        # right after it is decompressed (see _WarmDecode)
        warm = None
        if _records_inside([chunk.offsets_and_size() for _, chunk in chunks], _ROS1_RECORD_START):
            counts: dict[int, int] = {}
            for _, chunk in chunks:
                for conn, entries in chunk.positions.items():
                    counts[conn] = counts.get(conn, 0) + len(entries)
            warm = _WarmDecode("ros1", "ros1", wanted, counts)
        read: list[tuple[int, _StoredChunk, int]] = []
        at = 0
        for chunk_pos, chunk in chunks:
            try:
                chunk.decompress_into(buffer[at : at + chunk.size], wanted)
            except Exception as exc:  # noqa: BLE001 - recorded (or raised) by lose
                lose(chunk_pos, exc)
                continue  # its room is taken by the next chunk
            if warm is not None:
                warm.add(buffer, at, chunk.positions)
            read.append((chunk_pos, chunk, at))
            at += chunk.size
        if warm is not None and (decoded := warm.batches(buffer[:at])) is not None:
            return decoded
        # every index offset must lie inside its chunk, or the chunk is damaged: checked for
        # the whole group at once, and chunk by chunk only where that finds one outside
        if read and not _records_inside([chunk.offsets_and_size() for _, chunk, _ in read], _ROS1_RECORD_START):
            inside = []
            for chunk_pos, chunk, begins in read:
                if _records_inside([chunk.offsets_and_size()], _ROS1_RECORD_START):
                    inside.append((chunk_pos, chunk, begins))
                else:
                    lose(chunk_pos, chunk.lost("index offsets past the chunk's end", wanted, times=False))
            read = inside
        return list(self._group(buffer[:at], [(begins, chunk.positions) for _, chunk, begins in read], wanted))

    @staticmethod
    def _group(buffer: np.ndarray, pending: list[tuple[int, dict[int, np.ndarray]]], wanted: dict[int, str]) -> Iterator[RawBatch]:
        for conn, topic in wanted.items():
            parts = [(e, b) for b, positions in pending if len(e := positions.get(conn, ()))]
            if not parts:
                continue
            offset = np.concatenate([e["offset"] for e, _ in parts]).astype(np.int64)
            offset += np.repeat([b for _, b in parts], [len(e) for e, _ in parts])  # where its chunk begins
            sec = np.concatenate([e["sec"] for e, _ in parts]).astype(np.int64)
            nsec = np.concatenate([e["nsec"] for e, _ in parts]).astype(np.int64)
            log_ns = sec * 1_000_000_000 + nsec
            # writers give every message record the same header length: then the record header,
            # the data length and the message's first 16 bytes come in one gather
            first = int(np.frombuffer(buffer, "<u4", 1, int(offset[0]))[0]) if 0 <= offset[0] <= len(buffer) - 4 else -1
            records = np.dtype([("header_len", "<u4"), ("header", f"V{max(first, 1)}"), ("data_len", "<u4"), ("head", _ROS1_HEAD)])
            if 0 < first < 4096 and int(offset.min()) >= 0 and int(offset.max()) + records.itemsize <= len(buffer):
                both = _gather(buffer, offset, records.itemsize, "u1").view(records).ravel()
                if np.all(both["header_len"] == first):
                    data_len = both["data_len"].astype(np.int64)
                    head = both["head"] if np.all(data_len >= 16) else None
                    yield RawBatch(topic, "ros1", buffer, offset + 8 + first, data_len, log_ns, head)
                    continue
            header_len = _gather(buffer, offset, 4, "<u4").ravel().astype(np.int64)
            data_len = _gather(buffer, offset + 4 + header_len, 4, "<u4").ravel().astype(np.int64)
            yield RawBatch(topic, "ros1", buffer, offset + 8 + header_len, data_len, log_ns)

    def _read_chunk(self, chunk_pos: int, wanted: dict[int, str], head: bytes, index_bytes: int) -> _StoredChunk | None:
        """One chunk as stored and, per wanted connection, its index entries; None where it
        holds none of them (positioned reads: threads read chunks side by side); ``head`` is the first 4096 bytes
        at ``chunk_pos`` (its header), read when the groups were made; ``index_bytes`` what the
        index data records after the chunk are expected to take (read with it)."""
        fields, pos = _ros1_header(head, 0)
        compression = fields["compression"].decode()
        size = struct.unpack("<I", fields["size"])[0]
        (data_len,) = struct.unpack_from("<I", head, pos)
        start = chunk_pos + pos + 4
        raw = _pread(self.handle, start, data_len + index_bytes)

        def have(end: int) -> bool:
            """Whether ``raw`` reaches ``end``, read further if it does not yet."""
            nonlocal raw
            if end > len(raw) and len(raw) >= data_len:  # an index larger than expected
                raw += _pread(self.handle, start + len(raw), end - len(raw) + 4096)
            return end <= len(raw)

        # index data records follow the chunk, one per connection in it
        positions: dict[int, np.ndarray] = {}
        at = data_len
        while have(at + 8):
            (header_len,) = struct.unpack_from("<I", raw, at)
            if header_len > 4096 or not have(at + 8 + header_len):
                break
            try:
                op, conn, count, pos = _ros1_index_header(raw, at)
            except struct.error:
                break
            if op != 0x04:
                break
            (dlen,) = struct.unpack_from("<I", raw, pos)
            if conn in wanted:
                have(pos + 4 + dlen)
                entries = np.frombuffer(raw[pos + 4 : pos + 4 + dlen], dtype=_ROS1_INDEX_ENTRY, count=count)
                positions[conn] = entries
            at = pos + 4 + dlen
        if not positions:
            return None
        return _StoredChunk(compression, memoryview(raw)[:data_len], data_len, size, positions)


@dataclass(frozen=True)
class _StoredChunk:
    """A ROS 1 chunk as stored (``compressed``, ``data_len`` bytes by its record) and, per
    wanted connection, its index entries."""

    compression: str
    compressed: memoryview
    data_len: int
    size: int  # decompressed, by its header
    positions: dict[int, np.ndarray]

    def offsets_and_size(self) -> tuple[list[np.ndarray], int]:
        """Its records' offsets (an array a wanted connection) and its decompressed size."""
        return [entries["offset"] for entries in self.positions.values()], self.size

    def size_plausible(self) -> bool:
        """Whether its header's decompressed size can be true (a damaged one could claim any,
        and room is made for it before decompressing): at most :data:`_MAX_CHUNK`, the
        stored size when stored as it is, at most 255 times it (and a frame's few bytes) from
        LZ4, whose longest match adds 255 bytes a byte."""
        if self.compression == "none":
            return self.size == self.data_len
        if self.compression == "lz4":
            return self.size <= min(_MAX_CHUNK, 255 * self.data_len + 4096)
        return self.size <= _MAX_CHUNK

    def decompress_into(self, out: np.ndarray, wanted: dict[int, str]) -> None:
        """The chunk's records written into ``out`` (``size`` bytes); raises :class:`_ChunkLost`
        (with what its index says is lost) where it cannot be read."""
        try:
            if len(self.compressed) != self.data_len:
                raise ValueError("chunk cut off")
            if self.compression == "none":
                done = _copy_into(self.compressed, memoryview(out))
            elif self.compression == "bz2":
                import bz2

                done = _copy_into(bz2.decompress(self.compressed), memoryview(out))
            elif self.compression == "lz4":
                from imucal_cli.io.lz4frames import decompress_into

                done = decompress_into(self.compressed, out)
            else:
                raise ValueError(f"unsupported chunk compression {self.compression!r}")
            if done != self.size:
                raise ValueError("chunk size mismatch")
        except Exception as exc:  # noqa: BLE001 - a damaged chunk: its index says what is lost
            raise self.lost(str(exc), wanted) from None

    def lost(self, reason: str, wanted: dict[int, str], times: bool = True) -> _ChunkLost:
        """The chunk lost for ``reason``: its bytes, and from its index the messages a topic
        and (with ``times``) the span of their times."""
        counts = {wanted[c]: len(e) for c, e in self.positions.items()}
        stamps = [int(e["sec"][k]) * 1_000_000_000 + int(e["nsec"][k]) for e in self.positions.values() if len(e) for k in (0, -1)] if times else []
        return _ChunkLost(reason, self.data_len, min(stamps, default=None), max(stamps, default=None), counts)
