"""The one read loop: the ``sensor_msgs/Imu`` samples of a log, screened and counted.

:class:`ImuBatches` streams the decoded batches of the configured topics (the containers and the
message layout are :mod:`imucal_cli.io`'s), timed by ``header.stamp`` (log time where the stamp
is zero), with damaged samples dropped; :func:`read_imu` assembles whole topics, sorted,
duplicate stamps removed. Whatever was reordered, removed or replaced is counted in
:class:`ReadStats`; what could not be read at all is a :class:`~imucal_cli.io.base.Loss`.
Nothing here knows a file format.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from imucal_cli.io.base import LogReader, Loss
from imucal_cli.io.imu_msg import DecodedBatch, RawBatch, decode_imu
from imucal_cli.io.logs import check_topics, open_log, open_recording
from imucal_cli.types import GAP_PERIODS

if TYPE_CHECKING:
    from imucal_cli.types import ImuStream


@dataclass
class ReadStats:
    """What reading one topic found and did. Nothing is dropped without being counted here."""

    messages: int = 0  # messages read from the log
    zero_stamps: int = 0  # header.stamp was zero: log time used instead
    backwards: int = 0  # stamp earlier than the previous message's (in log order): sorted
    duplicates: int = 0  # stamp equal to an earlier one: removed (the first is kept)
    decode_errors: int = 0  # messages that could not be deserialized: skipped
    non_finite: int = 0  # a NaN or infinite gyro or accelerometer value: dropped
    saturated: int = 0  # a gyro or accelerometer axis clipped at its range: dropped
    clock_jumps: int = 0  # stamps leaping by more than CLOCK_JUMP_S (forwards or back)
    gaps: int = 0  # steps over GAP_PERIODS median periods: windows spanning them are not used
    implausible: int = (
        0  # values no IMU measures (|gyro| > 100 rad/s, |accel| > 2000 m/s^2): dropped
    )
    stamp_outliers: int = 0  # a lone stamp far from both neighbours (a damaged message): dropped
    frame_ids: list[str] = field(default_factory=list)

    def usable(self) -> int:
        """The messages read less those dropped."""
        dropped = self.decode_errors + self.non_finite + self.saturated + self.implausible
        return self.messages - dropped - self.stamp_outliers

    def to_dict(self) -> dict[str, Any]:
        """The counts (every field but the frame ids)."""
        return {k: v for k, v in asdict(self).items() if k != "frame_ids"}


@dataclass(frozen=True)
class ImuRead:
    stream: ImuStream
    stats: ReadStats
    log_time_ns: np.ndarray  # log (receive) time of each kept sample, same order as the stream


def _finish_topic(
    t_ns: np.ndarray, log_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray, stats: ReadStats
) -> ImuRead:
    """One topic's samples (in log order) sorted by stamp, duplicate stamps removed, counted."""
    from imucal_cli.types import ImuStream

    stats.backwards = int(np.count_nonzero(np.diff(t_ns) < 0))
    order = np.argsort(t_ns, kind="stable")
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = np.diff(t_ns[order]) != 0
    stats.duplicates = int(np.count_nonzero(~keep))
    index = order[keep]
    frame_id = stats.frame_ids[0] if stats.frame_ids else ""
    return ImuRead(
        ImuStream(t_ns[index], gyro[index].reshape(-1, 3), accel[index].reshape(-1, 3), frame_id),
        stats,
        log_ns[index],
    )


#: A step between consecutive stamps of one topic longer than this (s) is a clock jump.
CLOCK_JUMP_S = 60.0
#: Smallest magnitude a run of identical extreme samples must have to be called clipped: a
#: gyro past 2 rad/s or an accelerometer past 1.5 g is beyond vehicle motion and at the range
#: of common MEMS parts (+-125 deg/s and up, +-2 g and up).
SATURATION_GYRO_RADPS = 2.0
#: Beyond these no IMU measures: such values are damaged data, dropped and counted.
IMPLAUSIBLE_GYRO_RADPS = 100.0
IMPLAUSIBLE_ACCEL_MPS2 = 2000.0
SATURATION_ACCEL_MPS2 = 1.5 * 9.80665
#: A value repeated this many samples in a row at its batch's extreme is clipped.
SATURATION_RUN = 3


