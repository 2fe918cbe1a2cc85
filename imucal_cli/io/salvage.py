"""Reading what is intact in damaged logs.

A recorder killed mid-write leaves an MCAP file without its summary or a ROS 1 bag without its
index; a disk error leaves a chunk that does not decompress or fails its CRC. The readers here
walk such a file record by record from the start, keep every message that is whole, and record
what they could not read as :class:`Loss` entries (where in the file, which span of log time,
how many messages where the file says so). A chunk cut off by the end of the file is
decompressed as far as it goes (zstd, lz4 and bz2 streams decode a prefix), so the messages
before the cut are kept too. After a stretch of garbage the walk resynchronises on the next
record that parses as a chunk.

Speed is secondary here: messages inside chunks are walked one record at a time in Python
(about a microsecond each). The decoding itself stays vectorised (:func:`decode_imu`).
"""

from __future__ import annotations

import bz2
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from imucal_cli.io.fastimu import RawBatch, _ros1_header

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
#: Largest record a damaged length field is believed to announce when resynchronising.
_MAX_CHUNK = 1 << 31


@dataclass
class Loss:
    """A part of a log that could not be read."""

    reason: str
    offset: int  # byte offset in the file where it starts
    nbytes: int
    start_ns: int | None = None  # log-time span, where the container says
    end_ns: int | None = None
    messages: dict[str, int] | None = None  # per topic, where the container says
    lost: bool = True  # False: a note on how the log was read, nothing lost by it

    def describe(self) -> str:
        if not self.lost:
            return self.reason
        span = ""
        if self.start_ns is not None and self.end_ns is not None and self.end_ns >= self.start_ns:
            span = f", {(self.end_ns - self.start_ns) * 1e-9:.2f} s of log time"
        count = ""
        if self.messages:
            count = ", " + ", ".join(f"{n} messages of {t}" for t, n in sorted(self.messages.items()))
        return f"not read: {self.reason} at byte {self.offset} ({self.nbytes} bytes{span}{count})"


@dataclass
class Channel:
    topic: str
    encoding: str  # "cdr", "ros1" or what the file says
    msgtype: str


@dataclass
class ScanResult:
    """What a walk found: topics, message counts and losses (filled in as it goes)."""

    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)
    losses: list[Loss] = field(default_factory=list)
    truncated: bool = False


def _partial_decompress(compression: str, data: bytes) -> bytes:
    """As much of a compressed stream as decodes (the whole of it when it is intact)."""
    if compression in ("", "none"):
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    if compression == "bz2":
        return bz2.BZ2Decompressor().decompress(data)
    raise ValueError(f"unsupported compression {compression!r}")


def _decompress_whole(compression: str, data: bytes, size: int) -> bytes:
    out = _partial_decompress(compression, data)
    if len(out) != size:
        raise ValueError(f"decompressed to {len(out)} bytes, the header says {size}")
    return out


# --------------------------------------------------------------------------- MCAP

_KNOWN_MCAP_OPS = set(range(0x01, 0x10))


def _string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    if pos + 4 + n > len(buf):
        raise ValueError("string runs past its record")
    return buf[pos + 4 : pos + 4 + n].decode("utf-8", errors="replace"), pos + 4 + n


def _chunk_header(body: bytes) -> tuple[int, int, int, int, str, int, int]:
    """start, end, uncompressed size, crc, compression, records offset, records length."""
    start, end, size, crc = struct.unpack_from("<QQQI", body, 0)
    compression, pos = _string(body, 28)
    (records_len,) = struct.unpack_from("<Q", body, pos)
    return start, end, size, crc, compression, pos + 8, records_len


def _search(handle: BinaryIO, start: int, size: int, overlap: int, find: Callable[[bytes, int], int | None]) -> int | None:
    """The first file offset at or after ``start`` where ``find(block, limit)`` finds a record
    (the block is read in 1 MB pieces, ``overlap`` bytes longer so a record header is whole)."""
    block_size = 1 << 20
    pos = start
    while pos < size:
        handle.seek(pos)
        block = handle.read(block_size + overlap)
        if len(block) < 16:
            return None
        found = find(block, block_size)
        if found is not None:
            return pos + found
        pos += block_size
    return None


