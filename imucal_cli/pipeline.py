"""The one pipeline that ``calibrate``, ``--follow``, ``biases``, ``segments``, ``batch`` and
the Python API run, in one process: one read loop (:func:`read_log`, with the clock
comparison) feeding a streaming calibrator (or the bias trackers), the final reduction and its
checks, the solve, and one :class:`~imucal_cli.calibration.Calibration`. Nothing here prints;
the CLI draws progress and writes the documents.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.calibration import Calibration, Reading
from imucal_cli.config import Config, SensorConfig
from imucal_cli.core.biases import BaseGyroBias, BiasTracker
from imucal_cli.core.calibrate import CalibrationOptions
from imucal_cli.core.estimates import estimates as solved_estimates
from imucal_cli.core.grades import GRADES
from imucal_cli.core.status import every_axis_missing
from imucal_cli.core.streaming import BOOT_RETRY_S, SensorSetup, StreamingCalibrator
from imucal_cli.errors import ImucalError, InputError
from imucal_cli.io.base import Loss
from imucal_cli.reading import ImuBatches
from imucal_cli.types import DriveStreams


def options_for(config: Config, sensor: SensorConfig) -> CalibrationOptions:
    return CalibrationOptions(
        resample_hz=config.calibration.resample_hz,
        max_time_offset_s=config.calibration.max_time_offset_s,
        max_clock_drift_ppm=config.calibration.max_clock_drift_ppm,
        window_s=config.segments.window_s,
        epoch_s=config.calibration.epoch_s,
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
    config: Config,
    block_windows: int | None = None,
    reorder_s: float | None = None,
    keep_rows: bool = False,
) -> StreamingCalibrator:
    """A streaming calibrator for every sensor of the config; feed it ``"base"`` and sensor names
    (``block_windows=1``: every window reduced as soon as the data cover it, for live use;
    ``keep_rows``: every window's observability kept, as ``segments`` lists it)."""
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
        keep_rows=keep_rows,
        base_bias=BaseGyroBias(
            config.rest.accel_tolerance_mps2,
            config.rest.gyro_tolerance_radps,
            config.rest.min_duration_s,
        ),
        **extra,
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


def calibrate_streams(streams: DriveStreams, config: Config) -> Calibration:
    """Calibrate every sensor from streams in memory (a simulated drive, say)."""
    calibrator = make_calibrator(config)
    feed(calibrator, streams)
    calibrator.finish()
    return _solved(calibrator, config, streams.t0_ns, None)


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


def blas_threads(workers: int = 1) -> Any:
    """BLAS on ``workers`` threads while the pipeline runs, as it was after: its products are
    of a window's few dozen columns, where OpenBLAS's threads cost more than they share (1 h
    log: 0.52 CPU-s of 3.9 spent in them, to no gain in wall time). The caller's setting is
    back when the block ends (``threadpoolctl``)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(workers, user_api="blas")


Progress = Callable[[int, int], None]
Sink = Callable[[str, np.ndarray, np.ndarray, np.ndarray], object]


def read_log(
    reader: ImuBatches,
    config: Config,
    sink: Sink,
    clocks: bool = True,
    progress: Progress | None = None,
    after: Callable[[], None] | None = None,
    clipped: Callable[[str, np.ndarray], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> int | None:
    """The one read loop: every IMU batch of ``reader`` to ``sink(name, stamps, gyro,
    accel)`` (``name``: "base" or the sensor's), the clocks compared (``clocks``),
    ``progress(messages read, messages in the log)`` and ``after()`` after each batch, and
    before it the stamps of the clipped samples reading dropped to ``clipped(name, stamps)``;
    it ends early where ``stop()`` says so after a batch. Returns the first stamp (ns), None
    where no message was read."""
    names = config.imu_names()
    check = _ClockCheck(reader.path, config.base.topic, config.calibration.max_time_offset_s)
    topics, t0_ns, count = list(names), None, 0
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
        if stop is not None and stop():
            break
    return t0_ns


def _reading(reader: ImuBatches, calibrator: StreamingCalibrator, config: Config) -> Reading:
    """What the reader and the calibrator found."""
    counts = {
        topic: stats.to_dict()
        | {"duplicates": stats.duplicates + calibrator.duplicates(config.imu_names()[topic])}
        for topic, stats in reader.stats.items()
    }
    return Reading(reader.path, reader.format_name, counts, list(reader.losses))


def _reduce_rest(reader: ImuBatches, calibrator: StreamingCalibrator, t0_ns: int | None) -> None:
    """What is left reduced, once the reading has ended; the topics that gave too little data
    named."""
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


def _solved(
    calibrator: StreamingCalibrator,
    config: Config,
    t0_ns: int | None,
    reading: Reading | None,
    followed: bool = False,
) -> Calibration:
    """Every sensor solved from the windows reduced so far."""
    try:
        with np.errstate(all="ignore"):
            estimates = solved_estimates(calibrator)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        # only data no IMU produces get here (the reader drops what it can recognise)
        log = reading.log if reading is not None else "the streams"
        raise InputError(
            f"{log}: the IMU data are numerically degenerate ({exc}); the log may hold "
            "damaged samples"
        ) from None
    return _calibration(calibrator, config, t0_ns, reading, estimates, followed)


def _calibration(
    calibrator: StreamingCalibrator,
    config: Config,
    t0_ns: int | None,
    reading: Reading | None,
    estimates: dict[str, Any],
    followed: bool = False,
) -> Calibration:
    windows = {name: calibrator.window_infos(name) for name in calibrator.sensors}
    return Calibration(
        config,
        estimates,
        windows,
        int(t0_ns or 0),
        int(calibrator.t_ref_ns or 0),
        dict(calibrator.tau0),
        dict(calibrator.rates_hz),
        dict(calibrator.noise),
        reading,
        followed,
    )


def _streamed(
    log: str | Path,
    config: Config,
    progress: Progress | None,
    on_window: Callable[[int], None] | None,
    stop: Callable[[], bool] | None,
    keep_rows: bool = False,
) -> tuple[StreamingCalibrator, int | None, Reading]:
    """The log's IMU topics through a calibrator, every window reduced, nothing solved."""
    reader = ImuBatches(Path(log), config.imu_names())
    calibrator = make_calibrator(config, keep_rows=keep_rows)
    told = [0]

    def after() -> None:
        reduced = calibrator.reduced
        if on_window is not None and reduced > told[0]:
            told[0] = reduced
            on_window(reduced)

    t0_ns = read_log(
        reader,
        config,
        calibrator.add,
        progress=progress,
        after=after,
        clipped=calibrator.add_clipped,
        stop=stop,
    )
    _reduce_rest(reader, calibrator, t0_ns)
    return calibrator, t0_ns, _reading(reader, calibrator, config)


def calibrate(
    log: str | Path,
    config: Config,
    *,
    progress: Progress | None = None,
    on_window: Callable[[int], None] | None = None,
    stop: Callable[[], bool] | None = None,
    workers: int = 1,
) -> Calibration:
    """Calibrate every sensor of ``config`` from the IMU topics of ``log``, memory flat in the
    log's length. ``progress(messages read, messages in the log)`` as reading goes,
    ``on_window(windows reduced)`` as each block of windows is, and where ``stop()`` says so
    the reading ends there and the calibration is of what was read. ``workers``: the threads
    the linear algebra may take (BLAS; one, as a fleet that runs a log per core wants)."""
    with blas_threads(workers):
        calibrator, t0_ns, reading = _streamed(log, config, progress, on_window, stop)
        return _solved(calibrator, config, t0_ns, reading)


def segments(
    log: str | Path,
    config: Config,
    *,
    progress: Progress | None = None,
    on_window: Callable[[int], None] | None = None,
    stop: Callable[[], bool] | None = None,
    workers: int = 1,
) -> Calibration:
    """:func:`calibrate` without the solve: every window's observability
    (:meth:`Calibration.segments_document`), no estimate."""
    with blas_threads(workers):
        calibrator, t0_ns, reading = _streamed(
            log, config, progress, on_window, stop, keep_rows=True
        )
        return _calibration(calibrator, config, t0_ns, reading, {})


def biases(
    log: str | Path,
    config: Config,
    *,
    progress: Progress | None = None,
    stop: Callable[[], bool] | None = None,
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
        stop=stop,
    )
    empty = [topic for topic, name in names.items() if trackers[name].first_ns is None]
    if empty:
        raise InputError(
            f"{log} [{empty[0]}]: too little data: no usable message{lost_summary(reader.losses)}"
        )
    reports = {name: tracker.report() for name, tracker in trackers.items()}
    counts = {topic: stats.to_dict() for topic, stats in reader.stats.items()}
    return biases_document(config, reports, reader.losses, counts)


class _Follower:
    """What :func:`follow` keeps: the calibrator, the samples seen, the latest calibration,
    and when it last told the state before the first estimate."""

    def __init__(
        self,
        config: Config,
        on_window: Callable[[Calibration, int], None] | None,
        on_waiting: Callable[[dict[str, Any]], None] | None,
        stop: Callable[[], bool],
        until_converged: bool,
    ) -> None:
        self.config, self.on_window, self.on_waiting = config, on_window, on_waiting
        self.stop, self.until_converged = stop, until_converged
        self.calibrator = make_calibrator(config, reorder_s=FOLLOW_REORDER_S)
        self.samples = dict.fromkeys(["base", *(s.name for s in config.sensors)], 0)
        self.windows, self.told, self.done = 0, -np.inf, False
        self.latest: Calibration | None = None

    def sink(self, name: str, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.samples[name] += len(t)
        self.calibrator.add(name, t, gyro, accel)

    def talk(self) -> None:
        """Until the first estimate: what each sensor has and waits for, at most every
        :data:`PROGRESS_S` (nothing before the first data)."""
        now = time.monotonic()
        if self.on_waiting is None or self.latest is not None or now - self.told < PROGRESS_S:
            return
        if any(self.samples.values()):
            self.told = now
            self.on_waiting(waiting(self.calibrator, self.config, self.samples))

    def caught_up(self) -> bool:
        """Asked by the reader whenever it waits for the recording: the windows covered so far
        reduced and solved; whether to stop."""
        if self.calibrator.t_ref_ns is not None:
            with np.errstate(all="ignore"):
                self.calibrator.process(whole_blocks=False)
        reduced = self.calibrator.reduced
        if reduced > self.windows:
            self.windows = reduced
            latest = _estimate_now(self.calibrator, self.config)
            if latest is not None:
                self.latest = latest
                if self.on_window is not None:
                    self.on_window(latest, reduced)
                self.done = self.until_converged and latest.converged
        self.talk()
        return self.done or self.stop()


def follow(
    log: str | Path,
    config: Config,
    *,
    on_window: Callable[[Calibration, int], None] | None = None,
    on_waiting: Callable[[dict[str, Any]], None] | None = None,
    stop: Callable[[], bool] = lambda: False,
    until_converged: bool = False,
    workers: int = 1,
) -> tuple[Calibration, bool]:
    """Follow a log that is still being written (an MCAP file, or a rosbag2 folder recording
    to mcap or sqlite3 storage) until the recording ends, ``stop()`` says so, or
    (``until_converged``) every sensor is within the config's ``stop:`` targets. The read loop,
    its checks, the windows and the final reduction are :func:`calibrate`'s: where the reader
    waits for the recording, the windows it covers are reduced and solved, ``on_window(
    calibration, windows)``; a finished file gives :func:`calibrate`'s calibration. Until the
    first estimate, ``on_waiting`` is told at most every :data:`PROGRESS_S` what each sensor
    has and waits for (:func:`waiting`). Returns the last calibration (its documents with each
    sensor's ``missing`` axes and ``converged``) and whether a Ctrl-C ended it (the estimate
    so far is returned all the same)."""
    state = _Follower(config, on_window, on_waiting, stop, until_converged)
    calibrator = state.calibrator
    reader = ImuBatches(Path(log), config.imu_names(), follow=state.caught_up)
    t0_ns, interrupted = None, False
    with blas_threads(workers):
        try:
            t0_ns = read_log(
                reader, config, state.sink, after=state.talk, clipped=calibrator.add_clipped
            )
        except KeyboardInterrupt:
            interrupted, t0_ns = True, _first_stamp(calibrator)
        latest = state.latest
        if not (state.done and not stop()):  # not converged: what is buffered, reduced
            try:
                _reduce_rest(reader, calibrator, t0_ns)
            except ImucalError:
                if not interrupted or latest is None:  # after a Ctrl-C: the estimate so far
                    raise
            latest = _estimate_now(calibrator, config) or latest
    if latest is None:
        raise InputError(
            f"{log}: too little data to estimate anything yet{lost_summary(reader.losses)}"
        )
    reading = _reading(reader, calibrator, config)
    return replace(latest, t0_ns=int(t0_ns or 0), reading=reading), interrupted


#: Follow mode: how often the state before the first estimate is told (s of wall time).
PROGRESS_S = 1.0


def waiting(
    calibrator: StreamingCalibrator, config: Config, samples: Mapping[str, int]
) -> dict[str, Any]:
    """Per sensor before its first estimate: samples seen, windows reduced, what it waits for
    and the axes it lacks (all of them), in words that say what driving supplies them."""
    booted = bool(calibrator.tau0)
    read_s, needs_s, tried = calibrator.starting()
    out: dict[str, Any] = {"base_samples": samples.get("base", 0), "sensors": {}}
    for sensor in config.sensors:
        windows = len(calibrator.windows.get(sensor.name, []))
        if not booted and not tried:  # (data, not motion: the start reads its first seconds)
            what = f"data: starting, {read_s:.0f} of {needs_s:.0f} s read"
        elif not booted:
            what = (
                f"motion that places the clock offsets: turns and changes of speed (the first "
                f"{needs_s - BOOT_RETRY_S:.0f} s held too little; tried again every "
                f"{BOOT_RETRY_S:g} s)"
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


def _estimate_now(calibrator: StreamingCalibrator, config: Config) -> Calibration | None:
    """The estimate from the windows so far, or None before the calibrator has booted."""
    if not calibrator.tau0:
        return None
    with np.errstate(all="ignore"):
        try:
            estimates = solved_estimates(calibrator)
        except (ImucalError, np.linalg.LinAlgError, ValueError):
            return None
    return _calibration(
        calibrator, config, _first_stamp(calibrator), None, estimates, followed=True
    )


#: Follow mode without a deadline: how long a log that does not exist yet is waited for (s).
WAIT_FOR_LOG_S = 30.0


def wait_for_log(log: Path, limit: float, waiting: Callable[[], None]) -> None:
    """Follow mode started beside a recorder: wait until ``limit`` (monotonic s) for the log
    to appear (a rosbag2 folder: its storage file), ``waiting()`` told once if it must."""

    def present() -> bool:
        if log.is_dir():
            return any(log.glob("*.mcap")) or any(log.glob("*.db3"))
        return log.exists()

    if present():
        return
    waiting()
    while not present():
        if time.monotonic() > limit:
            raise InputError(f"{log}: no such file or directory (waited for it to be created)")
        time.sleep(0.1)


def recording_config(path: Path, log: Path, limit: float, urdf: Path | None) -> tuple[Config, str]:
    """Follow mode's config, and a note for the user ("" for none). One that leaves transforms
    out is read against the recording's /tf_static and the URDF (``urdf``, else its
    /robot_description) as soon as they hold them and the IMUs' first messages (until
    ``limit``, monotonic s); an error in the URDF itself is said at once. A base pose left out
    is taken from the recording where it reads now, else the config's default (said)."""
    from imucal_cli.frames import MAX_URDF_BYTES, FrameTree, read_urdf
    from imucal_cli.priors import config_alone, init_marks, load_config_for

    config, partial = config_alone(path)
    if config is not None and not partial and not init_marks(path):
        return config, ""
    if config is not None and not partial:  # (what init took from the tree: still the tree's?)
        try:
            return load_config_for(path, log, urdf), ""
        except ImucalError:
            return config, ""
    if config is not None:  # the base IMU's pose alone left out: the recording's, where it reads
        try:
            return load_config_for(path, log, urdf), ""
        except ImucalError as exc:
            why = f"no base.T_base_imu from the recording yet ({exc})"
            return config, f"{log}: {why}: the config's default is used"
    if urdf is not None:
        from imucal_cli.documents import read_capped

        text = read_capped(urdf, MAX_URDF_BYTES, "a URDF").decode("utf-8", errors="replace")
        read_urdf(text, FrameTree(), str(urdf))  # (not a URDF: said now, not at --timeout)
    while True:
        try:
            return load_config_for(path, log, urdf), ""
        except ImucalError:
            if time.monotonic() > limit:
                raise
            time.sleep(0.5)
