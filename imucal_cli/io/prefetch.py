"""Read a log ahead of the math that consumes it.

:func:`read_ahead` runs a batch reader (:class:`~imucal_cli.io.logs.ImuBatches`) in a forked
child process that decompresses and decodes while the parent calibrates, so on a machine with
two cores reading costs little wall time. (A thread does not pay: the reader's numpy work holds
the GIL too often.) Batches cross a pipe; the child reads at most :data:`DEPTH` of them ahead
of what it has sent (it reads on while the parent imports the math) and the parent receives at
most :data:`RECEIVE_DEPTH` ahead of the calibration, so memory stays flat whatever the log's
length. Errors raised in the child (a damaged
log, a missing topic) are raised again in the parent, and the reader's statistics are copied
back when it is done. Where ``fork`` is not available the reader simply runs inline.
"""

from __future__ import annotations

import multiprocessing
import queue
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: Batches the reader process may have read ahead of what it has sent: it reads on while the
#: parent cannot take them yet (the math's imports, about a second, come after the fork).
DEPTH = 96
#: Batches received ahead of the calibration in the parent (the pipe is read in a thread).
RECEIVE_DEPTH = 8


class _Raised:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


class _Done:
    def __init__(self, stats: Any) -> None:
        self.stats = stats


class StatsReader(Protocol):
    stats: Any

    def __iter__(self) -> Iterator[Any]: ...


_END = object()


def queued(items: Iterable[T], depth: int, switch_interval_s: float | None = None) -> Iterator[T]:
    """``items`` produced by a background thread up to ``depth`` ahead: worth it where the
    producer spends its time outside the GIL (receiving from a pipe, reading a file,
    decompressing, checking a CRC). An exception in the producer is raised in the consumer;
    closing the iterator stops the producer.

    A producer that takes the GIL back after every call outside it waits up to the
    interpreter's switch interval (5 ms) each time while the consumer computes;
    ``switch_interval_s`` shortens it while the iterator runs (then puts it back).
    """
    slots: queue.Queue[object] = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                slots.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
            put(_END)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            put(_Raised(exc))

    previous = sys.getswitchinterval()
    if switch_interval_s is not None:
        sys.setswitchinterval(min(previous, switch_interval_s))
    thread = threading.Thread(target=produce, name="imucal-read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item = slots.get()
            if item is _END:
                return
            if isinstance(item, _Raised):
                raise item.exc
            yield item  # type: ignore[misc]
            if isinstance(item, _Done):
                return
    finally:
        stop.set()
        thread.join(timeout=5.0)
        if switch_interval_s is not None:
            sys.setswitchinterval(previous)


def ordered_map(
    func: Callable[[T], R], items: Iterable[T], workers: int, ahead: int, switch_interval_s: float | None = None
) -> Iterator[R]:
    """``func(item)`` of every item, computed by ``workers`` threads, at most ``workers + ahead``
    at once, and yielded in the items' order: worth it where ``func`` spends its time outside
    the GIL (reading a file, decompressing, checking a CRC, numpy's gathers and reductions).
    ``items`` is iterated here, in the consumer's thread, as results are taken. An exception
    of ``func`` is raised at its item's turn; closing the iterator cancels what has not
    started and waits for what has (so nothing runs on after it, on a closed file say).
    ``switch_interval_s`` is as for :func:`queued`.
    """
    if workers <= 0:
        yield from map(func, items)
        return
    from collections import deque
    from concurrent.futures import Future, ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="imucal-decode")
    pending: deque[Future[R]] = deque()
    previous = sys.getswitchinterval()
    if switch_interval_s is not None:
        sys.setswitchinterval(min(previous, switch_interval_s))
    try:
        for item in items:
            pending.append(pool.submit(func, item))
            if len(pending) >= workers + ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()
        pool.shutdown(wait=True)
        if switch_interval_s is not None:
            sys.setswitchinterval(previous)


