"""Vectorised decoding of ``sensor_msgs/Imu``, the one message layout this tool reads.

A batch is many serialized messages of one topic in one buffer (:class:`RawBatch`); decoding
gathers each field of every message with one numpy index (:func:`decode_imu`), bit-exact with
the ``rosbags`` deserializers, which decode what the layout check does not recognise (a
big-endian CDR message, say) one message at a time.

CDR (ROS 2): a 4-byte encapsulation header, ``stamp`` (int32 sec, uint32 nanosec), ``frame_id``
(uint32 length with the NUL, bytes), padding to 8 (counted from the end of the encapsulation
header), then the float64 fields. ROS 1: ``seq``, ``stamp`` (uint32 sec, nsec), ``frame_id``
(uint32 length, bytes), then the float64 fields, unpadded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

IMU_MSGTYPE = "sensor_msgs/msg/Imu"

#: Bytes after the frame id: orientation (4 f64), its covariance (9), angular velocity (3),
#: covariance (9), linear acceleration (3), covariance (9).
_TAIL = 8 * (4 + 9 + 3 + 9 + 3 + 9)
_GYRO_AFTER_FRAME = 8 * (4 + 9)
_ACCEL_AFTER_GYRO = 8 * (3 + 9)  # each triad is gathered on its own: 48 bytes, not 120
_CDR_NAMES = ["encapsulation", "options", "sec", "nsec", "frame_len"]
_CDR_HEAD = np.dtype({"names": _CDR_NAMES, "formats": ["<u2", "<u2", "<i4", "<u4", "<u4"]})
_ROS1_HEAD = np.dtype([("seq", "<u4"), ("sec", "<u4"), ("nsec", "<u4"), ("frame_len", "<u4")])
#: How many messages of a batch have their frame id read (evenly spread, the first included).
FRAME_ID_SAMPLES = 64


def normalize_msgtype(msgtype: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1) -> ``sensor_msgs/msg/Imu`` (the ROS 2 form used throughout)."""
    parts = msgtype.strip().split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype.strip()


@dataclass(frozen=True)
class RawBatch:
    """Serialized messages of one topic inside one buffer."""

    topic: str
    encoding: str  # "cdr" or "ros1"
    buffer: np.ndarray  # uint8
    starts: np.ndarray  # int64, first byte of each message's data
    lengths: np.ndarray  # int64
    log_time_ns: np.ndarray  # int64


@dataclass(frozen=True)
class DecodedBatch:
    stamp_ns: np.ndarray  # int64, header.stamp
    log_time_ns: np.ndarray  # int64
    gyro: np.ndarray  # (n, 3) rad/s as published
    accel: np.ndarray  # (n, 3)
    frame_ids: list[str]  # in order of first appearance
    errors: int  # messages that could not be decoded (skipped)


def pack_blobs(
    topic: str, encoding: str, blobs: Sequence[bytes | memoryview], log_time_ns: Sequence[int]
) -> RawBatch:
    """Serialized messages, one ``bytes`` each, as one batch."""
    lengths = np.fromiter(map(len, blobs), dtype=np.int64, count=len(blobs))
    starts = np.zeros(len(blobs), dtype=np.int64)
    np.cumsum(lengths[:-1], out=starts[1:])
    buffer = np.frombuffer(b"".join(blobs), dtype=np.uint8)
    return RawBatch(
        topic, encoding, buffer, starts, lengths, np.asarray(log_time_ns, dtype=np.int64)
    )


def bytes_at(buffer: np.ndarray, positions: np.ndarray, nbytes: int) -> np.ndarray:
    """Bytes ``positions[i] .. positions[i] + nbytes`` of every position: an (n, nbytes) uint8
    array. The buffer is seen as overlapping ``nbytes``-long records, one starting at every
    byte (a strided view, no copy), so a field costs one index per message, not one per byte."""
    if len(buffer) < nbytes:
        return np.zeros((0, nbytes), dtype=np.uint8)
    records = np.ndarray(
        shape=(len(buffer) - nbytes + 1,), dtype=f"V{nbytes}", buffer=buffer, strides=(1,)
    )
    return records[positions].view(np.uint8).reshape(len(positions), nbytes)


def gather(
    buffer: np.ndarray, positions: np.ndarray, nbytes: int, dtype: str | np.dtype
) -> np.ndarray:
    """:func:`bytes_at` viewed as ``dtype``: an (n, nbytes / itemsize) array."""
    return bytes_at(buffer, positions, nbytes).view(dtype)


