"""Streaming calibration: memory flat in the log's length, an estimate after every window.

IMU samples are fed as they are read (:meth:`StreamingCalibrator.add`). Every window of
``window_s`` that all IMUs cover is conditioned once (cubic-spline resampling onto the grid and
the common zero-phase low-pass of :mod:`imucal_cli.core.signals`, computed on the window plus
:data:`PAD_S` of padding on each side, which reproduces a whole-log filter to round-off), its
observability is analysed (eqs. 18-19), and it is reduced to the second moments of the data
vectors of :mod:`imucal_cli.core.model` (:mod:`imucal_cli.core.moments`), the sensor resampled
at ``t + tau0`` (``tau0`` from the cross-correlation of ``|w|`` over the first minute). The raw
samples are dropped once a window is reduced; what is kept per window and sensor is two small
matrices, and :func:`imucal_cli.core.estimates.estimates` solves from them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from imucal_cli.core.biases import BaseGyroBias
from imucal_cli.core.boot import Rig, SensorUnits, boot
from imucal_cli.core.calibrate import CalibrationOptions, bias_model
from imucal_cli.core.checks import Check
from imucal_cli.core.clock import GROUP_WINDOWS, ClockTrack, Offset, constant
from imucal_cli.core.moments import (
    MIN_SPAN_SAMPLES,
    WindowMoments,
    assemble_moments,
    merged,
    reduce_block,
    unused_window,
    used,
)
from imucal_cli.core.segments import WindowInfo, WindowRows, window_infos_from_moments
from imucal_cli.core.signals import (
    Lowpass,
    Saturation,
    TooLittleData,
)
from imucal_cli.core.timeline import EpochCache, epoch_of
from imucal_cli.core.timing import TimeOffset
from imucal_cli.types import Transform

#: Padding on each side of a window for the spline and the low-pass (s). The filter's impulse
#: response has decayed by far more than double precision within it.
PAD_S = 2.0
#: Seconds of data used to find each sensor's clock offset before windows are reduced.
BOOT_S = 60.0
#: Longest wait for enough motion to find the clock offset (s).
MAX_BOOT_S = 600.0
#: While waiting for that motion, the boot is tried again after this much more data (s).
BOOT_RETRY_S = 10.0
#: Stamps may arrive this much out of order (s): windows wait for it.
REORDER_S = 0.5
#: Windows conditioned together (one spline and one filter pass per IMU and block).
BLOCK_WINDOWS = 6
#: An IMU with no sample for this long (s) while another goes on has stopped (a driver that
#: died, a topic not recorded): the others' windows go on without it, its own are not used.
STOPPED_S = 30.0
#: Windows whose observability is computed together (bounds scratch memory).
INFO_CHUNK = 128
#: The newest windows of each sensor are kept as they were reduced (a move of the mount, a
#: step of its clock and the last epochs are seen at full resolution)...
FULL_WINDOWS = 180
#: ... and at most this many in all (windows, or older windows merged: :func:`~.moments.merged`,
#: the shortest neighbours of one epoch first, then of neighbouring epochs): what a sensor
#: keeps is bounded however long the log (about an hour of 10 s windows).
MAX_UNITS = 400


@dataclass(frozen=True)
class SensorSetup:
    name: str
    prior_T_base_imu: Transform
    options: CalibrationOptions
    gyro_units: str = "auto"  # auto | radps | dps
    accel_units: str = "auto"  # auto | mps2 | g
    topic: str = ""  # where its samples come from, and its config's key path: for messages
    key: str = ""


@dataclass
class _Buffer:
    """Raw samples of one IMU still needed: stamps (ns) and ``[gyro, accel]`` side by side
    (n, 6)."""

    t_ns: list[np.ndarray] = field(default_factory=list)
    both: list[np.ndarray] = field(default_factory=list)
    first_ns: int | None = None
    last_ns: int | None = None
    duplicates: int = 0
    sorted: bool = True  # as cleaned() left it: one array, strictly increasing

    def append(self, t_ns: np.ndarray, both: np.ndarray) -> None:
        self.t_ns.append(t_ns)
        self.both.append(both)
        self.sorted = False

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self.t_ns) > 1:
            self.t_ns = [np.concatenate(self.t_ns)]
            self.both = [np.concatenate(self.both)]
        if not self.t_ns:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 6))
        return self.t_ns[0], self.both[0]

    def cleaned(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted, duplicates removed (and counted), kept so for the next call."""
        t, both = self.arrays()
        t, both, removed = _clean(t, both)
        self.t_ns, self.both = [t], [both]
        self.duplicates += removed
        self.sorted = True
        return t, both

    def drop_before(self, t_min_ns: int) -> None:
        t, both = self.arrays()
        if self.sorted:  # what is kept is a slice (views: the next concatenation copies them)
            first = int(np.searchsorted(t, t_min_ns, side="left"))
            if first:
                self.t_ns, self.both = [t[first:]], [both[first:]]
            return
        keep = t >= t_min_ns
        if not keep.all():
            self.t_ns, self.both = [t[keep]], [both[keep]]


