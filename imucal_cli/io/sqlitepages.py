"""The ``messages`` table of a rosbag2 sqlite3 file read from its B-tree pages, in bulk.

SQLite hands rows over one at a time, and its own per-row work (the virtual machine, the record
decoding, the Python objects) is most of the cost of reading an IMU log: an hour of five IMUs is
3.2 million rows. The table's rows live in the leaf pages of its B-tree
(https://www.sqlite.org/fileformat2.html, "B-tree Pages" and "Record Format"), so this module
walks the interior pages in key order to list the leaves, reads the leaves in large groups and
finds every cell, its rowid, its ``topic_id``, ``timestamp`` and where its ``data`` blob lies
with numpy, many pages at once. The blobs are not copied: they are decoded in place by
:func:`imucal_cli.io.fastimu.decode_imu`.

Anything this reader does not expect (a write-ahead log, a row on overflow pages, another
schema, an inconsistent page) raises :class:`PageLayoutError` before the rows concerned are
handed over; the caller reads from there on through SQLite (``WHERE id > last rowid``).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imucal_cli.io.fastimu import bytes_at

#: Bytes of leaf pages read and parsed together (2,048 pages of the usual 4 kB).
GROUP_BYTES = 8 << 20
_LEAF, _INTERIOR = 0x0D, 0x05
_SPARE = 32  # bytes after the last page (the widest gather starting inside a page is 18)
#: Bytes of an SQLite integer of each serial type (0: NULL, 8 and 9: the constants 0 and 1).
_INT_SIZE = {0: 0, 1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8, 8: 0, 9: 0}


class PageLayoutError(Exception):
    """The file is not laid out as this reader expects; read it through SQLite."""


@dataclass(frozen=True)
class Rows:
    """Rows of ``messages`` in one buffer: ``data`` of row ``i`` is
    ``buffer[starts[i] : starts[i] + lengths[i]]``."""

    buffer: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray
    topic_ids: np.ndarray
    timestamps: np.ndarray
    last_rowid: int  # of every row read so far, wanted or not


def _decode_varints(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SQLite varints at the start of each row of ``block`` (n, >= 9): big-endian groups of 7
    bits, the ninth byte whole. Their values (int64) and byte lengths."""
    more = block[:, :8] >= 0x80
    length = np.where(more.all(axis=1), 9, np.argmin(more, axis=1) + 1)
    value = (block[:, 0] & 0x7F).astype(np.int64)
    for i in range(1, int(length.max(initial=1))):
        byte = block[:, i].astype(np.int64)
        part = (value << 8) | byte if i == 8 else (value << 7) | (byte & 0x7F)
        value = np.where(length > i, part, value)
    return value, length