def _stamp_outliers(stamps: np.ndarray) -> np.ndarray:
    """Runs of stamps that leap more than ``CLOCK_JUMP_S`` away and come back within the batch
    (to within ``CLOCK_JUMP_S`` of where they left): damaged stamps (a flipped bit, copied along
    by the compressor), not a clock jump, after which the stamps stay moved."""
    out = np.zeros(len(stamps), dtype=bool)
    if len(stamps) < 2:
        return out
    jump = CLOCK_JUMP_S * 1e9
    t = stamps.astype(np.float64)
    leaps = np.flatnonzero(np.abs(np.diff(t)) > jump)  # a leap between k and k + 1
    if len(leaps) and leaps[0] == 0 and np.all(np.abs(t[1:] - t[0]) > jump):
        out[0] = True  # the first stamp alone is off: no later stamp comes near it
        leaps = leaps[1:]
    k = 0
    while k < len(leaps):
        start = leaps[k]
        back = next((j for j in leaps[k + 1 :] if abs(t[j + 1] - t[start]) <= jump), None)
        if back is None:  # a clock jump: the stamps stay moved; later runs may still come back
            k += 1
            continue
        out[start + 1 : back + 1] = True
        k = int(np.searchsorted(leaps, back)) + 1
    return out


def _clipped(values: np.ndarray, floor: float) -> np.ndarray:
    """Rows where some axis sits at the batch's extreme magnitude (at least ``floor``) for
    ``SATURATION_RUN`` or more samples in a row: what a sensor at the end of its range outputs."""
    out = np.zeros(len(values), dtype=bool)
    if len(values) < SATURATION_RUN:
        return out
    # the largest magnitude per axis, column by column (numpy reduces an (n, 3) array over its
    # long axis seven times slower than three columns one at a time)
    extreme = np.array([max(-float(column.min()), float(column.max())) for column in values.T])
    for axis in np.flatnonzero(extreme >= floor):
        at = np.abs(values[:, axis]) == extreme[axis]
        if np.count_nonzero(at) < SATURATION_RUN:
            continue  # too few samples at the extreme for a run
        run = (
            np.convolve(at.astype(np.int64), np.ones(SATURATION_RUN, dtype=np.int64), mode="valid")
            == SATURATION_RUN
        )
        for k in range(SATURATION_RUN):
            out[k : k + len(run)] |= run
    return out


def _within(extremes: tuple[float, ...], gyro_max: float, accel_max: float, strict: bool) -> bool:
    """Whether a batch's ``(gyro min, max, accel min, max)`` lie within the bounds (and are
    finite: a NaN anywhere makes the whole-array extremes NaN, and the comparisons False)."""
    g_lo, g_hi, a_lo, a_hi = extremes
    if strict:
        return bool(-gyro_max < g_lo and g_hi < gyro_max and -accel_max < a_lo and a_hi < accel_max)
    return bool(-gyro_max <= g_lo and g_hi <= gyro_max and -accel_max <= a_lo and a_hi <= accel_max)


