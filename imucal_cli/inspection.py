"""What ``imucal inspect`` reports of a log: per topic its type, count, rate, duration, gaps,
backwards jumps and duplicate stamps, read in one streamed pass."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imucal_cli.io.base import Loss
from imucal_cli.io.imu_msg import decode_imu
from imucal_cli.io.logs import open_log
from imucal_cli.types import GAP_PERIODS


@dataclass(frozen=True)
class TopicTiming:
    """Timing of one topic, as ``imucal inspect`` reports it (seconds since ``t0_ns``)."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float
    duration_s: float
    gaps: list[tuple[float, float]]
    backwards: int
    duplicates: int
    time_source: str  # "header.stamp" or "log_time"


@dataclass(frozen=True)
class LogSummary:
    path: str
    format_name: str
    t0_ns: int
    topics: list[TopicTiming]
    losses: list[Loss] = field(default_factory=list)


#: Stamps may arrive this far out of order (ns) and still be put in order; a stamp later than
#: that is counted backwards but not placed (a damaged stamp, or another clock).
REORDER_NS = 10 * 10**9
#: Distinct step lengths kept exactly (ns); past that (stamps with jitter), in units of
#: :data:`COARSE_NS`: the median period then has 50 ns of rounding (5e-6 of a 100 Hz period).
EXACT_STEPS, COARSE_NS = 16384, 100


class _Clock:
    """One topic's stamps, taken in log order and put in stamp order within :data:`REORDER_NS`:
    count, span, backwards, duplicates, the steps' lengths and the long steps. Memory follows
    the distinct step lengths and the gaps, not the log's length."""

    def __init__(self) -> None:
        self.count = self.backwards = self.duplicates = 0
        self.low: int | None = None
        self.high: int | None = None
        self.last_in: int | None = None  # the last stamp in log order
        self.placed: int | None = None  # the last stamp put in order
        self.pending: list[np.ndarray] = []
        self.steps: Counter[int] = Counter()  # length (ns, or COARSE_NS once coarse) -> how many
        self.coarse = False
        self.long: list[tuple[int, int]] = []  # steps past 2.5 median periods, for the gaps

    def add(self, t: np.ndarray) -> None:
        t = t.astype(np.int64)
        self.count += len(t)
        self.low = int(t.min()) if self.low is None else min(self.low, int(t.min()))
        self.high = int(t.max()) if self.high is None else max(self.high, int(t.max()))
        self.backwards += int(
            np.count_nonzero(
                np.diff(t if self.last_in is None else np.concatenate([[self.last_in], t])) < 0
            )
        )
        self.last_in = int(t[-1])
        self.pending.append(t)
        if sum(map(len, self.pending)) > 65536:
            self.place(self.high - REORDER_NS)

    def place(self, upto: int | None = None) -> None:
        """Put the pending stamps up to ``upto`` (all: None) in order and count their steps."""
        if not self.pending:
            return
        t = np.sort(np.concatenate(self.pending))
        split = len(t) if upto is None else int(np.searchsorted(t, upto, side="right"))
        self.pending = [t[split:]] if split < len(t) else []
        t = t[:split]
        if self.placed is not None:
            t = t[t >= self.placed]  # (later than the reordering allows: counted backwards only)
            t = np.concatenate([[self.placed], t])
        if len(t) < 2:
            self.placed = int(t[-1]) if len(t) else self.placed
            return
        steps = np.diff(t)
        self.duplicates += int(np.count_nonzero(steps == 0))
        positive = steps[steps > 0]
        values, counts = np.unique(
            positive // COARSE_NS if self.coarse else positive, return_counts=True
        )
        self.steps.update(dict(zip(values.tolist(), counts.tolist(), strict=True)))
        if not self.coarse and len(self.steps) > EXACT_STEPS:
            coarse: Counter[int] = Counter()
            for value, n in self.steps.items():
                coarse[value // COARSE_NS] += n
            self.steps, self.coarse = coarse, True
        median = self.median()
        for i in np.flatnonzero(steps > 0.5 * GAP_PERIODS * median):
            self.long.append((int(t[i]), int(t[i + 1])))
        self.placed = int(t[-1])

    def median(self) -> float:
        """The median step between stamps (ns)."""
        total, seen = sum(self.steps.values()), 0
        for value in sorted(self.steps):
            seen += self.steps[value]
            if 2 * seen >= total:
                return (value + 0.5) * COARSE_NS if self.coarse else float(value)
        return 0.0


def _timing(
    topic: str, msgtype: str, clock: _Clock | None, t0_ns: int, time_source: str
) -> TopicTiming:
    if clock is None or clock.count == 0:
        return TopicTiming(topic, msgtype, 0, 0.0, 0.0, [], 0, 0, time_source)
    clock.place()
    median = clock.median()
    rate = 1e9 / median if median > 0 else 0.0
    gaps = [
        ((a - t0_ns) * 1e-9, (b - t0_ns) * 1e-9)
        for a, b in clock.long
        if median > 0 and b - a > GAP_PERIODS * median
    ]
    duration = float(clock.high - clock.low) * 1e-9  # type: ignore[operator]
    return TopicTiming(
        topic,
        msgtype,
        clock.count,
        rate,
        duration,
        gaps,
        clock.backwards,
        clock.duplicates,
        time_source,
    )


def summarize_log(
    path: str | Path, progress: Callable[[int, int], None] | None = None
) -> LogSummary:
    """Per topic: type, count, median rate, duration, gaps, backwards jumps, duplicates, read
    in one streamed pass, memory flat in the log's length. IMU topics are timed by
    ``header.stamp`` (log time where it is zero or the message does not decode), others by log
    time."""
    path = Path(path)
    clocks: dict[str, _Clock] = {}
    with open_log(path) as log:
        available = log.topics()
        imu = {
            t for t, info in available.items() if info.is_imu and info.encoding in ("cdr", "ros1")
        }
        count, total = 0, sum(info.count for info in available.values())
        for batch in log.batches(list(available)):
            times = batch.log_time_ns
            if batch.topic in imu:
                decoded = decode_imu(batch)
                if decoded.errors == 0:
                    times = np.where(decoded.stamp_ns == 0, times, decoded.stamp_ns)
            if len(times):
                clocks.setdefault(batch.topic, _Clock()).add(times)
            count += len(times)
            if progress is not None:
                progress(count, total)
        format_name, losses = log.format_name, list(log.losses)
    t0_ns = min((c.low for c in clocks.values() if c.low is not None), default=0)
    timings = [
        _timing(
            topic,
            available[topic].msgtype,
            clocks.get(topic),
            t0_ns,
            "header.stamp" if topic in imu else "log_time",
        )
        for topic in sorted(available)
    ]
    return LogSummary(
        path=str(path), format_name=format_name, t0_ns=t0_ns, topics=timings, losses=losses
    )