def _varints(buf: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SQLite varints starting at ``at``: values and byte lengths."""
    return _decode_varints(bytes_at(buf, at, 9))


def _shifted(block: np.ndarray, offset: np.ndarray, width: int) -> np.ndarray:
    """``block[i, offset[i] : offset[i] + width]`` of every row (few distinct offsets)."""
    out = np.empty((len(block), width), dtype=block.dtype)
    for value in np.unique(offset):
        pick = offset == value
        out[pick] = block[pick, int(value) : int(value) + width]
    return out


def _big_endian(buf: np.ndarray, at: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Signed big-endian integers of ``sizes`` bytes (0 to 8) at ``at``."""
    value = np.zeros(len(at), dtype=np.int64)
    for size in range(1, 9):
        pick = sizes == size
        if not pick.any():
            continue
        raw = bytes_at(buf, at[pick], int(size)).astype(np.uint64)
        v = np.zeros(len(raw), dtype=np.uint64)
        for k in range(int(size)):
            v = (v << np.uint64(8)) | raw[:, k]
        if size < 8:  # sign-extend
            sign = np.uint64(1) << np.uint64(8 * size - 1)
            v = (v ^ sign) - sign
        value[pick] = v.view(np.int64)
    return value


class MessagePages:
    """The leaf pages of a rosbag2 ``messages`` table, read in key (rowid) order."""

    def __init__(self, path: Path, root_page: int) -> None:
        self.path = path
        self.fd = os.open(path, os.O_RDONLY)
        try:
            header = os.pread(self.fd, 100, 0)
            if len(header) < 100 or not header.startswith(b"SQLite format 3\x00"):
                raise PageLayoutError("not an SQLite 3 database")
            (size,) = struct.unpack(">H", header[16:18])
            self.page_size = 65536 if size == 1 else size
            self.usable = self.page_size - header[20]
            for suffix in ("-wal", "-journal"):  # changes not in the main file yet
                side = Path(str(path) + suffix)
                if side.exists() and side.stat().st_size > 0:
                    raise PageLayoutError(f"the database has a {suffix[1:]} file")
            self.pages = os.fstat(self.fd).st_size // self.page_size
            self.leaves = self._leaves(root_page)
        except BaseException:
            os.close(self.fd)
            raise

    def close(self) -> None:
        os.close(self.fd)

    def _page(self, number: int) -> bytes:
        if not 1 <= number <= self.pages:
            raise PageLayoutError(f"page {number} is outside the file")
        return os.pread(self.fd, self.page_size, (number - 1) * self.page_size)

    def _leaves(self, root: int) -> list[int]:
        """Leaf page numbers in key order. Every leaf of a B-tree lies at the same depth, so
        the interior pages are walked breadth first and the leaves themselves are not read
        here (:meth:`_parse` checks that they are leaves)."""
        level, seen = [root], {root}
        while True:
            page = self._page(level[0])
            kind = page[100 if level[0] == 1 else 0]
            if kind == _LEAF:
                return level
            if kind != _INTERIOR:
                raise PageLayoutError(f"page {level[0]} is neither a table leaf nor an interior page")
            below: list[int] = []
            for number in level:
                page = page if number == level[0] else self._page(number)
                head = 100 if number == 1 else 0
                if page[head] != _INTERIOR:
                    raise PageLayoutError(f"page {number} is not an interior page like the others of its level")
                (cells,) = struct.unpack_from(">H", page, head + 3)
                (right,) = struct.unpack_from(">I", page, head + 8)
                pointers = struct.unpack_from(f">{cells}H", page, head + 12)
                below.extend(struct.unpack_from(">I", page, p)[0] for p in pointers)
                below.append(right)
            if seen.intersection(below) or len(set(below)) != len(below):
                raise PageLayoutError("a page is reached twice")
            seen.update(below)
            level = below

    def rows(self, wanted_topics: set[int], after_rowid: int = 0, group_pages: int | None = None) -> Iterator[Rows]:
        """Rows of the wanted topics, a group of leaf pages (:data:`GROUP_BYTES`) at a time."""
        group_pages = group_pages or max(1, GROUP_BYTES // self.page_size)
        last = after_rowid
        for a in range(0, len(self.leaves), group_pages):
            numbers = self.leaves[a : a + group_pages]
            buffer = self._read(numbers)
            rows = self._parse(buffer, numbers, last)
            last = rows.last_rowid
            keep = np.isin(rows.topic_ids, list(wanted_topics))
            if not keep.all():
                rows = Rows(buffer, rows.starts[keep], rows.lengths[keep], rows.topic_ids[keep], rows.timestamps[keep], last)
            yield rows

    def _read(self, numbers: list[int]) -> np.ndarray:
        """The pages, one after the other, in one buffer (runs of consecutive pages read at once),
        with spare bytes so that fixed-width gathers near the end stay inside."""
        size = self.page_size
        buffer = np.zeros(len(numbers) * size + _SPARE, dtype=np.uint8)
        view = memoryview(buffer)
        i = 0
        while i < len(numbers):
            j = i + 1
            while j < len(numbers) and numbers[j] == numbers[j - 1] + 1:
                j += 1
            if not (1 <= numbers[i] and numbers[j - 1] <= self.pages):
                raise PageLayoutError(f"page {numbers[i]} is outside the file")
            got = os.preadv(self.fd, [view[i * size : j * size]], (numbers[i] - 1) * size)
            if got != (j - i) * size:
                raise PageLayoutError(f"page {numbers[i]} is cut off")
            i = j
        return buffer

    def _parse(self, buffer: np.ndarray, numbers: list[int], after_rowid: int) -> Rows:
        size, usable = self.page_size, self.usable
        base = np.arange(len(numbers), dtype=np.int64) * size
        head = base + np.array([100 if n == 1 else 0 for n in numbers], dtype=np.int64)
        if np.any(buffer[head] != _LEAF):
            raise PageLayoutError("a leaf page is not a table leaf")
        cells = (buffer[head + 3].astype(np.int64) << 8) | buffer[head + 4]
        if np.any(8 + 2 * cells > usable - (head - base)):
            raise PageLayoutError("a leaf page has more cells than fit")
        page_of = np.repeat(np.arange(len(numbers)), cells)
        k = np.arange(len(page_of)) - np.repeat(np.cumsum(cells) - cells, cells)
        at = head[page_of] + 8 + 2 * k
        pointer = (buffer[at].astype(np.int64) << 8) | buffer[at + 1]
        page_end = base[page_of] + usable
        cell = base[page_of] + pointer
        if np.any((pointer < 8) | (cell >= page_end)):
            raise PageLayoutError("a cell pointer is outside its page")
        # the cell: payload size and rowid (varints), then the record
        start = bytes_at(buffer, cell, 18)
        payload, n1 = _decode_varints(start)
        rowid, n2 = _decode_varints(_shifted(start, n1, 9))
        record = cell + n1 + n2
        if np.any(payload > usable - 35):
            raise PageLayoutError("a row spills onto overflow pages")
        if np.any(record + payload > page_end):
            raise PageLayoutError("a row runs past its page")
        if len(rowid) and (rowid[0] <= after_rowid or np.any(np.diff(rowid) <= 0)):
            raise PageLayoutError("rowids are not in order")
        # record header: its length, then the serial types of id, topic_id, timestamp, data
        header = bytes_at(buffer, record, 16)
        if np.all(header[:, :4] < 0x80):  # the usual: four one-byte varints, then the blob's
            header_len, t_id, t_topic, t_time = (header[:, k].astype(np.int64) for k in range(4))
            t_data, h4 = _decode_varints(header[:, 4:13])
            sizes_ok = 4 + h4 == header_len
        else:
            header_len, h0 = _varints(buffer, record)
            t_id, h1 = _varints(buffer, record + h0)
            t_topic, h2 = _varints(buffer, record + h0 + h1)
            t_time, h3 = _varints(buffer, record + h0 + h1 + h2)
            t_data, h4 = _varints(buffer, record + h0 + h1 + h2 + h3)
            sizes_ok = h0 + h1 + h2 + h3 + h4 == header_len
        if not np.all(sizes_ok) or np.any(t_id != 0):
            raise PageLayoutError("a row is not (id, topic_id, timestamp, data)")
        size_topic = _int_sizes(t_topic)
        size_time = _int_sizes(t_time)
        if np.any(t_data < 12) or np.any(t_data % 2 == 1):
            raise PageLayoutError("a row's data is not a blob")
        lengths = (t_data - 12) // 2
        body = record + header_len
        if np.any(header_len + size_topic + size_time + lengths != payload):
            raise PageLayoutError("a row's fields do not add up to its payload")
        topic_ids = _big_endian(buffer, body, size_topic)
        topic_ids = np.where(t_topic == 9, 1, topic_ids)  # serial type 9 is the constant 1
        timestamps = _big_endian(buffer, body + size_topic, size_time)
        timestamps = np.where(t_time == 9, 1, timestamps)
        last = int(rowid[-1]) if len(rowid) else after_rowid
        return Rows(buffer, body + size_topic + size_time, lengths, topic_ids, timestamps, last)


def _int_sizes(serial: np.ndarray) -> np.ndarray:
    sizes = np.full(len(serial), -1, dtype=np.int64)
    for kind, nbytes in _INT_SIZE.items():
        sizes[serial == kind] = nbytes
    if np.any(sizes < 0) or np.any(serial == 0):
        raise PageLayoutError("a row's topic_id or timestamp is not an integer")
    return sizes
