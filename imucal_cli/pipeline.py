"""The one pipeline that ``calibrate``, ``--follow``, ``biases``, ``segments``, ``batch`` and
the Python API run: one read loop (:func:`read_log`, with the clock comparison) feeding a
streaming calibrator (or the bias trackers), the final reduction and its checks
(:func:`_finish`), the solve, and the document (:mod:`imucal_cli.documents`). Nothing here
prints; the CLI draws progress and writes the documents.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.config import Config, SensorConfig, load_config
from imucal_cli.core.biases import BiasTracker
from imucal_cli.core.calibrate import CalibrationOptions, SensorEstimate
from imucal_cli.core.grades import GRADES
from imucal_cli.core.streaming import BOOT_S, SensorSetup, StreamingCalibrator
from imucal_cli.errors import ImucalError, InputError
from imucal_cli.io.base import Loss
from imucal_cli.reading import ImuBatches, ReadStats
from imucal_cli.result import CalibrationResult
from imucal_cli.types import ImuStream


@dataclass(frozen=True)
class DriveStreams:
    """The IMU streams of one log: the base and one per configured sensor (by name)."""

    base: ImuStream
    sensors: Mapping[str, ImuStream]
    t0_ns: int  # first stamp of the log's IMU messages: the origin of report times

    def seconds(self, t_ns: int) -> float:
        return (t_ns - self.t0_ns) * 1e-9


def options_for(config: Config, sensor: SensorConfig) -> CalibrationOptions:
    return CalibrationOptions(
        resample_hz=config.calibration.resample_hz,
        max_time_offset_s=config.calibration.max_time_offset_s,
        window_s=config.segments.window_s,
        max_rotation_std_deg=config.segments.max_rotation_std_deg,
        translation_bound_m=sensor.translation_bound_m,
        rotation_bound_deg=sensor.rotation_bound_deg,
        gyro_bias_walk=np.radians(config.gyro_bias.process_noise_dps),
        gyro_bias_prior_std=np.radians(config.gyro_bias.initial_std_dps),
        consistency_alpha=config.calibration.consistency_alpha,
        # what no drive sees: the config's floor and the sensor IMU's alignment to its housing
        # (the base's turns the lever arm too: the solve carries it, core.uncertainty)
        rotation_floor_deg=float(
            np.hypot(sensor.rotation_floor_deg, np.degrees(GRADES[sensor.grade].housing_rad))
        ),
        translation_floor_m=sensor.translation_floor_m,
        sensor_grade=sensor.grade,
        base_grade=config.base.grade,
    )


def make_calibrator(
    config: Config, block_windows: int | None = None, reorder_s: float | None = None
) -> StreamingCalibrator:
    """A streaming calibrator for every sensor of the config; feed it ``"base"`` and sensor names
    (``block_windows=1``: every window reduced as soon as the data cover it, for live use)."""
    extra: dict[str, Any] = {} if block_windows is None else {"block_windows": block_windows}
    if reorder_s is not None:
        extra["reorder_s"] = reorder_s
    return StreamingCalibrator(
        [
            SensorSetup(
                s.name,
                s.prior_T_base_imu,
                options_for(config, s),
                s.gyro_units,
                s.accel_units,
                s.imu_topic,
                f"sensors.{s.name}",
            )
            for s in config.sensors
        ],
        base_name="base",
        base_units=(config.base.gyro_units, config.base.accel_units),
        base_label=(config.base.topic, "base"),
        base_pose=config.base.T_base_imu,
        **extra,
    )


#: What driving supplies information about each axis (the lever arm enters through
#: ``([w]x^2 + [dw]x) t``: x and y through the yaw rate and its changes, z through roll and pitch).
MANOEUVRES = {
    "rotation x (roll)": "roll motion: crossfall, speed bumps, turns taken briskly",
    "rotation y (pitch)": "pitch motion: braking and accelerating, speed bumps",
    "rotation z (yaw)": "turns in both directions",
    "translation x": "turns in both directions and changes of turn rate (slalom, roundabouts)",
    "translation y": "turns in both directions and changes of turn rate (slalom, roundabouts)",
    "translation z": "roll and pitch motion: speed bumps, crossfall, braking and accelerating",
}


def every_axis_missing() -> list[str]:
    """Nothing determined yet: every axis, with the driving that supplies it."""
    return [f"{axis}: {what}" for axis, what in MANOEUVRES.items()]


def missing_axes(estimate: SensorEstimate, stop: Any) -> list[str]:
    """The axes whose std is not yet within the ``stop:`` targets, each with the driving that
    supplies it: from the estimate's statistical std (what more driving shrinks)."""
    if estimate.statistical_covariance is None:
        return every_axis_missing()
    # the statistical std: what more driving shrinks (the total adds what it cannot)
    rotation = estimate.statistical_rotation_std_deg
    translation = estimate.statistical_translation_std_m
    assert rotation is not None and translation is not None
    names = list(MANOEUVRES)
    out = [
        f"{names[k]}: {MANOEUVRES[names[k]]} (std {rotation[k]:.3g} deg, target "
        f"{stop.max_rotation_std_deg:g})"
        for k in range(3)
        if rotation[k] > stop.max_rotation_std_deg
    ]
    out += [
        f"{names[3 + k]}: {MANOEUVRES[names[3 + k]]} (std {translation[k]:.3g} m, target "
        f"{stop.max_translation_std_m:g})"
        for k in range(3)
        if translation[k] > stop.max_translation_std_m or not estimate.translation_observable[k]
    ]
    return out


