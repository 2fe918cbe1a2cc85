"""What the container readers share: topics, losses, the reader interface, bounded
decompression."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from itertools import islice
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from imucal_cli.errors import LogError
from imucal_cli.io.imu_msg import IMU_MSGTYPE, RawBatch, normalize_msgtype, pack_blobs

#: Messages gathered into a block by the readers that get them one at a time (:func:`in_blocks`).
BATCH_MESSAGES = 8192

T = TypeVar("T")
D = TypeVar("D")
Bytes = bytes | memoryview  # a chunk's stored data: as read, or a view of it

#: The largest decompressed chunk and compression ratio believed (recorders write chunks of
#: 768 KiB to a few MiB; motionless noise-free IMU data compress 23:1): what a read decompresses
#: is bounded by the file's size, not by what its records claim.
MAX_CHUNK_BYTES, MAX_RATIO = 256 << 20, 1000


def check_chunk_size(claimed: int, stored: int, compression: str) -> None:
    """Raise :class:`ValueError` where a chunk of ``stored`` bytes claims to decompress to more
    than a real one could (:data:`MAX_CHUNK_BYTES`, :data:`MAX_RATIO`)."""
    if compression in ("", "none") and claimed != stored:
        raise ValueError(f"an uncompressed chunk of {stored} bytes claims {claimed}")
    if claimed > MAX_CHUNK_BYTES or claimed > MAX_RATIO * max(stored, 1):
        raise ValueError(
            f"a chunk of {stored} bytes claims to decompress to {claimed} (more than {MAX_RATIO}:1 "
            f"or {MAX_CHUNK_BYTES >> 20} MiB)"
        )


def decompress(
    compression: str, data: Bytes, claimed: int, prefix: bool = False, out: np.ndarray | None = None
) -> Any:
    """A chunk's data decompressed: exactly ``claimed`` bytes, checked before anything is
    decompressed (:func:`check_chunk_size`) and never decompressed past it. With ``prefix``
    (a chunk cut off or damaged): as much as decompresses, at most ``claimed`` bytes. With
    ``out`` (``claimed`` bytes of uint8) the data go there, zstd's straight (half the time of
    decompressing to bytes and copying those), and ``out`` is returned."""
    import bz2

    import lz4.frame
    import zstandard

    if not prefix:
        check_chunk_size(claimed, len(data), compression)
    parts: list[bytes] = []
    size = 0
    try:
        if compression == "zstd" and out is not None:
            reader = zstandard.ZstdDecompressor().stream_reader(data)
            while size < claimed and (got := reader.readinto(out.data[size:])):
                size += got
            size += len(reader.read(1))  # (anything beyond is an error)
        elif compression in ("", "none"):
            parts.append(bytes(data[: claimed + 1]))
        elif compression == "zstd":
            reader = zstandard.ZstdDecompressor().stream_reader(data)
            while sum(map(len, parts)) <= claimed and (
                piece := reader.read(min(claimed + 1, 1 << 20))
            ):
                parts.append(piece)
        elif compression in ("lz4", "bz2"):
            stream = (
                lz4.frame.LZ4FrameDecompressor() if compression == "lz4" else bz2.BZ2Decompressor()
            )
            parts.append(stream.decompress(bytes(data), max_length=claimed + 1))
        else:
            raise ValueError(f"unsupported chunk compression {compression!r}")
    except (zstandard.ZstdError, RuntimeError, OSError, EOFError, ValueError):
        if not prefix:
            raise
    result = b"".join(parts)
    size = size if compression == "zstd" and out is not None else len(result)
    if prefix:
        return result[:claimed]
    if size != claimed:
        raise ValueError(
            f"decompressed to {'more than ' * (size > claimed)}{min(size, claimed)} bytes, the "
            f"chunk says {claimed}"
        )
    if out is None:
        return result
    if parts:
        out[:] = np.frombuffer(result, np.uint8)
    return out


@dataclass(frozen=True)
class TopicInfo:
    """A topic as the container describes it."""

    topic: str
    msgtype: str  # as stored: sensor_msgs/msg/Imu (ROS 2) or sensor_msgs/Imu (ROS 1)
    count: int
    encoding: str  # "cdr", "ros1" or what the file says

    @property
    def is_imu(self) -> bool:
        return normalize_msgtype(self.msgtype) == IMU_MSGTYPE


@dataclass
class Loss:
    """A part of a log that could not be read (or, with ``lost=False``, a note on how it was)."""

    reason: str
    offset: int = 0  # byte offset in the file where it starts
    nbytes: int = 0
    start_ns: int | None = None  # log-time span, where the container says
    end_ns: int | None = None
    messages: dict[str, int] | None = None  # per topic, where the container says
    lost: bool = True

    def describe(self) -> str:
        if not self.lost:
            return self.reason
        span = ""
        if self.start_ns is not None and self.end_ns is not None and self.end_ns >= self.start_ns:
            span = f", {(self.end_ns - self.start_ns) * 1e-9:.2f} s of log time"
        count = ""
        if self.messages:
            count = ", " + ", ".join(
                f"{n} messages of {t}" for t, n in sorted(self.messages.items())
            )
        return f"not read from byte {self.offset} ({self.nbytes} bytes{span}{count}): {self.reason}"


class LogReader:
    """A log opened for reading; use as a context manager. Subclasses list the topics and
    yield raw batches of the topics asked for; :attr:`losses` fills in as they read."""

    format_name = ""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.losses: list[Loss] = []

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the file handles."""

    def topics(self) -> dict[str, TopicInfo]:
        raise NotImplementedError

    def batches(self, topics: Iterable[str]) -> Iterator[RawBatch]:
        """Raw batches of ``topics``, each of one topic, in roughly log-time order."""
        raise NotImplementedError

    def follow(
        self, topics: Iterable[str], stop: Callable[[], bool], poll_s: float = 0.05
    ) -> Iterator[RawBatch]:
        """Follow mode: raw batches of a log still being written, until it ends or ``stop()``."""
        raise self.error("this log cannot be followed while it is written")

    def error(self, problem: str, topic: str | None = None) -> LogError:
        return LogError(str(self.path), problem, topic)


