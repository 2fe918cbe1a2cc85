"""What ``imucal inspect`` reports of a log: per topic its type, count, rate, duration, gaps,
backwards jumps and duplicate stamps, read in one streamed pass."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imucal_cli.io.base import Loss
from imucal_cli.io.imu_msg import decode_imu
from imucal_cli.io.logs import open_log
from imucal_cli.reading import GAP_MEDIAN_PERIODS


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




def _timing(
    topic: str, msgtype: str, stamps_in_log_order: np.ndarray, t0_ns: int, time_source: str
) -> TopicTiming:
    n = len(stamps_in_log_order)
    if n == 0:
        return TopicTiming(topic, msgtype, 0, 0.0, 0.0, [], 0, 0, time_source)
    backwards = int(np.count_nonzero(np.diff(stamps_in_log_order) < 0))
    t_sorted = np.sort(stamps_in_log_order)
    steps = np.diff(t_sorted)
    duplicates = int(np.count_nonzero(steps == 0))
    positive = steps[steps > 0]
    median = float(np.median(positive)) if len(positive) else 0.0
    rate = 1e9 / median if median > 0 else 0.0
    gaps: list[tuple[float, float]] = []
    if median > 0:
        for i in np.flatnonzero(steps > GAP_MEDIAN_PERIODS * median):
            gaps.append(
                (float(t_sorted[i] - t0_ns) * 1e-9, float(t_sorted[i + 1] - t0_ns) * 1e-9)
            )
    duration = float(t_sorted[-1] - t_sorted[0]) * 1e-9
    return TopicTiming(topic, msgtype, n, rate, duration, gaps, backwards, duplicates, time_source)


def summarize_log(path: str | Path, progress: Callable[[int, int], None] | None = None) -> LogSummary:
    """Per topic: type, count, median rate, duration, gaps, backwards jumps, duplicates, read
    in one streamed pass. IMU topics are timed by ``header.stamp`` (log time where it is zero
    or the message does not decode), others by log time."""
    path = Path(path)
    stamps: dict[str, list[np.ndarray]] = {}
    firsts: dict[str, int] = {}
    with open_log(path) as log:
        available = log.topics()
        imu = {t for t, info in available.items() if info.is_imu and info.encoding in ("cdr", "ros1")}
        count, total = 0, sum(info.count for info in available.values())
        for batch in log.batches(list(available)):
            times = batch.log_time_ns
            if batch.topic in imu:
                decoded = decode_imu(batch)
                if decoded.errors == 0:
                    times = np.where(decoded.stamp_ns == 0, times, decoded.stamp_ns)
            if len(times):
                stamps.setdefault(batch.topic, []).append(times)
                firsts[batch.topic] = min(firsts.get(batch.topic, int(times.min())), int(times.min()))
            count += len(times)
            if progress is not None:
                progress(count, total)
        format_name, losses = log.format_name, list(log.losses)
    t0_ns = min(firsts.values()) if firsts else 0
    timings = []
    for topic in sorted(available):  # a topic at a time, its batches freed as it is joined
        parts = stamps.pop(topic, [])
        joined = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        del parts
        timings.append(_timing(topic, available[topic].msgtype, joined, t0_ns, "header.stamp" if topic in imu else "log_time"))
    return LogSummary(path=str(path), format_name=format_name, t0_ns=t0_ns, topics=timings, losses=losses)