def converged(result: CalibrationResult) -> bool:
    """Every sensor ``ok`` and within the config's ``stop:`` targets."""
    return all(
        e.status == "ok" and not missing_axes(e, result.config.stop)
        for e in result.estimates.values()
    )


def feed(calibrator: StreamingCalibrator, streams: DriveStreams, block_s: float = 10.0) -> None:
    """Feed in-memory streams to a calibrator in time order, ``block_s`` at a time."""
    all_streams = {"base": streams.base, **streams.sensors}
    start = min(int(s.t_ns[0]) for s in all_streams.values())
    end = max(int(s.t_ns[-1]) for s in all_streams.values())
    step = int(block_s * 1e9)
    cursors = dict.fromkeys(all_streams, 0)
    for edge in range(start + step, end + 2 * step, step):
        for name, stream in all_streams.items():
            stop = int(np.searchsorted(stream.t_ns, edge, side="left"))
            a = cursors[name]
            if stop > a:
                calibrator.add(name, stream.t_ns[a:stop], stream.gyro[a:stop], stream.accel[a:stop])
                cursors[name] = stop


def bias_trackers(config: Config) -> dict[str, BiasTracker]:
    """A :class:`BiasTracker` per IMU (``base`` first, then each sensor), as the config says."""
    rest, gyro = config.rest, config.gyro_bias
    args = (
        rest.accel_tolerance_mps2,
        rest.gyro_tolerance_radps,
        rest.min_duration_s,
        np.radians(gyro.process_noise_dps),
        np.radians(gyro.initial_std_dps),
    )
    return {name: BiasTracker(*args) for name in ["base", *(s.name for s in config.sensors)]}


def run_calibrate(streams: DriveStreams, config: Config) -> CalibrationResult:
    """Calibrate every sensor from in-memory streams."""
    calibrator = make_calibrator(config)
    feed(calibrator, streams)
    estimates = calibrator.finish()
    return CalibrationResult(estimates, config, dict(calibrator.rates_hz), dict(calibrator.noise))


# --------------------------------------------------------------------------- one run over a log

#: Follow mode: how far out of order a recording's stamps may arrive (s). A recorder appends in
#: receive order, so a window waits less for stragglers than in a file (0.5 s), and its
#: estimate comes sooner.
FOLLOW_REORDER_S = 0.2
#: Spread of receive latencies allowed between topics when their clocks are compared (s).
CLOCK_COMPARE_SLACK_S = 0.05
#: Samples at the start of each topic whose ``stamp - log_time`` gives its clock's offset.
CLOCK_COMPARE_SAMPLES = 200