def decode_imu(batch: RawBatch) -> DecodedBatch:
    """Decode the ``sensor_msgs/Imu`` messages of a batch (see the module's text)."""
    if batch.encoding not in ("cdr", "ros1"):
        raise ValueError(f"unsupported message encoding {batch.encoding!r}")
    buf, starts, lengths = batch.buffer, batch.starts, batch.lengths
    head_dtype = _CDR_HEAD if batch.encoding == "cdr" else _ROS1_HEAD
    ok = (lengths >= 16) & (starts >= 0) & (starts + lengths <= len(buf))
    everything = bool(ok.all())
    if everything:
        head = gather(buf, starts, 16, head_dtype).ravel()
    else:
        head = np.zeros(len(starts), dtype=head_dtype)
        head[ok] = gather(buf, starts[ok], 16, head_dtype).ravel()
    frame_len = head["frame_len"].astype(np.int64)
    if batch.encoding == "cdr":
        ok &= head["encapsulation"] == 0x0100  # bytes 00 01: CDR, little endian
        floats_at = (
            4 + (frame_len + 19) // 8 * 8
        )  # after the body's 12 bytes and the frame id, to 8
        frame_chars = frame_len - 1
    else:
        floats_at = 16 + frame_len
        frame_chars = frame_len
    ok &= (lengths >= floats_at + _TAIL) & (frame_chars >= 0)
    everything = bool(ok.all())
    index = slice(None) if everything else np.flatnonzero(ok)
    floats_abs = starts[index] + floats_at[index]
    used = head[index]
    stamp = used["sec"].astype(np.int64) * 1_000_000_000 + used["nsec"]
    gyro = gather(buf, floats_abs + _GYRO_AFTER_FRAME, 24, "<f8")
    accel = gather(buf, floats_abs + (_GYRO_AFTER_FRAME + _ACCEL_AFTER_GYRO), 24, "<f8")
    frame_ids = _frame_ids(buf, starts[index] + 16, frame_chars[index]) if len(stamp) else []
    log_times = batch.log_time_ns[index]
    if everything:
        return DecodedBatch(stamp, log_times, gyro, accel, frame_ids, 0)
    index = np.asarray(index)
    errors = 0
    rest = np.flatnonzero(~ok)
    if len(rest):  # what the layout check did not recognise: the generic deserializer
        extra = [_decode_generic(batch, int(i)) for i in rest]
        good = [(i, e) for i, e in zip(rest.tolist(), extra, strict=True) if e is not None]
        errors = len(rest) - len(good)
        if good:
            order = np.argsort(np.concatenate([index, [i for i, _ in good]]), kind="stable")
            stamp = np.concatenate([stamp, [e[0] for _, e in good]])[order]
            log_times = np.concatenate([log_times, batch.log_time_ns[[i for i, _ in good]]])[order]
            gyro = np.concatenate([gyro, [e[1] for _, e in good]])[order]
            accel = np.concatenate([accel, [e[2] for _, e in good]])[order]
            frame_ids += [e[3] for _, e in good if e[3] not in frame_ids]
    return DecodedBatch(
        stamp,
        log_times,
        np.ascontiguousarray(gyro, dtype=np.float64),
        np.ascontiguousarray(accel, dtype=np.float64),
        frame_ids,
        errors,
    )


@cache
def _typestore(encoding: str) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE if encoding == "cdr" else Stores.ROS1_NOETIC)


def _decode_generic(batch: RawBatch, i: int) -> tuple[int, list[float], list[float], str] | None:
    """One message through the ``rosbags`` deserializer, or None where it is not an Imu."""
    data = bytes(batch.buffer[batch.starts[i] : batch.starts[i] + batch.lengths[i]])
    store = _typestore(batch.encoding)
    try:
        if batch.encoding == "cdr":
            msg = store.deserialize_cdr(data, IMU_MSGTYPE)
        else:
            msg = store.deserialize_ros1(data, IMU_MSGTYPE)
    except Exception:
        return None
    w, a = msg.angular_velocity, msg.linear_acceleration
    stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    return stamp, [w.x, w.y, w.z], [a.x, a.y, a.z], str(msg.header.frame_id)


def _frame_ids(buf: np.ndarray, frame_start: np.ndarray, frame_chars: np.ndarray) -> list[str]:
    """The frame ids of a batch in order of first appearance. Frame ids are metadata, not
    measurements: an even sample of :data:`FRAME_ID_SAMPLES` messages of each frame id length
    is read, the first message always (the topic's frame id is its)."""
    found: list[tuple[int, bytes]] = []
    one_length = frame_chars[0] == frame_chars[-1] and frame_chars.min() == frame_chars.max()
    for length in [frame_chars[0]] if one_length else np.unique(frame_chars):
        group = np.arange(len(frame_chars)) if one_length else np.flatnonzero(frame_chars == length)
        sample = group[:: max(1, len(group) // FRAME_ID_SAMPLES)]
        names = (
            bytes_at(buf, frame_start[sample], int(length))
            if length
            else np.zeros((len(sample), 0), np.uint8)
        )
        if (names == names[0]).all():  # one frame id per topic is the rule: check it cheaply
            found.append((int(sample[0]), bytes(names[0])))
            continue
        unique, first = np.unique(names, axis=0, return_index=True)
        found.extend((int(sample[f]), bytes(row)) for f, row in zip(first, unique, strict=True))
    out: list[str] = []
    for _, raw in sorted(found):
        try:
            name = raw.decode("utf-8")
        except UnicodeDecodeError:
            name = raw.decode("latin-1")
        if name not in out:
            out.append(name)
    return out
