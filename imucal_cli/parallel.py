"""A second process for the math: :class:`ForkedWorker` runs functions sent to it, in order.

The calibration's per-block work (splines, filters, moments; :mod:`imucal_cli.core.streaming`)
is plain numpy that holds the GIL too often for a thread to pay, so a block is handed to a
forked process whenever that process is idle, and the caller reduces the next block meanwhile.
The worker is forked before the calibration holds any data, so it shares the modules already
imported and holds little memory of its own. Its results come back over a pipe in the order sent; an
exception raised in it is raised again by ``result()``; a worker that dies is a
``RuntimeError``. Where ``fork`` is not available, :func:`ForkedWorker.available` is False and
callers work inline.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import weakref
from collections import deque
from collections.abc import Callable
from typing import Any, Self

#: The parent's ends of the pipes to this process's children (workers, readers). A forked
#: child closes them all: holding a copy, it would keep a pipe open after the parent died and
#: wait on it for ever (and keep its siblings waiting too).
_PARENT_ENDS: weakref.WeakSet[Any] = weakref.WeakSet()


def parent_end(conn: Any) -> Any:
    """Register ``conn`` as the parent's end of a pipe to a child (see :data:`_PARENT_ENDS`)."""
    _PARENT_ENDS.add(conn)
    return conn


def _close_parent_ends() -> None:  # pragma: no cover - runs in forked children
    for conn in list(_PARENT_ENDS):
        try:
            conn.close()
        except OSError:
            pass
    _PARENT_ENDS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_parent_ends)


#: glibc's allocator: blocks up to this size come from its heap (32 MiB, the most it allows),
#: not from a fresh ``mmap`` each (its default starts at 128 KiB).
MALLOC_MMAP_BYTES = 32 << 20
#: glibc's allocator: free memory at the heap's top kept for reuse, up to this size, not handed
#: back to the kernel at every ``free``.
MALLOC_TRIM_BYTES = 256 << 20


def reuse_freed_memory() -> None:
    """Have glibc's allocator keep freed buffers for the next ones (nothing elsewhere).

    Reading a log allocates a few megabytes for every decompressed chunk and every batch's
    arrays, and frees them soon after. With glibc's defaults many of those are ``mmap``-ed
    one by one, and unmapped when freed, so the kernel faults in and zeroes every page of every
    new buffer. Measured with ``calibrate`` on the 1 h MCAP of ``benchmarks/throughput.py``
    (all processes): 300 000 page faults and 1.2 s of system CPU with the defaults, 66 000 and
    0.5 s with these, wall time 0.3-0.5 s less; the largest process's peak RSS a few per cent
    higher. Forked children inherit the setting."""
    try:
        if "glibc" not in (os.confstr("CS_GNU_LIBC_VERSION") or "").lower():
            return
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt  # the process's own symbols, glibc's among them
    except (AttributeError, OSError, ValueError):  # no confstr, or a name it does not know
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # malloc.h
    mallopt(M_MMAP_THRESHOLD, MALLOC_MMAP_BYTES)
    mallopt(M_TRIM_THRESHOLD, MALLOC_TRIM_BYTES)


#: Bytes a pipe between the processes holds (Linux's default is 64 KiB): fewer, larger writes
#: and reads, and so fewer switches between the two processes for each batch.
PIPE_BYTES = 1 << 20


