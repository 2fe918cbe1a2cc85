"""LZ4 frames decompressed straight into a given buffer, through liblz4's frame API.

python-lz4 (the binding rosbags and mcap use) returns a new ``bytes`` object for every frame:
a reader that wants the chunks of a log side by side in one buffer then copies each of them
once more (a quarter of a second for an hour of IMU messages). liblz4's ``LZ4F_decompress``
writes into memory the caller gives. Its frame API is stable since liblz4 1.8 (2017); the
library is loaded from the system (``liblz4.so.1``, part of the base system of the common Linux
distributions; python-lz4 carries its own copy, built in), and where it cannot be loaded
:func:`decompress_into` falls back to python-lz4 and a copy, with the same result.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Iterator
from functools import lru_cache

import numpy as np

#: ``LZ4F_VERSION``: the version of the frame API's structures a context is made for.
_LZ4F_VERSION = 100


@lru_cache(maxsize=1)
def _liblz4() -> ctypes.CDLL | None:
    """The system's liblz4 with the frame API's signatures set; None where it cannot be had."""
    def names() -> Iterator[str]:
        yield from ("liblz4.so.1", "liblz4.1.dylib")
        found = ctypes.util.find_library("lz4")  # a search (ldconfig's cache, a compiler): last
        if found:
            yield found

    for name in names():
        try:
            lib = ctypes.CDLL(name)
            create, decompress = lib.LZ4F_createDecompressionContext, lib.LZ4F_decompress
            free, is_error, error_name = lib.LZ4F_freeDecompressionContext, lib.LZ4F_isError, lib.LZ4F_getErrorName
        except (OSError, AttributeError):
            continue
        size_p = ctypes.POINTER(ctypes.c_size_t)
        create.argtypes, create.restype = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_uint], ctypes.c_size_t
        free.argtypes, free.restype = [ctypes.c_void_p], ctypes.c_size_t
        # (context, destination, its capacity in / written out, source, its size in / read out, options)
        decompress.argtypes = [ctypes.c_void_p, ctypes.c_void_p, size_p, ctypes.c_void_p, size_p, ctypes.c_void_p]
        decompress.restype = ctypes.c_size_t
        is_error.argtypes, is_error.restype = [ctypes.c_size_t], ctypes.c_uint
        error_name.argtypes, error_name.restype = [ctypes.c_size_t], ctypes.c_char_p
        return lib
    return None


def decompress_into(frame: bytes | memoryview, out: np.ndarray) -> int:
    """Decompress the LZ4 frame at the start of ``frame`` into ``out`` (a contiguous uint8
    array); returns the size it decompresses to, more than ``len(out)`` where it does not fit
    (then only ``len(out)`` bytes are written). Raises ValueError for a damaged or cut-off
    frame (its checksums are checked where the frame has them), as python-lz4 does."""
    if out.dtype != np.uint8 or out.ndim != 1 or not (out.flags.c_contiguous and out.flags.writeable):
        raise ValueError("decompress_into needs a writable, contiguous uint8 array")
    lib = _liblz4()
    if lib is None:
        return _copied(frame, out)
    source = np.frombuffer(frame, dtype=np.uint8)  # no copy: its address, kept alive here
    context = ctypes.c_void_p()
    if lib.LZ4F_isError(lib.LZ4F_createDecompressionContext(ctypes.byref(context), _LZ4F_VERSION)):
        return _copied(frame, out)
    try:
        written, read = ctypes.c_size_t(len(out)), ctypes.c_size_t(len(source))
        hint = lib.LZ4F_decompress(context, out.ctypes.data, ctypes.byref(written), source.ctypes.data, ctypes.byref(read), None)
        if lib.LZ4F_isError(hint):
            raise ValueError(f"LZ4F_decompress failed with code: {lib.LZ4F_getErrorName(hint).decode()}")
        if hint == 0:  # the frame ended
            return written.value
        if read.value < len(source):  # stopped with input left: the output is full
            return len(out) + 1
        raise ValueError("LZ4 frame cut off")
    finally:
        lib.LZ4F_freeDecompressionContext(context)


def _copied(frame: bytes | memoryview, out: np.ndarray) -> int:
    """:func:`decompress_into` through python-lz4 and a copy."""
    import lz4.frame

    try:
        data = lz4.frame.decompress(frame)
    except RuntimeError as exc:
        raise ValueError(str(exc)) from None
    n = min(len(data), len(out))
    out[:n] = np.frombuffer(data, dtype=np.uint8, count=n)
    return len(data)
