"""Vectorised serialisation of ``sensor_msgs/Imu`` for writing long logs quickly.

Used by the benchmarks to build hour-long logs; tests check it is byte-identical with the rosbags
serialisers. (The simulator's writer, :mod:`imucal_cli.sim.writers`, serialises message by
message and is the reference.)
"""

from __future__ import annotations

import numpy as np

from imucal_cli.types import ImuStream


def _float_block(stream: ImuStream, index: slice) -> np.ndarray:
    n = len(stream.t_ns[index])
    floats = np.zeros((n, 37))
    floats[:, 3] = 1.0  # orientation w (orientation not provided: covariance[0] = -1)
    floats[:, 4] = -1.0
    floats[:, 13:16] = stream.gyro[index]
    floats[:, 25:28] = stream.accel[index]
    return floats


def serialize_cdr(stream: ImuStream, index: slice = slice(None)) -> np.ndarray:
    """(n, size) uint8: little-endian CDR messages, as ``rosbags`` ``serialize_cdr`` writes them."""
    frame = stream.frame_id.encode() + b"\x00"
    body_head = 12 + len(frame)
    pad = (-body_head) % 8
    dtype = np.dtype(
        [
            ("encap", "u1", 4),
            ("sec", "<i4"),
            ("nanosec", "<u4"),
            ("frame_len", "<u4"),
            ("frame", "u1", len(frame)),
            ("pad", "u1", pad),
            ("floats", "<f8", 37),
        ],
        align=False,
    )
    t = stream.t_ns[index]
    out = np.zeros(len(t), dtype=dtype)
    out["encap"][:, 1] = 1
    out["sec"], out["nanosec"] = np.divmod(t, 1_000_000_000)
    out["frame_len"] = len(frame)
    out["frame"] = np.frombuffer(frame, dtype=np.uint8)
    out["floats"] = _float_block(stream, index)
    return out.view(np.uint8).reshape(len(t), dtype.itemsize)


def serialize_ros1(stream: ImuStream, index: slice = slice(None), first_seq: int = 0) -> np.ndarray:
    """(n, size) uint8: ROS 1 messages, as ``rosbags`` ``serialize_ros1`` writes them."""
    frame = stream.frame_id.encode()
    dtype = np.dtype(
        [
            ("seq", "<u4"),
            ("sec", "<u4"),
            ("nsec", "<u4"),
            ("frame_len", "<u4"),
            ("frame", "u1", len(frame)),
            ("floats", "<f8", 37),
        ],
        align=False,
    )
    t = stream.t_ns[index]
    out = np.zeros(len(t), dtype=dtype)
    out["seq"] = first_seq + np.arange(len(t))
    out["sec"], out["nsec"] = np.divmod(t, 1_000_000_000)
    out["frame_len"] = len(frame)
    out["frame"] = np.frombuffer(frame, dtype=np.uint8)
    out["floats"] = _float_block(stream, index)
    return out.view(np.uint8).reshape(len(t), dtype.itemsize)