def widen(conn: Any) -> Any:
    """Let the pipe under ``conn`` hold :data:`PIPE_BYTES` where the system allows it (Linux;
    elsewhere, or above ``/proc/sys/fs/pipe-max-size``, it stays as it is)."""
    try:
        import fcntl

        fcntl.fcntl(conn.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
    except (ImportError, OSError, ValueError):
        pass
    return conn


def send(conn: Any, obj: Any) -> None:
    """Send ``obj`` over a :class:`multiprocessing.connection.Connection`, its numpy arrays as
    raw bytes straight from their memory (pickle protocol 5, out of band), not copied into the
    pickle first; read it with :func:`receive`. ``obj`` is pickled whole before anything is
    written, so one that does not pickle raises with nothing sent."""
    buffers: list[pickle.PickleBuffer] = []
    data = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    views = [buffer.raw() for buffer in buffers]
    conn.send_bytes(pickle.dumps((data, [view.nbytes for view in views]), protocol=5))
    fd = conn.fileno()
    for view in views:
        while view.nbytes:
            view = view[os.write(fd, view) :]


def receive(conn: Any) -> Any:
    """The next object :func:`send` sent on the other end; its arrays' bytes are read straight
    into their own new memory. ``EOFError`` when the other end is closed."""
    import numpy as np

    data, sizes = pickle.loads(conn.recv_bytes())
    fd = conn.fileno()
    buffers = []
    for size in sizes:
        buffer = np.empty(size, dtype=np.uint8)
        view, done = memoryview(buffer), 0
        while done < size:
            got = os.readv(fd, [view[done:]])
            if not got:
                raise EOFError("the other end closed the pipe in the middle of an object")
            done += got
        buffers.append(buffer)
    return pickle.loads(data, buffers=buffers)


class ForkedWorker:
    """One forked process running ``fn(*args)`` for each :meth:`submit`, in order.

    >>> with ForkedWorker() as worker:                  # doctest: +SKIP
    ...     pending = worker.submit(sum, [1, 2, 3])
    ...     pending.result()
    6
    """

    @staticmethod
    def available() -> bool:
        return "fork" in multiprocessing.get_all_start_methods()

    def __init__(self) -> None:
        context = multiprocessing.get_context("fork")
        job_out, job_in = context.Pipe(duplex=False)  # (receiving end, sending end)
        result_out, result_in = context.Pipe(duplex=False)
        self._jobs, self._results = parent_end(widen(job_in)), parent_end(widen(result_out))
        self._process = context.Process(target=_serve, args=(job_out, result_in), name="imucal-math", daemon=True)
        self._process.start()
        job_out.close()
        result_in.close()
        self._waiting: deque[_Pending] = deque()

    def submit(self, fn: Callable[..., Any], *args: Any) -> _Pending:
        """Send ``fn(*args)`` to the worker (``fn`` and ``args`` must pickle); the returned
        object's ``done()`` says whether it has finished, ``result()`` waits for it.

        Jobs run one at a time: this first waits for the results of those sent before (kept
        for their ``result()``). Two processes that both send a message larger than the pipe
        holds, each before reading the other's, would wait for each other for ever; so nothing
        is sent while a result may still be on its way.
        """
        while self._waiting:
            self._receive()
        pending = _Pending(self)
        try:
            send(self._jobs, (fn, args))
        except (BrokenPipeError, ConnectionResetError):
            raise self._died() from None
        self._waiting.append(pending)
        return pending

    def _receive(self) -> None:
        try:
            ok, value = receive(self._results)
        except (EOFError, OSError):
            raise self._died() from None
        self._waiting.popleft()._set(ok, value)

    def _died(self) -> RuntimeError:
        self._process.join(timeout=1.0)
        return RuntimeError(f"the math worker process ended unexpectedly (exit code {self._process.exitcode})")

    def close(self) -> None:
        """End the worker (what it has not finished is dropped); again does nothing."""
        if self._jobs.closed:
            return
        try:
            send(self._jobs, None)
        except OSError:
            pass
        self._process.join(timeout=5.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()
        self._jobs.close()
        self._results.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Pending:
    """The future result of one :meth:`ForkedWorker.submit`."""

    def __init__(self, worker: ForkedWorker) -> None:
        self._worker = worker
        self._finished = False
        self._ok = False
        self._value: Any = None

    def _set(self, ok: bool, value: Any) -> None:
        self._finished, self._ok, self._value = True, ok, value

    def done(self) -> bool:
        """Finished (without waiting)."""
        while not self._finished and self._worker._results.poll():
            self._worker._receive()
        return self._finished

    def result(self) -> Any:
        """Wait for the result; an exception raised in the worker is raised here."""
        while not self._finished:
            self._worker._receive()
        if not self._ok:
            raise self._value
        return self._value


def _serve(jobs: Any, results: Any) -> None:  # pragma: no cover - runs in the child
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it ends us
    try:
        while True:
            try:
                item = receive(jobs)
            except (EOFError, OSError):
                return
            if item is None:
                return
            fn, args = item
            try:
                reply = (True, fn(*args))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                reply = (False, exc)
            try:
                send(results, reply)
            except OSError:
                return  # the parent is gone
            except Exception as exc:  # noqa: BLE001 - a result or exception that does not pickle
                failed = exc if reply[0] else reply[1]
                send(results, (False, RuntimeError(f"{type(failed).__name__}: {failed}")))
    except OSError:
        return  # the parent is gone
    finally:
        jobs.close()
        results.close()