def in_blocks(
    rows: Iterable[tuple[int, int, Bytes]], topic_of: dict[int, tuple[str, str]]
) -> Iterator[RawBatch]:
    """Messages got one at a time (a key of ``topic_of``, which gives its topic and encoding;
    its log time, ns; its data), in log-time order, as batches: blocks of
    :data:`BATCH_MESSAGES` rows, each a batch per topic cut into pieces of
    :data:`BATCH_SPAN_NS` in time order (:func:`interleaved`); a block's data joined once and
    its columns gathered in C, not a Python call per message."""
    rows = iter(rows)
    while block := list(islice(rows, BATCH_MESSAGES)):
        keys, times, data = zip(*block, strict=True)
        whole, of, kinds = pack_blobs("", "", data, times), np.array(keys), dict.fromkeys(keys)
        pieces = []
        for topic, encoding in dict.fromkeys(topic_of[k] for k in kinds):
            mine = np.isin(of, [k for k in kinds if topic_of[k] == (topic, encoding)])
            at = (whole.starts[mine], whole.lengths[mine], whole.log_time_ns[mine])
            pieces.append(RawBatch(topic, encoding, whole.buffer, *at))
        yield from interleaved(pieces)


#: A topic's batch of a group longer than this (ns) is cut, the pieces given in time order: a topic
#: read minutes ahead of another (low-rate chunks) looks to the calibrator like one that stopped.
BATCH_SPAN_NS = 10_000_000_000


def interleaved(batches: list[RawBatch], span_ns: int = BATCH_SPAN_NS) -> list[RawBatch]:
    """``batches``, each longer than ``span_ns`` of log time cut into pieces of it, in the order of
    their first log time (as they are where none is cut)."""
    pieces = []
    for b in batches:
        t = b.log_time_ns
        if not len(t) or t[-1] - t[0] <= span_ns:
            pieces.append(b)
            continue
        ends = [*(np.flatnonzero(np.diff((t - t[0]) // span_ns)) + 1).tolist(), len(t)]
        for a, z in zip([0, *ends[:-1]], ends, strict=True):
            pieces.append(
                replace(b, starts=b.starts[a:z], lengths=b.lengths[a:z], log_time_ns=t[a:z])
            )
    if len(pieces) == len(batches):
        return batches
    return sorted(pieces, key=lambda p: int(p.log_time_ns[0]) if len(p.log_time_ns) else 0)