def _clean(t: np.ndarray, both: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Sorted by time, duplicate stamps removed (the first kept); returns the count removed."""
    if len(t) < 2 or np.all(t[1:] > t[:-1]):
        return t, both, 0
    order = np.argsort(t, kind="stable")
    t, both = t[order], both[order]
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = np.diff(t) > 0
    return t[keep], both[keep], int(np.count_nonzero(~keep))


class StreamingCalibrator:
    """The schedule: IMU samples buffered as they are read, the boot once enough are
    (:func:`~.boot.boot`), and every window all IMUs cover reduced to its moments
    (:func:`~.moments.reduce_block`). It solves nothing: :func:`~.estimates.estimates` does,
    from :meth:`moments`, at any time.

    Windows are reduced ``block_windows`` at a time (one spline and filter pass per block); a
    follower that catches up with a recording reduces the windows covered so far
    (``process(whole_blocks=False)``). Memory holds the raw samples of about one block plus
    two small matrices per window and sensor.

    >>> cal = StreamingCalibrator(sensors, base_name="base")        # doctest: +SKIP
    >>> for imu, t_ns, gyro, accel in batches:                      # doctest: +SKIP
    ...     cal.add(imu, t_ns, gyro, accel)
    >>> cal.finish()                                                # doctest: +SKIP
    >>> found = estimates(cal)                                      # doctest: +SKIP
    """

    def __init__(
        self,
        sensors: Sequence[SensorSetup],
        base_name: str = "base",
        block_windows: int = BLOCK_WINDOWS,
        reorder_s: float = REORDER_S,
        base_units: tuple[str, str] = ("auto", "auto"),
        base_label: tuple[str, str] = ("", ""),
        base_pose: Transform | None = None,
        keep_rows: bool = False,
        base_bias: BaseGyroBias | None = None,
    ) -> None:
        if not sensors:
            raise ValueError("no sensors")
        sensors = self._place_base(sensors, base_pose)
        self.sensors = {s.name: s for s in sensors}
        self.base_name = base_name
        opts = sensors[0].options
        self.rate, self.window_s = opts.resample_hz, opts.window_s
        self.max_offset = max(s.options.max_time_offset_s for s in sensors)
        self.lowpass = Lowpass(opts.lowpass_hz, self.rate)
        self.buffers = {base_name: _Buffer(), **{name: _Buffer() for name in self.sensors}}
        self.t_ref_ns: int | None = None
        self.next_window, self.reduced = 0, 0  # (windows reduced so far, merged or not)
        self.windows: dict[str, list[WindowMoments]] = {name: [] for name in self.sensors}
        #: Where every window's observability is kept (``segments``): the merged ones'.
        self.rows = {name: WindowRows() for name in self.sensors} if keep_rows else None
        self.tau0: dict[str, float] = {}
        #: Each sensor's clock offset followed through the drive (where its drift is estimated).
        self.clocks: dict[str, ClockTrack] = {}
        #: Each sensor's timeline, the epochs solved so far (:mod:`.timeline`).
        self.epochs = {name: EpochCache() for name in self.sensors}
        #: Per sensor, windows a step of its clock may lie in (made unusable once reduced).
        self._unused: dict[str, set[int]] = {}
        self._final = self.finished = False
        #: Each sensor's clock offset as the boot's correlation placed it (None: not estimated).
        self.time_offsets: dict[str, TimeOffset | None] = {}
        #: Per IMU, the factors (gyro, accelerometer) that made its samples SI, from the boot on.
        self.scales: dict[str, tuple[float, float]] = {}
        self.unit_warnings: dict[str, list[str]] = {}
        #: Per IMU, (topic, config key path) for messages.
        self.labels = {base_name: base_label, **{s.name: (s.topic, s.key) for s in sensors}}
        units = {s.name: SensorUnits(s.options, s.gyro_units, s.accel_units) for s in sensors}
        self.rig = Rig(base_name, base_units, units, self.rate, self.lowpass, self.labels)
        self.dw_noise_var, self._boot_horizon_s = 0.0, BOOT_S
        self.noise: dict[str, tuple[float, float]] = {}
        self.sigma: dict[str, tuple[float, float]] = {}
        #: Median sample rate of every IMU (Hz), measured at boot.
        self.rates_hz: dict[str, float] = {}
        #: Checks of the whole rig made at boot, counted in every sensor's status.
        self.given_checks: tuple[Check, ...] = ()
        self.block_windows = max(1, int(block_windows))
        #: How far out of order stamps may arrive (s): windows wait this long for them.
        self.reorder_s = reorder_s
        #: Per IMU that went silent while the others went on: [from, to] s (``to`` None: still).
        self.silences: dict[str, list[list[float | None]]] = {}
        #: Per IMU, where it read values that are not the motion (its readings as sent).
        self.saturation = {name: Saturation() for name in self.buffers}
        #: The base gyro's bias where its rests show it: the lever arms' terms take rates less it.
        self.base_bias = base_bias

    def _place_base(
        self, sensors: Sequence[SensorSetup], base_pose: Transform | None
    ) -> list[SensorSetup]:
        """Where the base IMU sits in B. Its samples are turned into B's axes as they come, and
        each sensor is estimated relative to it: the lever arms the model sees are from the
        base IMU (its centripetal and Euler terms are the sensors' own, less its own), and the
        estimates are moved back to B's origin (:meth:`estimates`). Returns the sensors with
        their priors from the base IMU."""
        R = base_pose.rotation.as_matrix() if base_pose is not None else np.eye(3)
        self.R_base_baseimu = None if np.array_equal(R, np.eye(3)) else R
        offset = base_pose.translation if base_pose is not None else np.zeros(3)
        self.t_base_baseimu = offset
        return [
            replace(
                s,
                prior_T_base_imu=Transform(
                    s.prior_T_base_imu.rotation, s.prior_T_base_imu.translation - offset
                ),
            )
            for s in sensors
        ]

    # ---------------------------------------------------------------- input

    def add(self, imu: str, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> int:
        """Append samples of one IMU (``base_name`` or a sensor name); returns the number of
        windows reduced as a result."""
        if len(t_ns) == 0:
            return 0
        buffer = self.buffers[imu]
        t_ns = np.array(t_ns, dtype=np.int64)  # a copy: a live caller may reuse its buffers
        buffer.first_ns = (
            int(t_ns.min()) if buffer.first_ns is None else min(buffer.first_ns, int(t_ns.min()))
        )
        buffer.last_ns = (
            int(t_ns.max()) if buffer.last_ns is None else max(buffer.last_ns, int(t_ns.max()))
        )
        gyro = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
        accel = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
        self.saturation[imu].add(t_ns, gyro, accel)  # as sent: before units and turns
        both = np.hstack([gyro, accel])
        if imu in self.scales:  # after boot: in SI, as the boot found the units
            gyro_scale, accel_scale = self.scales[imu]
            if gyro_scale != 1.0:
                both[:, :3] *= gyro_scale
            if accel_scale != 1.0:
                both[:, 3:] *= accel_scale
        if imu == self.base_name and self.R_base_baseimu is not None:  # into B's axes
            both[:, :3] = both[:, :3] @ self.R_base_baseimu.T
            both[:, 3:] = both[:, 3:] @ self.R_base_baseimu.T
        buffer.append(t_ns, both)
        if self.t_ref_ns is None and all(b.first_ns is not None for b in self.buffers.values()):
            self.t_ref_ns = max(int(b.first_ns) for b in self.buffers.values())  # type: ignore[arg-type]
        return self.process()

    def add_clipped(self, imu: str, t_ns: np.ndarray) -> None:
        """Stamps (ns) of samples of one IMU that were clipped at its range and dropped before
        :meth:`add`: the windows that hold one are not used, as for a saturated reading."""
        if len(t_ns):
            self.saturation[imu].dropped.append(np.asarray(t_ns, dtype=np.int64))

    def _seconds(self, t_ns: np.ndarray) -> np.ndarray:
        assert self.t_ref_ns is not None
        return (t_ns - self.t_ref_ns).astype(np.float64) * 1e-9

    # ---------------------------------------------------------------- windows

    @property
    def _grid_start(self) -> float:
        """Seconds from ``t_ref_ns`` where the first window starts."""
        return PAD_S + self.max_offset

    def _covered_until(self) -> float:
        """Seconds from the origin every IMU that has not stopped has data up to."""
        assert self.t_ref_ns is not None
        lasts = {name: (int(b.last_ns) - self.t_ref_ns) * 1e-9 for name, b in self.buffers.items()}  # type: ignore[arg-type]
        lead = sorted(lasts.values())[
            len(lasts) // 2
        ]  # where most IMUs are: one whose clock leapt ahead leads nothing
        for name, last in lasts.items():  # an IMU that has stopped, or that resumed
            silent = self._stopped(name)
            if lead - last > max(STOPPED_S, 3 * self.window_s) and not silent:
                self.silences.setdefault(name, []).append([last, None])
            elif silent and lead - last <= self.reorder_s + self.max_offset + PAD_S:
                self.silences[name][-1][1] = last
        return min(last for name, last in lasts.items() if not self._stopped(name))

    def _stopped(self, name: str) -> bool:
        """Whether IMU ``name`` is silent now while the others go on."""
        silences = self.silences.get(name)
        return bool(silences) and silences[-1][1] is None  # type: ignore[index]

    def starting(self) -> tuple[float, float, bool]:
        """Before the start (the boot): seconds of data read from the grid's origin, seconds the
        next attempt needs, and whether an attempt found too little motion already."""
        read = self._covered_until() - self._grid_start if self.t_ref_ns is not None else 0.0
        needs = self._boot_horizon_s + PAD_S + self.max_offset
        return max(read, 0.0), needs, self._boot_horizon_s > BOOT_S

    def _boot(self, final: bool) -> bool:
        """Once enough data is buffered: each IMU's units and noise, each sensor's clock offset
        (where the drive shows it) and the residuals' noise levels."""
        if self.tau0:
            return True
        covered = self._covered_until() if self.t_ref_ns is not None else 0.0
        # patient attempts at fixed horizons (BOOT_S, then every BOOT_RETRY_S), each on the data
        # up to its horizon only: the boot, and so the estimate, is the same however the log
        # arrives (in 10 s chunks from a file, or message by message while it is recorded)
        horizon = self._grid_start + self._boot_horizon_s
        if not final and covered < horizon + PAD_S + self.max_offset:
            return False
        end = min(
            covered - PAD_S - self.max_offset, self._grid_start + MAX_BOOT_S if final else horizon
        )
        grid = np.arange(self._grid_start, end, 1.0 / self.rate)
        if len(grid) < 10:
            if final:
                raise TooLittleData(self._too_little(covered))
            return False
        patient = not final and self._boot_horizon_s < MAX_BOOT_S  # may wait for more motion
        self._boot_horizon_s += BOOT_RETRY_S  # the next attempt's, should this one wait
        limit = self.t_ref_ns + int((end + PAD_S + self.max_offset + 3.0 / self.rate) * 1e9)  # type: ignore[operator]
        full = {name: buffer.cleaned() for name, buffer in self.buffers.items()}
        upto = {name: int(np.searchsorted(t, limit, side="right")) for name, (t, _) in full.items()}
        samples = {name: (t[: upto[name]], both[: upto[name]]) for name, (t, both) in full.items()}
        seconds = {name: self._seconds(t) for name, (t, _) in samples.items()}
        booted = boot(self.rig, samples, seconds, grid, patient)
        if booted is None:
            return False
        # booted: the buffers from now on in SI
        for name, (_, both) in full.items():
            if booted.scales[name] != (1.0, 1.0):
                both *= np.repeat(booted.scales[name], 3)  # the stored samples, in place
        self.scales, self.unit_warnings, self.sigma = booted.scales, booted.unit_notes, booted.sigma
        self.noise, self.rates_hz = booted.noise, booted.rates_hz
        self.given_checks, self.dw_noise_var = booted.given_checks, booted.dw_noise_var
        self.time_offsets = booted.time_offsets
        self.tau0 = {name: booted.tau0(name) for name in self.sensors}
        for name, setup in self.sensors.items():
            offset = booted.time_offsets.get(name)
            if offset is not None and offset.shown and setup.options.max_clock_drift_ppm > 0:
                drift = 1e-6 * setup.options.max_clock_drift_ppm
                self.clocks[name] = ClockTrack(self.tau0[name], drift)
        return True

    def process(self, final: bool = False, whole_blocks: bool = True) -> int:
        """Reduce every window all IMUs now cover, ``block_windows`` at a time (one spline and
        one filter pass per IMU and block); returns how many. Without ``whole_blocks`` (a
        follower that caught up with the recording), the windows covered so far are reduced
        in a block that is not whole."""
        need = self.block_windows if whole_blocks else 1
        self._final = final  # (the log ended: each clock's last group joins its line at once)
        if self.t_ref_ns is None or not self._boot(final):
            if final:  # (the boot found no stretch to read: no window either)
                raise TooLittleData(self._too_little(self._covered_until()))
            return 0
        count = 0
        covered = self._covered_until()
        while True:
            if not final and covered < self._need(self.next_window + need - 1, final):
                break  # no whole block yet (skipping empty stretches would only move it later)
            self._skip_empty()
            spans: list[tuple[int, float, float]] = []
            partial = False
            while len(spans) < self.block_windows:
                number = self.next_window + len(spans)
                start = self._grid_start + number * self.window_s
                end = start + self.window_s
                if covered < self._need(number, final):
                    if final:
                        # (with the padding after it that every other window has: the
                        # filters, each of its own samples, part at their ends)
                        end = min(end, covered - self._reach(end) - PAD_S)
                        if end - start >= self.window_s / 2:
                            spans.append((number, start, end))
                            partial = end < start + self.window_s
                    break
                spans.append((number, start, end))
            if not spans or (not final and len(spans) < need):
                break  # wait for a whole block
            self._reduce(spans)
            self.next_window += len(spans)
            count += len(spans)
            keep_from = spans[-1][1] + self.window_s - PAD_S - self._reach(spans[-1][2]) - 1.0
            assert self.t_ref_ns is not None
            for buffer in self.buffers.values():
                buffer.drop_before(self.t_ref_ns + int(keep_from * 1e9))
            if partial or len(spans) < self.block_windows:
                break
        if final and not any(self.windows.values()):
            raise TooLittleData(self._too_little(covered))
        return count

    def _too_little(self, covered: float) -> str:
        """No window: the one threshold, as :meth:`process` applies it to a log's last window
        (half a window after the grid's start, with the padding and the clock offset)."""
        need = self._grid_start + self.window_s / 2 + self.max_offset + PAD_S
        return (
            f"too little data: the IMUs overlap for {max(covered, 0.0):.1f} s; calibration "
            f"needs {need:.1f} s for one window"
        )

    def _need(self, number: int, final: bool) -> float:
        """Seconds from the origin every IMU must cover before window ``number`` is reduced:
        its end, the padding, the clock offset and (while reading) the reordering slack."""
        end = self._grid_start + (number + 1) * self.window_s
        return end + PAD_S + self._reach(end) + (0.0 if final else self.reorder_s)

    def _reach(self, t: float) -> float:
        """How far (s) a sensor's samples may lie from the base's at ``t``: the offset
        searched, or a followed clock's offset where it drifted further."""
        return max([self.max_offset, *(c.reach(t) for c in self.clocks.values())])

    def _skip_empty(self) -> None:
        """Move the next window past a stretch where some IMU has no data at all (a long gap,
        or a clock that leapt forward): such windows could not be used, and there may be very
        many of them."""
        assert self.t_ref_ns is not None
        firsts = []
        for name, buffer in self.buffers.items():
            if self._stopped(name):
                continue  # its windows are not used
            t, _ = buffer.arrays()
            if not len(t):
                return
            firsts.append(int(t.min()))
        ready = (max(firsts) - self.t_ref_ns) * 1e-9 - PAD_S - self.max_offset
        start = self._grid_start + self.next_window * self.window_s
        if ready > start + 2 * self.window_s:
            self.next_window = int((ready - self._grid_start) // self.window_s)

    def _reduce(self, spans: list[tuple[int, float, float]]) -> None:
        """Condition a block of consecutive windows once and reduce each to its moments; a
        followed clock's offsets measured, and the block conditioned again where they show
        the offsets it was resampled at off (:meth:`_corrected`)."""
        block_start, block_end = spans[0][1], spans[-1][2]
        n_pad = round(PAD_S * self.rate)
        n_block = round((block_end - block_start) * self.rate)
        last = self._covered_until() - self._reach(block_end) - 2.0 / self.rate  # no extrapolating
        n_after = int(np.clip(np.floor((last - block_end) * self.rate), 0, n_pad))
        # the samples the grid needs (as in reduce_block), with a margin
        grid_first, grid_last = block_start + np.array([-n_pad, n_block + n_after - 1]) / self.rate
        ends = np.array([block_start, block_end])
        offsets = {name: constant(self.tau0[name]) for name in self.sensors}
        offsets.update({name: track.predictor(ends) for name, track in self.clocks.items()})
        samples = {}
        for name in (self.base_name, *self.sensors):
            tau = offsets.get(name, constant(0.0))
            grid = np.array([grid_first, grid_last])
            first_s, last_s = grid + tau(grid) + np.array([-1, 1]) * (3.0 / self.rate + 0.1)
            t, both = self.buffers[name].cleaned()
            t = self._seconds(t)  # sorted (cleaned): the samples in the span are a slice
            a = int(np.searchsorted(t, first_s, side="left"))
            b = int(np.searchsorted(t, last_s, side="right"))
            if b - a >= MIN_SPAN_SAMPLES:  # an IMU that stopped has none: its windows are not used
                saturated = self._saturated(name, first_s - self.lowpass.reach_s)
                samples[name] = (tau, t[a:b], both[a:b], saturated)
        args = (spans, self.rate, self.window_s, self.lowpass, n_pad, n_block, n_after)
        reduced: dict[str, list[WindowMoments]] = {}
        if self.base_name in samples:
            bias = self._base_bias(samples[self.base_name])
            measured: dict[str, list[tuple[float, float] | None]] = {n: [] for n in self.clocks}
            reduced = reduce_block(*args, self.base_name, samples, measured, base_gyro_bias=bias)
            again = self._corrected(spans, samples, measured)
            if again:
                redone = reduce_block(
                    *args, self.base_name, {**samples, **again}, base_gyro_bias=bias
                )
                reduced.update({name: redone[name] for name in again if name in redone})
            for name, windows in reduced.items():  # the offsets they were resampled at
                tau = (again.get(name) or samples[name])[0]
                for w in windows:
                    w.offset_s = float(tau(np.array([0.5 * (w.start_s + w.end_s)]))[0])
        for name in self.sensors:
            self.windows[name].extend(
                reduced.get(name)
                or [unused_window(number, start, end) for number, start, end in spans]
            )
            self._not_used(name)
            self._merge(name)
        self.reduced += len(spans)

    def _base_bias(
        self, samples: tuple[Offset, np.ndarray, np.ndarray, np.ndarray]
    ) -> np.ndarray | None:
        """The base gyro's bias, from the middles of the rests among a block's base
        samples where they hold one (:class:`~.biases.BaseGyroBias`), else as before."""
        if self.base_bias is None:
            return None
        _, t_s, both, _ = samples
        self.base_bias.update(np.round(t_s * 1e9).astype(np.int64), both[:, :3], both[:, 3:])
        return self.base_bias.value

    def _merge(self, name: str) -> None:
        """Sensor ``name``'s oldest windows merged in pairs (:func:`~.moments.merged`) until it
        keeps :data:`MAX_UNITS`: of the neighbours beyond the newest :data:`FULL_WINDOWS`,
        those that stand for the fewest windows, both used or both not and in one epoch where
        any such are, the oldest first; each moved to its clock's track as followed now."""
        windows = self.windows[name]
        if len(windows) <= MAX_UNITS:
            return
        self.moments(name)  # (their observability: which are used)
        track = self.clocks.get(name)
        line = track.fit() if track is not None and track.followed else None
        epoch_s = self.sensors[name].options.epoch_s
        biases = bias_model(self.sensors[name].options)
        while len(windows) > MAX_UNITS:
            old = windows[: len(windows) - FULL_WINDOWS]
            kept = np.array([used(w) for w in old])
            epochs = np.array([epoch_of(w, epoch_s) for w in old])
            cost = np.array([w.count for w in old], dtype=float)
            cost = cost[:-1] + cost[1:]
            whole = np.array([w.valid for w in old])  # (no gap: unused for want of motion)
            cost[(kept[:-1] != kept[1:]) | (whole[:-1] != whole[1:])] += 1e6  # (last resorts)
            cost[epochs[:-1] != epochs[1:]] += 1e9  # (across epochs: likewise)
            i = int(np.argmin(cost))
            pair = windows[i : i + 2]
            if self.rows is not None:
                self.rows[name].extend(
                    [w.info for w in pair if w.count == 1 and w.info is not None]
                )
            middles = np.array([0.5 * (w.start_s + w.end_s) for w in pair])
            middle = np.array([0.5 * (pair[0].start_s + pair[1].end_s)])
            if line is None:
                shifts, offset = np.zeros(2), pair[0].offset_s
            else:
                shifts = line.at(middles) - np.array([w.offset_s for w in pair])
                offset = float(line.at(middle)[0])
            windows[i : i + 2] = [merged(pair, shifts, offset, biases, self.sigma[name])]

    def _not_used(self, name: str) -> None:
        """The windows of sensor ``name`` a step of its clock may lie in made unusable (they
        are among the last three groups')."""
        unused = self._unused.pop(name, set())
        for window in self.windows[name][-3 * GROUP_WINDOWS :]:
            if window.valid and window.number in unused:
                window.valid, window.info = False, None  # (its observability again)

    def _corrected(
        self,
        spans: list[tuple[int, float, float]],
        samples: dict[str, tuple[Offset, np.ndarray, np.ndarray, np.ndarray]],
        measured: dict[str, list[tuple[float, float] | None]],
    ) -> dict[str, tuple[Offset, np.ndarray, np.ndarray, np.ndarray]]:
        """Each followed clock's windows measured into its track (a step of the clock found
        first: the windows it may lie in are not used), and the sensors whose block the track
        now places off the offsets it was resampled at (by its 3 std and
        :data:`~.clock.MIN_CORRECTION_S`), with the track's offsets."""
        again = {}
        for name, found in measured.items():
            if name not in samples:
                continue
            tau, track = samples[name][0], self.clocks[name]
            windows = [(span, m) for span, m in zip(spans, found, strict=False) if m is not None]
            times = np.array([0.5 * (start + end) for (_, start, end), _ in windows])
            rows = [
                (number, start, float(t), float(at) + delta, variance)
                for t, at, ((number, start, _), (delta, variance)) in zip(
                    times, tau(times), windows, strict=True
                )
            ]
            unused = track.measure(rows) + (track.flush() if self._final else [])
            if unused:  # and the windows after it reduced before it was found
                unused += range(min(unused), spans[0][0])
            self._unused.setdefault(name, set()).update(unused)
            all_times = np.array([0.5 * (start + end) for _, start, end in spans])
            corrected = track.correction(all_times, tau(all_times))
            if corrected is not None:
                again[name] = (corrected, *samples[name][1:])
        return again

    def _saturated(self, name: str, from_s: float) -> np.ndarray:
        """The stamps (s) from ``from_s`` on where IMU ``name`` read its full scale (either
        triad, where it saturates, and the clipped samples reading dropped)."""
        assert self.t_ref_ns is not None
        from_ns = self.t_ref_ns + int(from_s * 1e9)
        stamps = self.saturation[name].after(from_ns, self.scales.get(name, (1.0, 1.0)))
        return self._seconds(stamps)

    def moments(self, name: str) -> list[WindowMoments]:
        """Sensor ``name``'s windows reduced so far, each with its observability (filled in
        for those that lack it, all at once)."""
        windows = self.windows[name]
        missing = [w for w in windows if w.info is None]
        setup = self.sensors[name]
        sigma_gyro, sigma_accel = self.sigma.get(name, (1.0, 1.0))
        opts = setup.options
        for a in range(0, len(missing), INFO_CHUNK):
            part = missing[a : a + INFO_CHUNK]
            infos = window_infos_from_moments(
                [(w.start_s, w.end_s, w.valid) for w in part],
                np.array([w.samples for w in part]),
                assemble_moments(part, "gyro"),
                assemble_moments(part, "accel"),
                setup.prior_T_base_imu.translation,
                sigma_gyro,
                sigma_accel,
                opts.max_rotation_std_deg,
                opts.translation_bound_m,
                self.dw_noise_var,
            )
            for window, info in zip(part, infos, strict=True):
                if window.count > 1:
                    info = replace(info, count=window.count, left_out=window.left_out)
                window.info = info
        return windows

    # ---------------------------------------------------------------- output

    def finish(self) -> None:
        """Reduce what is left (the log has ended)."""
        if self.t_ref_ns is None:
            raise TooLittleData(
                "too little data: no samples from "
                + ", ".join(n for n, b in self.buffers.items() if b.first_ns is None)
            )
        self.process(final=True)
        for name, track in self.clocks.items():  # the last group's measurements
            self._unused.setdefault(name, set()).update(track.flush())
            self._not_used(name)
        self.finished = True

    def window_infos(self, name: str) -> Sequence[WindowInfo]:
        """Sensor ``name``'s windows' observability: of every window where its rows are kept,
        else of what is kept (old windows merged: each stands for its windows)."""
        kept = [w.info for w in self.moments(name) if w.info is not None]
        if self.rows is None:
            return kept
        return self.rows[name].sorted([info for info in kept if info.count == 1])

    def duplicates(self, imu: str) -> int:
        return self.buffers[imu].duplicates