class ImuBatches:
    """Decoded ``sensor_msgs/Imu`` batches of a log, in the container's order, without holding
    the whole log: ``(topic, stamp_ns, log_time_ns, gyro, accel)`` per batch (stamps that are
    zero replaced by the log time). What was read is counted in :attr:`stats`; what could not
    be read is in :attr:`losses` once iterated."""

    def __init__(
        self, path: str | Path, topics: Iterable[str], follow: Callable[[], bool] | None = None
    ) -> None:
        self.path = Path(path)
        #: Follow mode: read a log still being written until ``follow()`` says stop (or it ends).
        self.follow = follow
        self.topics = list(dict.fromkeys(topics))
        self.stats: dict[str, ReadStats] = {t: ReadStats() for t in self.topics}
        #: Per topic, the stamps (ns) of the clipped samples dropped since :meth:`take_clipped`.
        self.clipped: dict[str, list[np.ndarray]] = {t: [] for t in self.topics}
        self.losses: list[Loss] = []
        self.format_name = ""
        #: Per topic, the number of messages the container says it has (once iterating).
        self.expected: dict[str, int] = {}
        self._last_stamp: dict[str, int] = {}
        self._reached: dict[str, int] = {}  # per topic: the latest stamp kept so far
        self._period: dict[str, float] = {}  # per topic: median step between stamps (ns)

    def _screen(
        self,
        topic: str,
        stamps: np.ndarray,
        log_times: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
    ):
        """Drop (and count) samples with non-finite, implausible or clipped values and damaged
        stamps. The common case (nothing to drop) costs a few whole-batch reductions."""
        st = self.stats[topic]
        zero = stamps == 0
        if zero.any():
            st.zero_stamps += int(np.count_nonzero(zero))
            stamps = np.where(zero, log_times, stamps)
        if not len(stamps):
            return stamps, log_times, gyro, accel
        jump = int(CLOCK_JUMP_S * 1e9)
        reached_before = self._reached.get(topic, -(2**62))
        low, high = int(stamps.min()), int(stamps.max())
        # no step can leap by more than `jump` when the whole batch spans less than that
        narrow = high - low <= jump
        stamps_ok = (
            narrow or bool(np.abs(np.diff(stamps)).max() <= jump)
        ) and low >= reached_before - jump
        quiet = narrow and low >= reached_before - jump  # nothing leaps, nothing falls behind
        extremes = (float(gyro.min()), float(gyro.max()), float(accel.min()), float(accel.max()))
        values_ok = _within(extremes, SATURATION_GYRO_RADPS, SATURATION_ACCEL_MPS2, strict=True)
        # values past the saturation floors but plausible, stamps quiet (a lively sensor):
        # only a clipped run could be dropped, and there is none in the usual case
        if (values_ok and stamps_ok) or (
            quiet
            and _within(extremes, IMPLAUSIBLE_GYRO_RADPS, IMPLAUSIBLE_ACCEL_MPS2, strict=False)
            and not _clipped(gyro, SATURATION_GYRO_RADPS).any()
            and not _clipped(accel, SATURATION_ACCEL_MPS2).any()
        ):
            self._reached[topic] = max(reached_before, high)
            return stamps, log_times, gyro, accel
        unusable, clipped = self._bad_values(topic, stamps, gyro, accel)
        bad = unusable | clipped | self._bad_stamps(topic, stamps, reached_before, jump, unusable)
        if bad.any():
            keep = ~bad
            return stamps[keep], log_times[keep], gyro[keep], accel[keep]
        return stamps, log_times, gyro, accel

    def _bad_values(
        self, topic: str, stamps: np.ndarray, gyro: np.ndarray, accel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The samples whose values are not finite or not plausible, and those clipped,
        counted; the clipped ones' stamps kept for :meth:`take_clipped`."""
        st = self.stats[topic]
        finite = np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        bad = ~finite
        st.non_finite += int(np.count_nonzero(bad))
        with np.errstate(invalid="ignore"):
            absurd = finite & (
                (np.abs(gyro) > IMPLAUSIBLE_GYRO_RADPS).any(axis=1)
                | (np.abs(accel) > IMPLAUSIBLE_ACCEL_MPS2).any(axis=1)
            )
        st.implausible += int(np.count_nonzero(absurd))
        bad |= absurd
        finite &= ~absurd
        clipped = np.zeros(len(stamps), dtype=bool)
        if finite.any():
            clipped[finite] = _clipped(gyro[finite], SATURATION_GYRO_RADPS) | _clipped(
                accel[finite], SATURATION_ACCEL_MPS2
            )
        st.saturated += int(np.count_nonzero(clipped))
        if clipped.any():
            self.clipped[topic].append(stamps[clipped])
        return bad, clipped

    def _bad_stamps(
        self, topic: str, stamps: np.ndarray, reached_before: int, jump: int, unusable: np.ndarray
    ) -> np.ndarray:
        """The samples whose stamps are damaged or leap back behind what the topic reached,
        counted (the ``unusable`` ones, bad by their values, left out of the count)."""
        st = self.stats[topic]
        outlier = _stamp_outliers(stamps)
        # stamps that leap back by minutes or more behind what this topic already reached
        # cannot be placed in time: dropped (a forward leap is kept: time moves on)
        running = np.maximum(
            np.maximum.accumulate(np.where(outlier, -(2**62), stamps)), reached_before
        )
        behind = ~outlier & (stamps < running - jump)
        if (~outlier).any():
            self._reached[topic] = max(reached_before, int(stamps[~outlier].max()))
        st.stamp_outliers += int(np.count_nonzero((outlier | behind) & ~unusable))
        st.clock_jumps += int(
            np.count_nonzero(np.diff(np.concatenate([[0], behind.astype(np.int8)])) == 1)
        )
        return outlier | behind

    def take_clipped(self, topic: str) -> np.ndarray:
        """The stamps (ns) of ``topic``'s clipped samples dropped since the last call."""
        found, self.clipped[topic] = self.clipped[topic], []
        return np.concatenate(found) if found else np.zeros(0, dtype=np.int64)

    def _count(
        self, topic: str, stamps: np.ndarray, log_times: np.ndarray, frame_ids: list[str]
    ) -> np.ndarray:
        st = self.stats[topic]
        if len(stamps):
            previous = self._last_stamp.get(topic)
            steps = np.diff(stamps if previous is None else np.concatenate([[previous], stamps]))
            st.backwards += int(np.count_nonzero(steps < 0))
            jumps = np.abs(steps) > CLOCK_JUMP_S * 1e9
            st.clock_jumps += int(np.count_nonzero(jumps))
            period = self._period.get(topic)
            if period is None:  # the topic's median period, from its first batch long enough
                positive = steps[steps > 0]
                if len(positive) >= 10:
                    period = self._period[topic] = float(np.median(positive))
            if period is not None:
                st.gaps += int(np.count_nonzero((steps > GAP_PERIODS * period) & ~jumps))
            self._last_stamp[topic] = int(stamps[-1])
        for name in frame_ids:
            if name not in st.frame_ids:
                st.frame_ids.append(name)
        return stamps

    def __iter__(self) -> Iterator[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        log = open_log(self.path) if self.follow is None else open_recording(self.path)
        with log:
            self.format_name = log.format_name
            try:
                if self.follow is None:
                    available = check_topics(log, self.topics)
                    self.expected = {t: available[t].count for t in self.topics}
                    batches = log.batches(self.topics)
                else:  # topics appear as they are recorded
                    batches = log.follow(self.topics, self.follow)
                pairs = ((b, decode(log, b)) for b in batches)
                for batch, decoded in pairs:
                    st = self.stats[batch.topic]
                    st.messages += len(batch.starts)
                    st.decode_errors += decoded.errors
                    stamps, log_times, gyro, accel = self._screen(
                        batch.topic,
                        decoded.stamp_ns,
                        decoded.log_time_ns,
                        decoded.gyro,
                        decoded.accel,
                    )
                    yield (
                        batch.topic,
                        self._count(batch.topic, stamps, log_times, decoded.frame_ids),
                        log_times,
                        gyro,
                        accel,
                    )
            finally:
                self.losses = list(log.losses)


def decode(log: LogReader, batch: RawBatch) -> DecodedBatch:
    """A batch of IMU messages decoded; damaged data is the log's error naming the topic."""
    try:
        return decode_imu(batch)
    except ValueError as exc:
        raise log.error(str(exc), batch.topic) from None


def read_imu(
    path: str | Path,
    topics: Iterable[str],
    progress: Callable[[int, int], None] | None = None,
    losses: list[Loss] | None = None,
) -> dict[str, ImuRead]:
    """Read ``sensor_msgs/Imu`` topics of a log into one :class:`ImuRead` per topic.

    Raises :class:`LogError` where the log cannot be read, a topic is missing (the message
    lists the IMU topics the log has) or a topic is not ``sensor_msgs/Imu``."""
    reader = ImuBatches(path, topics)
    parts: dict[str, list[tuple[np.ndarray, ...]]] = {t: [] for t in reader.topics}
    count = 0
    for topic, stamps, log_times, gyro, accel in reader:
        parts[topic].append((stamps, log_times, gyro, accel))
        count += len(stamps)
        if progress is not None:
            progress(count, sum(reader.expected.values()))
    if losses is not None:
        losses.extend(reader.losses)
    out = {}
    for topic, batches in parts.items():
        stamps, log_times, gyro, accel = (
            np.concatenate([b[k] for b in batches]) if batches else np.zeros((0, 3) if k > 1 else 0)
            for k in range(4)
        )
        if len(log_times) > 1 and np.any(
            np.diff(log_times) < 0
        ):  # log order, for the backwards count
            order = np.argsort(log_times, kind="stable")
            stamps, log_times, gyro, accel = (
                stamps[order],
                log_times[order],
                gyro[order],
                accel[order],
            )
        out[topic] = _finish_topic(
            stamps.astype(np.int64), log_times.astype(np.int64), gyro, accel, reader.stats[topic]
        )
    return out