def _find_mcap_chunk(handle: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the next record at or after ``start`` that parses as a whole chunk."""

    def find(block: bytes, limit: int) -> int | None:
        arr = np.frombuffer(block, dtype=np.uint8)
        for k in np.flatnonzero(arr[:limit] == 0x06).tolist():
            if k + 45 > len(block):
                continue
            (length,) = struct.unpack_from("<Q", block, k + 1)
            (name_len,) = struct.unpack_from("<I", block, k + 1 + 8 + 28)
            if name_len not in (0, 3, 4) or length > _MAX_CHUNK:
                continue
            name = block[k + 9 + 32 : k + 9 + 32 + name_len]
            if name not in (b"", b"lz4", b"zstd") or k + 9 + 32 + name_len + 8 > len(block):
                continue
            (records_len,) = struct.unpack_from("<Q", block, k + 9 + 32 + name_len)
            if length == 32 + name_len + 8 + records_len:
                return k
        return None

    return _search(handle, start, size, 64, find)


def _mcap_records(records: bytes, result: ScanResult, wanted: set[int] | None, base_offset: int):
    """Walk the records of a chunk (or a run of top-level records): register schemas and
    channels, count messages, and return per wanted channel (log times, starts, lengths)."""
    schemas: dict[int, str] = getattr(result, "_schemas", {})
    result._schemas = schemas  # type: ignore[attr-defined]
    found: dict[int, tuple[list[int], list[int], list[int]]] = {}
    pos, n = 0, len(records)
    while pos + 9 <= n:
        op = records[pos]
        (length,) = struct.unpack_from("<Q", records, pos + 1)
        end = pos + 9 + length
        if end > n:
            break  # cut off: the rest of the chunk is lost
        body_at = pos + 9
        if op == 0x05 and length >= 22:
            (channel,) = struct.unpack_from("<H", records, body_at)
            result.counts[channel] = result.counts.get(channel, 0) + 1
            if wanted is None or channel in wanted:
                (log_time,) = struct.unpack_from("<Q", records, body_at + 6)
                lists = found.setdefault(channel, ([], [], []))
                lists[0].append(log_time)
                lists[1].append(base_offset + body_at + 22)
                lists[2].append(length - 22)
        elif op == 0x03:
            try:
                (sid,) = struct.unpack_from("<H", records, body_at)
                name, _ = _string(records[body_at:end], 2)
                schemas[sid] = name
            except (struct.error, ValueError):
                pass
        elif op == 0x04:
            try:
                body = records[body_at:end]
                cid, sid = struct.unpack_from("<HH", body, 0)
                topic, p = _string(body, 4)
                encoding, _ = _string(body, p)
                result.channels[cid] = Channel(topic, encoding, schemas.get(sid, ""))
            except (struct.error, ValueError):
                pass
        pos = end
    return found, pos


def _batches(result: ScanResult, wanted_topics: set[str] | None, found: dict, buffer: np.ndarray) -> Iterator[RawBatch]:
    """Raw batches of the wanted topics among the messages ``found`` in one buffer."""
    for cid, (times, starts, lengths) in found.items():
        channel = result.channels.get(cid)
        if channel is None or wanted_topics is None or channel.topic not in wanted_topics:
            continue
        if channel.encoding not in ("cdr", "ros1"):
            continue
        yield RawBatch(
            channel.topic, channel.encoding, buffer,
            np.asarray(starts, dtype=np.int64), np.asarray(lengths, dtype=np.int64), np.asarray(times, dtype=np.int64),
        )


def scan_mcap(path: Path, wanted_topics: set[str] | None = None) -> tuple[ScanResult, Iterator[RawBatch]]:
    """Walk an MCAP file from the start; with ``wanted_topics`` also yield raw batches of them
    (one per chunk and channel). The result fills in as the iterator is consumed."""
    result = ScanResult()

    def walk() -> Iterator[RawBatch]:
        size = path.stat().st_size
        with path.open("rb") as handle:
            if handle.read(8) != MCAP_MAGIC:
                raise ValueError("not an MCAP file (bad magic bytes)")
            pos = 8
            failed: Loss | None = None  # the last chunk that could not be read: message indexes follow it
            while pos < size:
                handle.seek(pos)
                head = handle.read(9)
                if len(head) < 9:
                    result.truncated = True
                    result.losses.append(Loss("file ends inside a record header", pos, size - pos))
                    return
                op = head[0]
                (length,) = struct.unpack_from("<Q", head, 1)
                end = pos + 9 + length
                if op not in _KNOWN_MCAP_OPS or (end > size and op != 0x06) or length > _MAX_CHUNK:
                    if op == 0x00 and head == b"\x00" * 9:
                        pass
                    nxt = _find_mcap_chunk(handle, pos + 1, size)
                    if end > size and op in _KNOWN_MCAP_OPS and nxt is None:
                        result.truncated = True
                        result.losses.append(Loss("file ends inside a record", pos, size - pos))
                        return
                    stop = size if nxt is None else nxt
                    result.losses.append(Loss("unreadable bytes (damaged record structure)", pos, stop - pos))
                    if nxt is None:
                        return
                    pos = nxt
                    continue
                body = handle.read(min(end, size) - pos - 9)
                if op == 0x06:
                    try:
                        start_ns, end_ns, usize, crc, compression, rec_at, rec_len = _chunk_header(body)
                    except (struct.error, ValueError):
                        result.truncated = end > size
                        result.losses.append(Loss("damaged chunk header", pos, min(end, size) - pos))
                        pos = min(end, size)
                        continue
                    data = body[rec_at : rec_at + rec_len]
                    cut = end > size or len(data) < rec_len
                    try:
                        if cut:
                            records = _partial_decompress(compression, data)
                        else:
                            records = _decompress_whole(compression, data, usize)
                            if crc and zlib.crc32(records) != crc:
                                raise ValueError("CRC mismatch")
                    except Exception as exc:  # noqa: BLE001 - any codec error means a lost chunk
                        failed = Loss(f"chunk that does not decompress ({exc})", pos, len(body) + 9, start_ns, end_ns, {})
                        result.losses.append(failed)
                        if cut:
                            result.truncated = True
                            return
                        pos = end
                        continue
                    failed = None
                    found, used = _mcap_records(records, result, None, 0)
                    if cut or used < len(records):
                        kept = max((max(t[0]) for t in found.values() if t[0]), default=start_ns)
                        reason = "chunk cut off by the end of the file" if cut else "chunk with a damaged record"
                        result.losses.append(Loss(reason, pos, min(end, size) - pos, kept, end_ns))
                    if wanted_topics is not None and found:
                        yield from _batches(result, wanted_topics, found, np.frombuffer(records, dtype=np.uint8))
                    if cut:
                        result.truncated = True
                        return
                elif op == 0x07 and failed is not None and failed.messages is not None:
                    try:
                        (cid,) = struct.unpack_from("<H", body, 0)
                        (nbytes,) = struct.unpack_from("<I", body, 2)
                        channel = result.channels.get(cid)
                        topic = channel.topic if channel else f"channel {cid}"
                        failed.messages[topic] = failed.messages.get(topic, 0) + nbytes // 16
                    except struct.error:
                        pass
                elif op in (0x03, 0x04, 0x05):  # top-level records (unchunked files)
                    record = head + body
                    found, _ = _mcap_records(record, result, None, 0)
                    if wanted_topics is not None and found:
                        yield from _batches(result, wanted_topics, found, np.frombuffer(record, dtype=np.uint8))
                elif op == 0x0F:  # data end: the summary follows, nothing more to read
                    return
                if op != 0x07:
                    failed = None if op != 0x06 else failed
                pos = end

    return result, walk()


# --------------------------------------------------------------------------- ROS 1


def _ros1_records(data: bytes, result: ScanResult, wanted: set[int] | None) -> tuple[dict, int]:
    found: dict[int, tuple[list[int], list[int], list[int]]] = {}
    pos, n = 0, len(data)
    while pos + 4 <= n:
        try:
            fields, hend = _ros1_header(data, pos)
            (dlen,) = struct.unpack_from("<I", data, hend)
        except (struct.error, ValueError, UnicodeDecodeError):
            break
        end = hend + 4 + dlen
        if hend > n or end > n:
            break
        op = fields.get("op", b"\xff")[:1]
        if op == b"\x02" and "conn" in fields and "time" in fields:
            conn = struct.unpack("<I", fields["conn"])[0]
            result.counts[conn] = result.counts.get(conn, 0) + 1
            if wanted is None or conn in wanted:
                sec, nsec = struct.unpack("<II", fields["time"])
                lists = found.setdefault(conn, ([], [], []))
                lists[0].append(sec * 1_000_000_000 + nsec)
                lists[1].append(hend + 4)
                lists[2].append(dlen)
        elif op == b"\x07" and "conn" in fields and "topic" in fields:
            _register_ros1_connection(result, fields, data[hend + 4 : end])
        pos = end
    return found, pos


def _register_ros1_connection(result: ScanResult, fields: dict[str, bytes], data: bytes) -> None:
    conn = struct.unpack("<I", fields["conn"])[0]
    try:
        inner, _ = _ros1_header(struct.pack("<I", len(data)) + data, 0)
    except (struct.error, ValueError):
        inner = {}
    msgtype = inner.get("type", b"").decode("utf-8", errors="replace")
    result.channels[conn] = Channel(fields["topic"].decode("utf-8", errors="replace"), "ros1", msgtype)


def _find_ros1_chunk(handle: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the next record at or after ``start`` whose header says it is a chunk."""

    def find(block: bytes, limit: int) -> int | None:
        at = 0
        while (k := block.find(b"op=\x05", at, limit)) >= 0:
            at = k + 1
            for h in range(max(0, k - 128), k - 7):
                try:
                    (hlen,) = struct.unpack_from("<I", block, h)
                    if not 8 <= hlen <= 256 or h + 4 + hlen <= k:
                        continue
                    fields, _ = _ros1_header(block, h)
                except (struct.error, ValueError):
                    continue
                if fields.get("op") == b"\x05" and "compression" in fields and "size" in fields:
                    return h
        return None

    return _search(handle, start, size, 256, find)


def scan_ros1(path: Path, wanted_topics: set[str] | None = None) -> tuple[ScanResult, Iterator[RawBatch]]:
    """Walk a ROS 1 bag (v2.0) from the start, index or not; like :func:`scan_mcap`."""
    result = ScanResult()

    def walk() -> Iterator[RawBatch]:
        size = path.stat().st_size
        with path.open("rb") as handle:
            if handle.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
                raise ValueError("not a ROS 1 bag v2.0 (bad magic bytes)")
            pos = len(ROS1_MAGIC)
            while pos < size:
                handle.seek(pos)
                head = handle.read(4)
                if len(head) < 4:
                    result.truncated = True
                    result.losses.append(Loss("file ends inside a record header", pos, size - pos))
                    return
                (hlen,) = struct.unpack("<I", head)
                header = handle.read(hlen) if hlen <= 1 << 20 else b""
                fields: dict[str, bytes] = {}
                dlen = -1
                try:
                    if len(header) != hlen or hlen > 1 << 20:
                        raise ValueError("header")
                    fields, _ = _ros1_header(head + header, 0)
                    dhead = handle.read(4)
                    if len(dhead) == 4:
                        (dlen,) = struct.unpack("<I", dhead)
                except (struct.error, ValueError, UnicodeDecodeError):
                    fields = {}
                op = fields.get("op", b"")[:1]
                if not fields or not op:
                    if pos + 4 + hlen > size:
                        result.truncated = True
                        result.losses.append(Loss("file ends inside a record", pos, size - pos))
                        return
                    nxt = _find_ros1_chunk(handle, pos + 1, size)
                    stop = size if nxt is None else nxt
                    result.losses.append(Loss("unreadable bytes (damaged record structure)", pos, stop - pos))
                    if nxt is None:
                        return
                    pos = nxt
                    continue
                data_at = pos + 4 + hlen + 4
                end = data_at + max(dlen, 0)
                cut = dlen < 0 or end > size
                data = handle.read(max(0, min(end, size) - data_at)) if dlen > 0 else b""
                if op == b"\x05":
                    compression = fields.get("compression", b"none").decode("ascii", errors="replace")
                    try:
                        usize = struct.unpack("<I", fields["size"])[0]
                        records = _partial_decompress(compression, data) if cut else _decompress_whole(compression, data, usize)
                    except Exception as exc:  # noqa: BLE001 - any codec error means a lost chunk
                        result.losses.append(Loss(f"chunk that does not decompress ({exc})", pos, min(end, size) - pos))
                        if cut:
                            result.truncated = True
                            return
                        pos = end
                        continue
                    found, used = _ros1_records(records, result, None)
                    if cut or used < len(records):
                        reason = "chunk cut off by the end of the file" if cut else "chunk with a damaged record"
                        result.losses.append(Loss(reason, pos, min(end, size) - pos))
                    if wanted_topics is not None and found:
                        yield from _batches(result, wanted_topics, found, np.frombuffer(records, dtype=np.uint8))
                    if cut:
                        result.truncated = True
                        return
                elif op == b"\x07" and "conn" in fields and "topic" in fields and not cut:
                    _register_ros1_connection(result, fields, data)
                elif op == b"\x02" and not cut:  # unchunked message data
                    record = head + header + struct.pack("<I", dlen) + data
                    found, _ = _ros1_records(record, result, None)
                    if wanted_topics is not None and found:
                        yield from _batches(result, wanted_topics, found, np.frombuffer(record, dtype=np.uint8))
                elif cut:
                    result.truncated = True
                    if op not in (b"\x04", b"\x06"):  # a cut index is no data lost
                        result.losses.append(Loss("file ends inside a record", pos, size - pos))
                    return
                pos = end

    return result, walk()


# --------------------------------------------------------------------------- rosbag2 sqlite3


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = 0
    for i in range(8):
        byte = buf[pos + i]
        value = (value << 7) | (byte & 0x7F)
        if byte < 0x80:
            return value, pos + i + 1
    return (value << 8) | buf[pos + 8], pos + 9


_INT_SIZES = {1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8}


def _record(payload: bytes) -> list[object] | None:
    """The values of an SQLite record (integers, bytes for blobs and text, None)."""
    header_size, pos = _varint(payload, 0)
    types = []
    while pos < header_size:
        t, pos = _varint(payload, pos)
        types.append(t)
    values: list[object] = []
    at = header_size
    for t in types:
        if t == 0:
            values.append(None)
        elif t in _INT_SIZES:
            n = _INT_SIZES[t]
            values.append(int.from_bytes(payload[at : at + n], "big", signed=True))
            at += n
        elif t == 7:
            values.append(struct.unpack(">d", payload[at : at + 8])[0])
            at += 8
        elif t in (8, 9):
            values.append(t - 8)
        elif t >= 12:
            n = (t - 12) // 2
            values.append(bytes(payload[at : at + n]))
            at += n
        else:
            return None
    return values if at <= len(payload) else None


def scan_sqlite_rows(path: Path) -> tuple[dict[int, tuple[str, str, str]], list[Loss], list[tuple[int, int, int, bytes]]]:
    """Rows of a damaged rosbag2 sqlite3 file, read from its table leaf pages directly.

    SQLite itself stops at the first page it cannot follow (a cut-off file loses the interior
    pages that lead to the rows it still holds). Every leaf page of a table B-tree holds whole
    rows, so walking the pages in file order finds every row that is intact. ``topics`` rows are
    recognised as ``(id, name, type, serialization_format, ...)`` text rows, ``messages`` rows
    as ``(id, topic_id, timestamp, data)``; returned sorted by id. Rows that spill onto overflow pages (messages over
    about 4 kB, not IMU messages) are counted as lost.
    """
    data = path.read_bytes()
    if len(data) < 100 or not data.startswith(b"SQLite format 3\x00"):
        raise ValueError("not an SQLite database")
    (page_size,) = struct.unpack(">H", data[16:18])
    page_size = 65536 if page_size == 1 else page_size
    usable = page_size - data[20]
    topics: dict[int, tuple[str, str, str]] = {}
    messages: list[tuple[int, int, int, bytes]] = []
    skipped = 0
    for number in range(len(data) // page_size):
        start = number * page_size
        page = data[start : start + page_size]
        head = 100 if number == 0 else 0
        if page[head] != 0x0D:
            continue
        try:
            (cells,) = struct.unpack_from(">H", page, head + 3)
            pointers = struct.unpack_from(f">{cells}H", page, head + 8)
        except struct.error:
            continue
        for pointer in pointers:
            try:
                size, pos = _varint(page, pointer)
                rowid, pos = _varint(page, pos)
                if size > usable - 35:
                    skipped += 1  # spills onto overflow pages
                    continue
                values = _record(page[pos : pos + size])
            except (IndexError, struct.error):
                continue
            if values is None:
                continue
            if len(values) == 4 and isinstance(values[1], int) and isinstance(values[2], int) and isinstance(values[3], bytes):
                messages.append((rowid, values[1], values[2], values[3]))
            elif len(values) >= 4 and all(isinstance(v, bytes) for v in values[1:4]):
                name, msgtype, fmt = (v.decode("utf-8", errors="replace") for v in values[1:4])  # type: ignore[union-attr]
                if name.startswith("/") or "/" in msgtype:
                    topics[rowid] = (name, msgtype, fmt)
    losses: list[Loss] = []
    if len(data) % page_size:
        losses.append(Loss("page cut off by the end of the file", len(data) - len(data) % page_size, len(data) % page_size))
    if skipped:
        losses.append(Loss(f"{skipped} rows stored on overflow pages", 0, 0))
    messages.sort()
    return topics, losses, messages