def lost_summary(losses: Sequence[Loss]) -> str:
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

    def add(self, topic: str, stamps: np.ndarray, log_times: np.ndarray, topics: list[str]) -> None:
        if topic not in self.offsets and len(stamps):
            first = slice(0, CLOCK_COMPARE_SAMPLES)  # a clock that jumps later is a jump
            offset = np.median((stamps[first] - log_times[first]).astype(np.float64))
            self.offsets[topic] = float(offset) * 1e-9
        if self.checked or not all(t in self.offsets for t in topics):
            return
        self.checked = True
        base = self.offsets[self.base_topic]
        for other in topics:
            difference = self.offsets[other] - base
            if abs(difference) > self.max_offset_s + CLOCK_COMPARE_SLACK_S:
                raise InputError(
                    f"{self.log} [{other}]: stamps are {difference:+.3f} s from the base IMU's "
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
        return {
            topic: stats.to_dict()
            | {"duplicates": stats.duplicates + self.duplicates.get(topic, 0)}
            for topic, stats in self.stats.items()
        }


Sink = Callable[[str, np.ndarray, np.ndarray, np.ndarray], object]


def blas_threads(workers: int = 1) -> Any:
    """BLAS on ``workers`` threads while the pipeline runs, as it was after: its products are
    of a window's few dozen columns, where OpenBLAS's threads cost more than they share (1 h
    log: 0.52 CPU-s of 3.9 spent in them, to no gain in wall time). The caller's setting is
    back when the block ends (``threadpoolctl``)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(workers, user_api="blas")


def read_log(
    reader: ImuBatches,
    config: Config,
    sink: Sink,
    clocks: bool = True,
    progress: Callable[[int, int], None] | None = None,
    after: Callable[[], None] | None = None,
    clipped: Callable[[str, np.ndarray], None] | None = None,
) -> int | None:
    """The one read loop: every IMU batch of ``reader`` to ``sink(name, stamps, gyro,
    accel)`` (``name``: "base" or the sensor's), the clocks compared (``clocks``),
    ``progress(messages read, messages in the log)`` and ``after()`` after each batch, and
    before it the stamps of the clipped samples reading dropped to ``clipped(name, stamps)``.
    Returns the first stamp (ns), None where no message was read."""
    names = config.imu_names()
    check = _ClockCheck(reader.path, config.base.topic, config.calibration.max_time_offset_s)
    topics, t0_ns, count = list(names), None, 0
    with blas_threads():
        for topic, stamps, log_times, gyro, accel in reader:
            if clocks:
                check.add(topic, stamps, log_times, topics)
            if len(stamps):
                first = int(stamps.min())
                t0_ns = first if t0_ns is None else min(t0_ns, first)
            dropped = reader.take_clipped(topic)  # taken always: kept, they would pile up
            if clipped is not None:
                clipped(names[topic], dropped)
            sink(names[topic], stamps, gyro, accel)
            count += len(stamps)
            if progress is not None:
                progress(count, sum(reader.expected.values()))
            if after is not None:
                after()
    return t0_ns


def _finish(
    reader: ImuBatches,
    calibrator: StreamingCalibrator,
    t0_ns: int | None,
    config: Config,
) -> StreamedLog:
    """What is left reduced, once the reading has ended; the topics that gave too little
    data named."""
    log, lost = reader.path, lost_summary(reader.losses)
    for topic, stats in reader.stats.items():
        if stats.usable() < 10:
            raise InputError(
                f"{log} [{topic}]: too little data: {stats.usable()} usable messages{lost}"
            )
    if calibrator.t_ref_ns is None or t0_ns is None:
        raise InputError(f"{log}: too little data: an IMU topic has no messages{lost}")
    try:
        calibrator.process(final=True)
    except ImucalError as exc:
        raise InputError(f"{log}: {str(exc).removeprefix(str(log) + ': ')}{lost}") from None
    return _streamed(reader, calibrator, t0_ns, config)


def _streamed(
    reader: ImuBatches,
    calibrator: StreamingCalibrator,
    t0_ns: int | None,
    config: Config,
) -> StreamedLog:
    """What the reader and the calibrator found, as one :class:`StreamedLog`."""
    duplicates = {topic: calibrator.duplicates(name) for topic, name in config.imu_names().items()}
    return StreamedLog(
        reader.path,
        config,
        calibrator,
        int(t0_ns or 0),
        reader.stats,
        duplicates,
        reader.losses,
        reader.format_name,
    )


def stream_log(
    log: str | Path, config: Config, progress: Callable[[int, int], None] | None = None
) -> StreamedLog:
    """Stream the configured IMU topics of ``log`` through a calibrator, memory flat in the
    log's length: windows reduced, nothing solved yet."""
    reader = ImuBatches(Path(log), config.imu_names())
    calibrator = make_calibrator(config)
    t0_ns = read_log(
        reader, config, calibrator.add, progress=progress, clipped=calibrator.add_clipped
    )
    return _finish(reader, calibrator, t0_ns, config)


def stream_biases(
    log: str | Path, config: Config, progress: Callable[[int, int], None] | None = None
) -> dict[str, Any]:
    """The SPEC's ``biases`` document of ``log``: every configured IMU streamed through a
    :class:`~imucal_cli.core.biases.BiasTracker`, memory flat in the log's length."""
    from imucal_cli.outputs import biases_document

    names = config.imu_names()
    trackers = bias_trackers(config)
    reader = ImuBatches(Path(log), names)
    read_log(
        reader,
        config,
        lambda name, t, w, f: trackers[name].add(t, w, f),
        clocks=False,
        progress=progress,
    )
    empty = [topic for topic, name in names.items() if trackers[name].first_ns is None]
    if empty:
        raise InputError(
            f"{log} [{empty[0]}]: too little data: no usable message{lost_summary(reader.losses)}"
        )
    reports = {name: tracker.report() for name, tracker in trackers.items()}
    counts = {topic: stats.to_dict() for topic, stats in reader.stats.items()}
    return biases_document(config, reports, reader.losses, counts)


@dataclass
class LogCalibration:
    """The outcome of :func:`calibrate_log` and :func:`follow_log`."""

    result: CalibrationResult  # estimates per sensor; ``result.T_base_lidar(name)``
    document: dict[str, Any]  # the SPEC's calibrate document (what ``imucal calibrate -o`` writes)
    streamed: StreamedLog  # what reading found: counts per topic, losses


def calibrate_log(
    log: str | Path, config: Config | str | Path, progress: Callable[[int, int], None] | None = None
) -> LogCalibration:
    """Calibrate every sensor of ``config`` from the IMU topics of ``log`` (MCAP, rosbag2 or
    ROS 1 bag). ``config`` is a :class:`Config` or the path of its YAML file; ``progress`` is
    called with (messages read, messages in the log) as reading goes."""
    if not isinstance(config, Config):
        config = load_config(config, log)  # what it leaves out, from the log's /tf_static
    streamed = stream_log(log, config, progress)
    return _calibration(streamed, estimate(streamed))


def _calibration(streamed: StreamedLog, result: CalibrationResult) -> LogCalibration:
    from imucal_cli.outputs import calibration_document

    document = calibration_document(result, str(streamed.log), streamed.losses, streamed.counts())
    return LogCalibration(result, document, streamed)


def follow_log(
    log: str | Path,
    config: Config,
    on_update: Callable[[CalibrationResult, int], None] | None = None,
    stop: Callable[[], bool] = lambda: False,
    until_converged: bool = False,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[LogCalibration, bool, bool]:
    """Follow a log that is still being written (an MCAP file, or a rosbag2 folder recording
    to mcap or sqlite3 storage): the estimate after every window, ``on_update(result,
    windows)``, until the recording ends, ``stop()`` says so, or (``until_converged``) every
    sensor is within the config's ``stop:`` targets. The read loop, its checks and the final
    reduction are :func:`calibrate_log`'s. Returns the last calibration (its document with each
    sensor's ``missing`` axes and ``converged``), whether it converged, and whether a Ctrl-C
    ended it (the estimate so far is returned all the same). Until the first estimate,
    ``on_progress`` is told at most every :data:`PROGRESS_S` what each sensor has and waits for
    (:func:`waiting`)."""
    calibrator = make_calibrator(config, block_windows=1, reorder_s=FOLLOW_REORDER_S)
    done = [False]
    reader = ImuBatches(Path(log), config.imu_names(), follow=lambda: done[0] or stop())
    state: dict[str, Any] = {"windows": 0, "result": None, "told": -np.inf}
    samples = dict.fromkeys(["base", *(s.name for s in config.sensors)], 0)

    def sink(name: str, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        samples[name] += len(t)
        calibrator.add(name, t, gyro, accel)

    def talk() -> None:
        now = time.monotonic()
        if on_progress is None or state["result"] is not None or now - state["told"] < PROGRESS_S:
            return
        state["told"] = now
        on_progress(waiting(calibrator, config, samples))

    def update() -> None:
        reduced = min(len(w) for w in calibrator.windows.values())
        if reduced <= state["windows"]:
            return
        state["windows"] = reduced
        result = _estimate_now(calibrator, config)
        if result is not None:
            state["result"] = result
            if on_update is not None:
                on_update(result, reduced)
            done[0] = done[0] or (until_converged and converged(result))

    def after() -> None:
        update()
        talk()

    t0_ns, interrupted = None, False
    try:
        t0_ns = read_log(reader, config, sink, after=after, clipped=calibrator.add_clipped)
    except KeyboardInterrupt:
        interrupted = True
        t0_ns = _first_stamp(calibrator)
    if done[0] and not stop():  # converged: the estimate that did
        streamed = _streamed(reader, calibrator, t0_ns, config)
        result = state["result"]
    else:  # the recording ended, time is up, or a Ctrl-C: what is buffered, reduced
        try:
            streamed = _finish(reader, calibrator, t0_ns, config)
        except ImucalError:
            if not interrupted or state["result"] is None:  # after a Ctrl-C: the estimate so far
                raise
            streamed = _streamed(reader, calibrator, t0_ns, config)
        result = _estimate_now(calibrator, config) or state["result"]
    if result is None:
        raise InputError(
            f"{log}: too little data to estimate anything yet{lost_summary(reader.losses)}"
        )
    run = _calibration(streamed, result)
    good = converged(result)
    for name, sensor in result.estimates.items():  # what each sensor still lacks of the targets
        run.document["sensors"][name]["missing"] = missing_axes(sensor, config.stop)
    run.document["converged"] = good
    return run, good, interrupted


#: Follow mode: how often the state before the first estimate is told (s of wall time).
PROGRESS_S = 1.0


def waiting(
    calibrator: StreamingCalibrator, config: Config, samples: Mapping[str, int]
) -> dict[str, Any]:
    """Per sensor before its first estimate: samples seen, windows reduced, what it waits for
    and the axes it lacks (all of them), in words that say what driving supplies them."""
    booted = bool(calibrator.tau0)
    out: dict[str, Any] = {"base_samples": samples.get("base", 0), "sensors": {}}
    for sensor in config.sensors:
        windows = len(calibrator.windows.get(sensor.name, []))
        if not booted:
            what = (
                "motion that places the clock offsets: turns and changes of speed (the start "
                f"reads the first {BOOT_S:g} s of driving, and waits for such motion)"
            )
        elif not windows:
            what = f"the first window: {config.segments.window_s:g} s of data after the start"
        else:
            what = "the first estimate"
        out["sensors"][sensor.name] = {
            "status": "waiting",
            "samples": samples.get(sensor.name, 0),
            "windows": windows,
            "waiting_for": what,
            "missing": every_axis_missing(),
        }
    return out


def _first_stamp(calibrator: StreamingCalibrator) -> int | None:
    firsts = [b.first_ns for b in calibrator.buffers.values() if b.first_ns is not None]
    return min(firsts) if firsts else None


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
        with np.errstate(all="ignore"), blas_threads():
            estimates = streamed.calibrator.estimates()
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        # only data no IMU produces get here (the reader drops what it can recognise)
        raise InputError(
            f"{streamed.log}: the IMU data are numerically degenerate ({exc}); the log may hold "
            "damaged samples"
        ) from None
    return CalibrationResult(
        estimates,
        streamed.config,
        dict(streamed.calibrator.rates_hz),
        dict(streamed.calibrator.noise),
    )
