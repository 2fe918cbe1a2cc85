"""The Python API: calibrate a recorded log, export and evaluate, without the command line.

>>> from imucal_cli import calibrate_log, load_config              # doctest: +SKIP
>>> run = calibrate_log("drive.mcap", load_config("vehicle.yaml"))  # doctest: +SKIP
>>> run.result.T_base_lidar("front_left_top").as_matrix()          # doctest: +SKIP
>>> run.document["sensors"]["front_left_top"]["status"]             # doctest: +SKIP

Everything here raises :class:`~imucal_cli.errors.ImucalError` subclasses on bad input (with
the file, topic or key in the message) and prints nothing; what reading found (counts, losses)
is returned for the caller to report.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.config import Config, load_config
from imucal_cli.core.streaming import StreamingCalibrator
from imucal_cli.errors import ImucalError, InputError
from imucal_cli.io.base import Loss
from imucal_cli.pipeline import CalibrationResult, calibration_document, make_calibrator
from imucal_cli.reading import ImuBatches, ReadStats
from imucal_cli.types import Transform

#: Follow mode: how far out of order a recording's stamps may arrive (s). A recorder appends in
#: receive order, so a window waits less for stragglers than in a file (0.5 s), and its
#: estimate comes sooner.
FOLLOW_REORDER_S = 0.2
#: Spread of receive latencies allowed between topics when their clocks are compared (s).
CLOCK_COMPARE_SLACK_S = 0.05
#: Samples at the start of each topic whose ``stamp - log_time`` gives its clock's offset.
CLOCK_COMPARE_SAMPLES = 200

__all__ = [
    "LogCalibration",
    "StreamedLog",
    "calibrate_log",
    "estimate",
    "evaluate",
    "export_extrinsics",
    "follow_log",
    "load_transforms",
    "lost_summary",
    "stream_biases",
    "stream_log",
    "write_report",
]


def imu_names(config: Config) -> dict[str, str]:
    """Every configured IMU topic and the name the calibrator knows it by ("base", sensors')."""
    return {config.base.topic: "base"} | {s.imu_topic: s.name for s in config.sensors}


def lost_summary(losses: list[Loss]) -> str:
    """For an error message: what of the log could not be read, if anything."""
    real = [x for x in losses if x.lost]
    if not real:
        return ""
    more = f" and {len(real) - 1} more" if len(real) > 1 else ""
    return f" (damaged parts were skipped: {real[0].describe()}{more})"


class _ClockCheck:
    """Compares each IMU's stamps with the recorder's log (receive) times, which all topics
    share: the median of ``stamp - log_time`` over a topic's first samples is its clock's offset
    from the recorder's. A sensor whose offset differs from the base's by more than
    ``max_time_offset_s`` (plus receive-latency slack) is on another clock (stamped from
    power-on, say), which the time-offset search cannot bridge."""

    def __init__(self, log: Path, base_topic: str, max_offset_s: float) -> None:
        self.log, self.base_topic, self.max_offset_s = log, base_topic, max_offset_s
        self.offsets: dict[str, float] = {}
        self.checked = False

    def add(self, topic: str, stamps: np.ndarray, log_times: np.ndarray) -> None:
        if topic in self.offsets or not len(stamps):
            return
        first = slice(0, CLOCK_COMPARE_SAMPLES)  # a clock that jumps later is a jump, not another clock
        self.offsets[topic] = float(np.median((stamps[first] - log_times[first]).astype(np.float64))) * 1e-9

    def check(self, topics: list[str]) -> None:
        if self.checked or not all(t in self.offsets for t in topics):
            return
        self.checked = True
        base = self.offsets[self.base_topic]
        for topic in topics:
            difference = self.offsets[topic] - base
            if abs(difference) > self.max_offset_s + CLOCK_COMPARE_SLACK_S:
                raise InputError(
                    f"{self.log} [{topic}]: stamps are {difference:+.3f} s from the base IMU's "
                    f"({self.base_topic}), measured against the log's receive times; "
                    f"calibration.max_time_offset_s is {self.max_offset_s:g} s: fix the sensor's "
                    "clock, or raise max_time_offset_s if the offset is real"
                )


@dataclass
class StreamedLog:
    """A log streamed through a calibrator: windows reduced, nothing solved yet."""

    log: Path
    config: Config
    calibrator: StreamingCalibrator
    t0_ns: int  # first IMU stamp: the origin of report times
    stats: dict[str, ReadStats]  # per topic: what reading counted
    duplicates: dict[str, int]  # per topic: duplicate stamps the calibrator removed
    losses: list[Loss]  # parts of a damaged log that could not be read
    format_name: str

    def counts(self) -> dict[str, dict[str, int]]:
        """Per topic, what reading counted (:class:`ReadStats`), the calibrator's duplicates in."""
        return {topic: stats.to_dict() | {"duplicates": stats.duplicates + self.duplicates.get(topic, 0)} for topic, stats in self.stats.items()}


def stream_log(log: str | Path, config: Config, progress: Callable[[int, int], None] | None = None) -> StreamedLog:
    """Stream the configured IMU topics of ``log`` through a calibrator, memory flat in the
    log's length: windows reduced, nothing solved yet."""
    log = Path(log)
    names = imu_names(config)
    reader = ImuBatches(log, names)
    calibrator = make_calibrator(config)
    clocks = _ClockCheck(log, config.base.topic, config.calibration.max_time_offset_s)
    t0_ns: int | None = None
    count = 0
    for topic, stamps, log_times, gyro, accel in reader:
        clocks.add(topic, stamps, log_times)
        clocks.check(list(names))
        if len(stamps):
            first = int(stamps.min())
            t0_ns = first if t0_ns is None else min(t0_ns, first)
        calibrator.add(names[topic], stamps, gyro, accel)
        count += len(stamps)
        if progress is not None:
            progress(count, sum(reader.expected.values()))  # messages read, of what the log holds
    lost = lost_summary(reader.losses)
    for topic, stats in reader.stats.items():
        usable = stats.messages - stats.decode_errors - stats.non_finite - stats.saturated - stats.implausible - stats.stamp_outliers
        if usable < 10:
            raise InputError(f"{log} [{topic}]: too little data: {usable} usable messages{lost}")
    if calibrator.t_ref_ns is None or t0_ns is None:
        raise InputError(f"{log}: too little data: an IMU topic has no messages{lost}")
    try:
        calibrator.process(final=True)
    except ImucalError as exc:
        raise InputError(f"{log}: {str(exc).removeprefix(str(log) + ': ')}{lost}") from None
    duplicates = {topic: calibrator.duplicates(name) for topic, name in names.items()}
    return StreamedLog(log, config, calibrator, t0_ns, reader.stats, duplicates, reader.losses, reader.format_name)


def stream_biases(log: str | Path, config: Config, progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """The SPEC's ``biases`` document of ``log``: every configured IMU streamed through a
    :class:`~imucal_cli.core.biases.BiasTracker`, memory flat in the log's length."""
    from imucal_cli.pipeline import (
        bias_trackers,
        biases_document,
        dropped_document,
        losses_document,
        lost_seconds,
        read_warnings,
    )

    log = Path(log)
    names = imu_names(config)
    trackers = bias_trackers(config)
    reader = ImuBatches(log, names)
    count = 0
    for topic, stamps, _, gyro, accel in reader:
        trackers[names[topic]].add(stamps, gyro, accel)
        count += len(stamps)
        if progress is not None:
            progress(count, sum(reader.expected.values()))  # messages read, of what the log holds
    empty = [topic for topic, name in names.items() if trackers[name].first_ns is None]
    if empty:
        raise InputError(f"{log} [{empty[0]}]: too little data: no usable message{lost_summary(reader.losses)}")
    reports = {name: tracker.report() for name, tracker in trackers.items()}
    document = biases_document(min(r.first_ns for r in reports.values()), config, reports)
    counts = {topic: stats.to_dict() for topic, stats in reader.stats.items()}
    for topic, name in names.items():  # what reading lost and dropped, said where it happened
        document["imus"][name]["warnings"] += read_warnings(topic, counts[topic])
    return document | {"lost_s": lost_seconds(reader.losses), "losses": losses_document(reader.losses), "dropped": dropped_document(counts)}


@dataclass
class LogCalibration:
    """The outcome of :func:`calibrate_log`."""

    result: CalibrationResult  # estimates per sensor; ``result.T_base_lidar(name)``
    document: dict[str, Any]  # the SPEC's calibrate document (what ``imucal calibrate -o`` writes)
    streamed: StreamedLog  # what reading found: counts per topic, losses


def calibrate_log(log: str | Path, config: Config | str | Path, progress: Callable[[int, int], None] | None = None) -> LogCalibration:
    """Calibrate every sensor of ``config`` from the IMU topics of ``log`` (MCAP, rosbag2 or
    ROS 1 bag). ``config`` is a :class:`Config` or the path of its YAML file; ``progress`` is
    called with (messages read, messages in the log) as reading goes."""
    if not isinstance(config, Config):
        config = load_config(config)
    streamed = stream_log(log, config, progress)
    result = estimate(streamed)
    return LogCalibration(result, calibration_document(result, str(log), streamed.losses, streamed.counts()), streamed)


def follow_log(
    log: str | Path, config: Config, on_update: Callable[[CalibrationResult, int], None] | None = None,
    stop: Callable[[], bool] = lambda: False, until_converged: bool = False,
) -> tuple[LogCalibration, bool, bool]:
    """Follow a log that is still being written (an MCAP file, or a rosbag2 folder recording
    to mcap or sqlite3 storage): the estimate after every window, ``on_update(result,
    windows)``, until the recording ends, ``stop()`` says so, or (``until_converged``) every
    sensor is within the config's ``stop:`` targets. Returns the last calibration (its
    document with each sensor's ``missing`` axes and ``converged``), whether it converged, and
    whether a Ctrl-C ended it (the estimate so far is returned all the same)."""
    from imucal_cli.pipeline import converged, missing_axes

    log = Path(log)
    names = imu_names(config)
    calibrator = make_calibrator(config, block_windows=1, reorder_s=FOLLOW_REORDER_S)
    done = [False]
    reader = ImuBatches(log, names, follow=lambda: done[0] or stop())
    clocks = _ClockCheck(log, config.base.topic, config.calibration.max_time_offset_s)  # as stream_log
    windows, result, good = 0, None, False
    t0_ns: int | None = None
    interrupted = False
    try:
        for topic, stamps, log_times, gyro, accel in reader:
            clocks.add(topic, stamps, log_times)
            clocks.check(list(names))
            if len(stamps):
                t0_ns = int(stamps.min()) if t0_ns is None else min(t0_ns, int(stamps.min()))
            calibrator.add(names[topic], stamps, gyro, accel)
            reduced = min(len(w) for w in calibrator.windows.values())
            if reduced > windows:
                windows = reduced
                result = _estimate_now(calibrator, config)
                if result is not None:
                    good = converged(result)
                    if on_update is not None:
                        on_update(result, windows)
                    if until_converged and good:
                        done[0] = True
    except KeyboardInterrupt:
        interrupted = True
    if not done[0]:  # the recording ended, time is up, or a Ctrl-C: what is buffered, reduced
        try:
            calibrator.process(final=True)
            result = _estimate_now(calibrator, config) or result
            good = result is not None and converged(result)
        except ImucalError as exc:  # as stream_log says it (after a Ctrl-C: the estimate so far)
            if not interrupted:
                raise InputError(f"{log}: {str(exc).removeprefix(str(log) + ': ')}{lost_summary(reader.losses)}") from None
    if result is None or t0_ns is None:
        raise InputError(f"{log}: too little data to estimate anything yet{lost_summary(reader.losses)}")
    streamed = StreamedLog(log, config, calibrator, t0_ns, reader.stats, {t: calibrator.duplicates(n) for t, n in names.items()}, reader.losses, reader.format_name)
    document = calibration_document(result, str(log), reader.losses, streamed.counts())
    for name, estimate in result.estimates.items():  # what each sensor still lacks of the stop: targets
        document["sensors"][name]["missing"] = missing_axes(estimate, config.stop)
    document["converged"] = good
    return LogCalibration(result, document, streamed), good, interrupted


def _estimate_now(calibrator: StreamingCalibrator, config: Config) -> CalibrationResult | None:
    """The estimate from the windows so far, or None before the calibrator has booted."""
    if not calibrator.tau0:
        return None
    with np.errstate(all="ignore"):
        try:
            estimates = calibrator.estimates()
        except (ImucalError, np.linalg.LinAlgError, ValueError):
            return None
    return CalibrationResult(estimates, config, dict(calibrator.rates_hz), dict(calibrator.noise))


def estimate(streamed: StreamedLog) -> CalibrationResult:
    """Solve for every sensor from a streamed log."""
    try:
        with np.errstate(all="ignore"):
            estimates = streamed.calibrator.estimates()
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        # only data no IMU produces get here (the reader drops what it can recognise)
        raise InputError(f"{streamed.log}: the IMU data are numerically degenerate ({exc}); the log may hold damaged samples") from None
    return CalibrationResult(estimates, streamed.config, dict(streamed.calibrator.rates_hz), dict(streamed.calibrator.noise))


def export_extrinsics(
    document: Mapping[str, Any], fmt: str, parent: str | None = None, source: str = "<document>", T_base_parent: Transform | None = None, allow_not_ok: bool = False,
) -> dict[str, str]:
    """The text of one export format (:mod:`imucal_cli.exports`) from a calibrate document:
    ``{"main": ...}``, plus ``{"launch": ...}`` for the tf2 static publishers; relative to
    ``parent`` where given; sensors not ``ok`` only with ``allow_not_ok``."""
    from imucal_cli.exports import Extrinsics, export

    return export(Extrinsics.from_document(dict(document), source), fmt, parent, T_base_parent, allow_not_ok)


def evaluate(
    estimate: str | Path | Mapping[str, Any], truth: str | Path | Mapping[str, Any], max_rotation_deg: float | None = None,
    max_translation_m: float | None = None, allow_missing: bool = False,
) -> dict[str, Any]:
    """The SPEC's evaluate document of a calibrate output (or any document with ``sensors:
    NAME: T_base_lidar``) against a truth, each a file or the document itself (``run.document``);
    ``document["pass"]`` is the verdict."""
    from imucal_cli.pipeline import evaluate_document

    estimates, truths = load_transforms(estimate), load_transforms(truth)
    if not set(estimates) & set(truths):
        raise InputError(f"{estimate}: no sensor in common with {truth}")
    return evaluate_document(estimates, truths, max_rotation_deg, max_translation_m, allow_missing)


def write_report(out_dir: str | Path, run: LogCalibration) -> list[Path]:
    """The report's figures and ``report.html`` of a calibration into ``out_dir`` (needs
    matplotlib, ``imucal[report]``); returns the files written."""
    from imucal_cli.report import write_report as draw

    return draw(Path(out_dir), run.streamed.log, run.result, run.streamed, run.document)


def write_document(path: str | Path, document: Any) -> None:
    """Write a document (``run.document``, an evaluate or biases document) as YAML or JSON by
    the suffix of ``path``, atomically, as the commands' ``-o`` does."""
    from imucal_cli.documents import write_document as write

    write(path, document)


def load_transforms(path: str | Path | Mapping[str, Any], key: str = "T_base_lidar") -> dict[str, Transform]:
    """``key`` of every sensor of a calibrate output or truth (``sensors: NAME: key``), a file
    or the document itself; :class:`InputError` naming the file and the key path when one is
    missing or malformed."""
    from imucal_cli.documents import load_document
    from imucal_cli.errors import ConfigError

    document = path if isinstance(path, Mapping) else load_document(path)
    path = "<document>" if isinstance(path, Mapping) else path
    if not isinstance(document, dict) or not isinstance(document.get("sensors"), dict):
        raise InputError(f"{path}: expected a mapping with 'sensors'")
    out = {}
    for name, sensor in document["sensors"].items():
        if not isinstance(sensor, dict) or key not in sensor:
            raise InputError(f"{path}: sensors.{name}.{key}: missing")
        try:
            out[str(name)] = Transform.from_dict(sensor[key], str(path), f"sensors.{name}.{key}")
        except ConfigError as exc:
            raise InputError(str(exc)) from None
    return out