def _child(reader: StatsReader, conn: Any) -> None:  # pragma: no cover - runs in the child
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it ends us
    from imucal_cli.io import fastimu
    from imucal_cli.parallel import send

    # This process reads beside the calibration's two, which keep both cores busy: threads
    # decoding side by side here would only add switching and memory (the 1 h MCAP of
    # benchmarks/throughput.py: calibrate no faster, the reader's CPU 4.5 s against 3.8 s and
    # the peak RSS 450 MB against 347 MB). One thread reads; this one sends.
    fastimu.DECODE_THREADS = 0
    try:
        if isinstance(reader, _Made):
            reader = reader.make()  # here, after the fork: the parent needs none of its imports
        for item in queued(reader, DEPTH):  # read ahead in a thread while this one sends
            send(conn, item)
        send(conn, _Done((reader.stats, getattr(reader, "losses", None), getattr(reader, "format_name", None))))
    except (BrokenPipeError, ConnectionResetError):
        pass  # the parent is gone, or stopped reading
    except BaseException as exc:  # noqa: BLE001 - handed to the parent
        try:
            send(conn, _Raised(exc))
        except OSError:
            pass  # the parent is gone
        except Exception:  # noqa: BLE001 - an exception that does not pickle
            send(conn, _Raised(RuntimeError(f"{type(exc).__name__}: {exc}")))
    finally:
        conn.close()


def read_ahead(reader: StatsReader, background: bool = True) -> Iterator[Any]:
    """Start reading ``reader`` (in a child process when ``background`` and ``fork`` are
    available) and return an iterator over its items; once it is exhausted ``reader.stats``
    holds what the reading counted, as if it had run here.

    The child is forked here, at the call, so call it before starting threads (a progress bar).
    """
    if not background or "fork" not in multiprocessing.get_all_start_methods():
        return iter(reader)
    context = multiprocessing.get_context("fork")
    from imucal_cli.parallel import parent_end, widen

    receiving, sending = context.Pipe(duplex=False)
    parent_end(widen(receiving))
    process = context.Process(target=_child, args=(reader, sending), name="imucal-reader", daemon=True)
    process.start()
    sending.close()
    return _Ahead(_from_child(reader, process, receiving), process, receiving)


class _Made:
    """A reader to be made in the child process by ``make()``; until the child has read it
    all, this stands in for it in the parent (``path``, ``topics``; then ``stats``, ``losses``
    and ``format_name`` as the child's reader found them)."""

    def __init__(self, make: Callable[[], StatsReader], path: Any, topics: list[str]) -> None:
        self.make, self.path, self.topics = make, path, topics
        self.stats: Any = {}
        self.losses: list[Any] = []
        self.format_name = ""

    def __iter__(self) -> Iterator[Any]:  # where the reading runs inline: made here after all
        reader = self.make()
        yield from reader
        self.stats, self.losses, self.format_name = reader.stats, getattr(reader, "losses", []), getattr(reader, "format_name", "")


def read_made_ahead(make: Callable[[], StatsReader], path: Any, topics: list[str]) -> tuple[_Made, Iterator[Any]]:
    """:func:`read_ahead` of the reader ``make()`` returns, made in the child: the parent
    forks before importing what reading needs (numpy, the containers' libraries), so the child
    starts as early as it can and imports them itself beside the parent's imports. Returns the
    parent's stand-in for the reader (see :class:`_Made`) and the iterator over its items."""
    made = _Made(make, path, topics)
    return made, read_ahead(made)


class _Ahead:
    """The parent's side of :func:`read_ahead`: an iterator whose ``close()`` also ends a child
    whose items were never asked for."""

    def __init__(self, items: Iterator[Any], process: Any, receiving: Any) -> None:
        self._items, self._process, self._receiving = items, process, receiving

    def __iter__(self) -> Iterator[Any]:
        return self

    def __next__(self) -> Any:
        return next(self._items)

    def close(self) -> None:
        self._items.close()  # a started generator ends the child itself (its finally)
        if self._process.is_alive():
            self._process.terminate()
        self._process.join()
        self._receiving.close()


def _from_child(reader: StatsReader, process: Any, receiving: Any) -> Iterator[Any]:
    from imucal_cli.parallel import receive as receive_object

    def receive() -> Iterator[object]:
        while True:
            try:
                item = receive_object(receiving)
            except (EOFError, OSError):
                code = process.exitcode
                raise RuntimeError(f"the log reader process ended unexpectedly (exit code {code})") from None
            yield item
            if isinstance(item, (_Done, _Raised)):
                return

    queued_items = queued(receive(), RECEIVE_DEPTH)
    try:
        for item in queued_items:
            if isinstance(item, _Raised):
                raise item.exc
            if isinstance(item, _Done):
                reader.stats, losses, format_name = item.stats
                if losses is not None:
                    reader.losses = losses  # type: ignore[attr-defined]
                if format_name is not None:
                    reader.format_name = format_name  # type: ignore[attr-defined]
                return
            yield item
    finally:
        # end the child first: its end of the pipe closes, so the receiving thread stops
        if process.is_alive():
            process.terminate()
        process.join()
        queued_items.close()
        try:
            receiving.close()
        except OSError:
            pass
