"""LZ4 frames decompressed into a given buffer: through liblz4, and through python-lz4 where
liblz4 cannot be loaded; both the same as python-lz4's own result, damage refused alike."""

from __future__ import annotations

import lz4.frame
import numpy as np
import pytest

from imucal_cli.io import lz4frames
from imucal_cli.io.lz4frames import decompress_into

#: Compressible bytes (repeats, as message records are) with some noise in them.
DATA = (bytes(range(256)) * 40 + np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes()) * 30

FRAMES = {
    "default": {},
    "content checksum": {"content_checksum": True},
    "independent blocks, block checksums": {"block_linked": False, "block_checksum": True},
    "64 KiB blocks": {"block_size": lz4.frame.BLOCKSIZE_MAX64KB, "content_checksum": True},
    "size in the header": {"store_size": True},
}


@pytest.fixture(params=["liblz4", "python-lz4"])
def binding(request, monkeypatch):
    if request.param == "liblz4":
        if lz4frames._liblz4() is None:
            pytest.skip("liblz4 cannot be loaded here (the python-lz4 case covers the fallback)")
    else:
        monkeypatch.setattr(lz4frames, "_liblz4", lambda: None)
    return request.param


@pytest.mark.parametrize("kind", FRAMES)
def test_whole_frames_equal_python_lz4(binding, kind):
    frame = lz4.frame.compress(DATA, **FRAMES[kind])
    out = np.full(len(DATA), 7, dtype=np.uint8)
    assert decompress_into(frame, out) == len(DATA)
    assert out.tobytes() == lz4.frame.decompress(frame) == DATA
    # from a view of a larger buffer (a chunk record followed by its index), into a slice
    room = np.zeros(len(DATA) + 10, dtype=np.uint8)
    assert decompress_into(memoryview(frame + b"index")[: len(frame)], room[5 : 5 + len(DATA)]) == len(DATA)
    assert room[5 : 5 + len(DATA)].tobytes() == DATA and not room[:5].any() and not room[-5:].any()


def test_an_empty_frame(binding):
    assert decompress_into(lz4.frame.compress(b""), np.zeros(0, dtype=np.uint8)) == 0


def test_a_frame_larger_than_its_room_says_so(binding):
    frame = lz4.frame.compress(DATA, content_checksum=True)
    small = np.zeros(len(DATA) - 100, dtype=np.uint8)
    assert decompress_into(frame, small) > len(small)
    assert small.tobytes() == DATA[: len(small)]  # and writes no further
    large = np.zeros(len(DATA) + 100, dtype=np.uint8)
    assert decompress_into(frame, large) == len(DATA)


@pytest.mark.parametrize("damage", ["cut off", "cut in its checksum", "header", "content"])
def test_damaged_frames_are_refused(binding, damage):
    frame = bytearray(lz4.frame.compress(DATA, content_checksum=True, block_checksum=False))
    if damage == "cut off":
        frame = frame[: len(frame) // 2]
    elif damage == "cut in its checksum":
        frame = frame[:-2]
    elif damage == "header":
        frame[5] ^= 0xFF  # the frame descriptor, under its header checksum
    else:
        frame[len(frame) // 2] ^= 0x01  # inside a block: the content checksum catches it
    with pytest.raises(RuntimeError):  # python-lz4 refuses it too
        lz4.frame.decompress(bytes(frame))
    with pytest.raises(ValueError):
        decompress_into(bytes(frame), np.zeros(len(DATA), dtype=np.uint8))


@pytest.mark.parametrize("room", ["read-only", "strided", "float"])
def test_only_writable_contiguous_bytes_are_written_into(binding, room):
    frame = lz4.frame.compress(DATA)
    out = {
        "read-only": np.frombuffer(bytes(len(DATA)), dtype=np.uint8),
        "strided": np.zeros(2 * len(DATA), dtype=np.uint8)[::2],
        "float": np.zeros(len(DATA) // 8, dtype=np.float64),
    }[room]
    with pytest.raises(ValueError, match="writable, contiguous uint8"):
        decompress_into(frame, out)
