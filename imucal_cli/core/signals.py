"""Signal conditioning: resampling onto a common grid, one zero-phase low-pass, noise levels.

The calibration equations (paper eqs. 10-12) relate the two IMUs at the same instant. The IMUs
sample at different instants and rates, so both are interpolated onto one uniform grid with a
cubic spline (exact for smooth signals to ``(2 pi f / fs)^4``), and the *same* zero-phase
Butterworth low-pass is applied to every term of an equation. Linear filters commute with
rotation, constant biases and differentiation, so the filtered equations hold exactly; the
nonlinear centripetal term ``[w]x^2`` is formed before filtering, so it is filtered like the
others. (Smoothing one side and differentiating the other with a different filter would leave a
bias even on noise-free data.)
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from imucal_cli.errors import ImucalError

#: Default cut-off of the common low-pass (Hz): above the 1-2 Hz road and suspension content
#: that carries the lever-arm information, far below the 50 Hz Nyquist of a 100 Hz IMU.
LOWPASS_HZ = 5.0
LOWPASS_ORDER = 4


class TooLittleData(ImucalError):
    """Not enough samples to calibrate."""


@lru_cache(maxsize=256)
def _fast_length(n: int) -> int:
    """The smallest 2^a 3^b 5^c >= n (an FFT size numpy transforms quickly)."""
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            size = p35
            while size < n:
                size *= 2
            best = min(best, size)
            p35 *= 3
        p5 *= 5
    return best


@dataclass(frozen=True)
class Lowpass:
    """A zero-phase Butterworth low-pass on a uniform grid.

    The response is the squared magnitude of an ``order``-th order Butterworth filter,
    ``|H(f)|^2 = 1 / (1 + (f / cutoff)^(2 order))`` (what a forward-backward pass gives), applied
    with the FFT to the signal extended at both ends by point reflection (as ``filtfilt`` pads),
    less the line through its ends (which the filter passes unchanged), so linear trends pass
    unchanged and the periodic transform sees no jump. Real, even, unit gain at 0 Hz: one linear
    operator for every
    column, which is all the calibration equations need of it.
    """

    cutoff_hz: float
    rate_hz: float
    order: int = LOWPASS_ORDER
    #: A second response of the same form multiplied in (an anti-alias filter applied in the
    #: same pass), or None.
    second_cutoff_hz: float | None = None

    @property
    def pad(self) -> int:
        """Samples of reflection at each end: three times the filter's effective length."""
        return int(
            np.ceil(3.0 * self.rate_hz / min(self.cutoff_hz, self.second_cutoff_hz or np.inf))
        )

    @property
    def reach_s(self) -> float:
        """How far (s) a sample moves the filtered signal: its effective length, 1 / cutoff."""
        return 1.0 / self.cutoff_hz

    def __call__(self, x: np.ndarray, step: int = 1) -> np.ndarray:
        """Filter along axis 0 (any trailing shape); the result has each column contiguous
        (Fortran order), as the splines and the FFT take them fastest. With ``step`` > 1, only
        every ``step``-th sample of the result (samples 0, step, ...), from the inverse
        transform of the spectrum's lowest ``1 / step``: exact where the response has no
        content above the new Nyquist frequency (the caller's to know), and that much less work.
        """
        x = np.asarray(x, dtype=np.float64)
        n = len(x)
        if n < 2:
            return x[::step].copy()
        shape = x.shape
        pad = -(-min(self.pad, n - 1) // step) * step  # a multiple of step
        if pad > n - 1:  # too short to decimate in the transform
            return self(x)[::step].copy(order="F")
        m = n + 2 * pad
        size = _fast_length(-(-(m + pad) // step)) * step
        kept = size // step
        columns = x.reshape(n, -1).T  # time along the last axis (a view)
        # The signal extended by point reflections at both ends (as filtfilt pads) less the line
        # through the extension's two ends, which the filter passes unchanged: without it the
        # periodic FFT would see a jump where the ends meet. (Point reflection commutes with
        # subtracting a line, so the line is taken off the signal first and the reflections
        # made of what is left.) One buffer, this thread's from its last call: the
        # reflections, the signal, the reflections, then zeros up to the transform's length.
        first = 2.0 * columns[:, 0] - columns[:, pad]  # the extension's ends
        last = 2.0 * columns[:, n - 1] - columns[:, n - 1 - pad]
        along = np.linspace(0.0, 1.0, m)[pad : pad + n]  # the line's abscissa at the signal
        extended = _scratch("extended", (len(columns), size), np.float64)
        inner = extended[:, pad : pad + n]
        np.multiply.outer(last - first, along, out=inner)
        inner += first[:, None]  # the line at the signal's own samples
        np.subtract(columns, inner, out=inner)
        ends = extended[:, pad : pad + 1], extended[:, pad + n - 1 : pad + n]
        np.subtract(2.0 * ends[0], extended[:, 2 * pad : pad : -1], out=extended[:, :pad])
        np.subtract(
            2.0 * ends[1], extended[:, pad + n - 2 : n - 2 : -1], out=extended[:, pad + n : m]
        )
        extended[:, m:] = 0.0
        # numpy's pocketfft, the same results as scipy.fft's to the bit, without its import;
        # into this thread's buffers (fresh arrays of megabytes every call are pages the
        # kernel zeroes anew: half the page faults of an hour's calibration)
        spectrum = _scratch("spectrum", (len(columns), size // 2 + 1), np.complex128)
        np.fft.rfft(extended, axis=1, out=spectrum)
        spectrum = spectrum[:, : kept // 2 + 1]  # what the decimated inverse transforms
        spectrum *= _response(self, size, step)
        filtered = _scratch("filtered", (len(columns), kept), np.float64)
        np.fft.irfft(spectrum, n=kept, axis=1, out=filtered)
        out = np.multiply.outer(last - first, along[::step])  # the line back, every step-th
        out += first[:, None]
        out += filtered[:, pad // step : pad // step + out.shape[1]]
        # time along axis 0 again: the transpose, a view (Fortran order: each column contiguous)
        return out.T.reshape((out.shape[1], *shape[1:]))

    def gain(self, freq_hz: np.ndarray) -> np.ndarray:
        """The filter's (real, zero-phase) frequency response."""
        gain = 1.0 / (1.0 + _even_power(freq_hz / self.cutoff_hz, self.order))
        if self.second_cutoff_hz is not None:
            gain /= 1.0 + _even_power(freq_hz / self.second_cutoff_hz, self.order)
        return gain

    def white_noise_gain(self) -> float:
        """Variance of the filtered output of unit white noise: ``sum h^2`` of the zero-phase
        impulse response. An estimate's covariance computed from filtered residuals, as if they
        were independent, must be divided by this to be honest."""
        return _white_noise_gain(self)


_BUFFERS = threading.local()


def _scratch(name: str, shape: tuple[int, int], dtype: type) -> np.ndarray:
    """This thread's buffer ``name`` as an array of ``shape``: the same memory every call (grown
    when a call needs more), whose contents are the caller's to overwrite."""
    size = shape[0] * shape[1]
    held = _BUFFERS.__dict__.get(name)
    if held is None or held.size < size or held.dtype != dtype:
        held = _BUFFERS.__dict__[name] = np.empty(size, dtype)
    return held[:size].reshape(shape)


@lru_cache(maxsize=16)
def _white_noise_gain(lowpass: Lowpass) -> float:
    """:meth:`Lowpass.white_noise_gain` (kept: every block's clock measurement asks it)."""
    n = int(40 * lowpass.rate_hz / lowpass.cutoff_hz) | 1
    impulse = np.zeros(n)
    impulse[n // 2] = 1.0
    return float(np.sum(lowpass(impulse) ** 2))


def _even_power(ratio: np.ndarray, order: int) -> np.ndarray:
    """``ratio ** (2 order)`` by multiplication (``**`` with a general exponent is several
    times slower)."""
    squared = np.square(ratio)
    power = squared.copy()
    for _ in range(order - 1):
        power *= squared
    return power


@lru_cache(maxsize=64)
def _response(lowpass: Lowpass, size: int, step: int = 1) -> np.ndarray:
    """``lowpass``'s response at the frequencies of a real FFT of ``size`` samples up to the
    Nyquist frequency of every ``step``-th sample, divided by ``step`` (the inverse transform of
    ``size / step`` samples scales by that much less; exact for a power of two). Kept: the
    grid's filter takes the same lengths every block (a sensor's, at the rate measured in each
    block, mostly misses: 249 of 362 calls an hour of five IMUs)."""
    kept = size // step
    gain = lowpass.gain(np.fft.rfftfreq(size, d=1.0 / lowpass.rate_hz)[: kept // 2 + 1]) / step
    gain.flags.writeable = False
    return gain


def derivative_noise_variance(lowpass: Lowpass, density: float) -> float:
    """Variance of one sample of the low-passed time derivative of white noise of ``density``
    (per sqrt(Hz)): ``density^2 int |H(f)|^2 (2 pi f)^2 df``. The angular acceleration is the
    base gyro's derivative, so its noise is this, not the gyro's (errors in variables)."""
    f = np.linspace(0.0, 20.0 * lowpass.cutoff_hz, 8001)
    return float(2.0 * density**2 * np.trapezoid(lowpass.gain(f) ** 2 * (2 * np.pi * f) ** 2, f))


def welch(x: np.ndarray, rate_hz: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Welch's one-sided power spectral density of each column of ``x`` (N, m), as
    ``scipy.signal.welch(x, rate_hz, nperseg=nperseg, axis=0)`` computes it (Hann window, half
    overlap, each segment's mean removed): written here because ``scipy.signal`` takes 0.6 s
    to import (it imports ``scipy.stats``), a tenth of an hour's calibration."""
    step = nperseg - nperseg // 2  # scipy's default overlap, nperseg // 2
    starts = np.arange(0, len(x) - nperseg + 1, step)
    window = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(nperseg) / nperseg)  # periodic Hann
    segments = x[starts[:, None] + np.arange(nperseg)]  # (segments, nperseg, m)
    segments = (segments - segments.mean(axis=1, keepdims=True)) * window[None, :, None]
    power = np.abs(np.fft.rfft(segments, axis=1)) ** 2 / (rate_hz * np.sum(window**2))
    power[:, 1 : (nperseg + 1) // 2] *= 2.0  # one-sided: every bin but 0 and Nyquist twice
    return np.fft.rfftfreq(nperseg, 1.0 / rate_hz), power.mean(axis=0)


def white_noise_density(x: np.ndarray, rate_hz: float, band_hz: tuple[float, float]) -> np.ndarray:
    """Per-axis white-noise density (per sqrt(Hz), two-sided: a sample's std is
    ``density sqrt(rate)``) of a sampled signal (N, 3), from the median of its periodogram in
    ``band_hz``: above the motion, where a vibration line or two only moves the median by a few
    bins (second differences, :func:`white_noise_std`, count a 20-60 Hz mount vibration as
    noise). The periodogram is of the second differences, the signal's motion thereby
    suppressed by ``(2 sin(pi f / rate))^4`` before the window's leakage can spread it, and
    corrected back."""
    d2 = np.diff(np.asarray(x, dtype=np.float64), n=2, axis=0)
    nperseg = int(min(len(d2), 2 ** np.ceil(np.log2(4.0 * rate_hz))))  # about 4 s segments
    lo, hi = band_hz[0], min(band_hz[1], 0.8 * rate_hz / 2)
    if nperseg < 16 or lo >= hi:
        return white_noise_std(x) / np.sqrt(rate_hz)
    f, psd = welch(d2, rate_hz, nperseg)
    inside = (f >= lo) & (f <= hi)
    if np.count_nonzero(inside) < 3:
        return white_noise_std(x) / np.sqrt(rate_hz)
    response = (2.0 * np.sin(np.pi * f[inside] / rate_hz)) ** 4
    return np.sqrt(
        np.median(psd[inside] / response[:, None], axis=0) / 2.0
    )  # one-sided to two-sided


def white_noise_std(x: np.ndarray) -> np.ndarray:
    """Per-axis white-noise standard deviation of a sampled signal (N, 3).

    From second differences, where a smooth signal nearly cancels and white noise of variance
    ``s^2`` has variance ``6 s^2``; the median absolute deviation makes it robust to the few
    samples with sharp motion.
    """
    d2 = np.diff(np.asarray(x, dtype=np.float64), n=2, axis=0)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(6.0)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of True in ``mask``: ``(start, stop)`` index pairs, stop exclusive."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


#: Below these a triad's largest reading is no full scale (rad/s, m/s^2): 90% of the narrowest
#: ranges MEMS parts are sold with, 125 deg/s and 2 g.
MIN_FULL_SCALE = (0.9 * np.radians(125.0), 0.9 * 2.0 * 9.80665)
#: Readings this close to a triad's largest (relative) are at it: an int16 register's range is
#: asymmetric (-32768 to +32767 counts, 3e-5 apart).
FULL_SCALE_TOLERANCE = 1e-4
#: A triad saturates where this many readings sit at its largest: a clipped axis repeats its
#: full scale, where a signal's peak is reached once ...
FULL_SCALE_HITS = 3
#: ... and more of them than this times those in the band just below (as wide), as values
#: that repeat: a clipped axis piles up at one value (two, a register's asymmetric ends), where
#: a motion held at its top (a wheel at a steady speed) reads a new value each time and
#: spreads alike over both bands.
FULL_SCALE_SPIKE = 2.0
#: The most distinct values at the largest kept count of.
FULL_SCALE_VALUES = 64


@dataclass
class FullScale:
    """Where one IMU triad saturates: the largest magnitude it has read on any axis, in the
    units it sends, and the stamps (ns) of the readings at that magnitude.

    A saturated reading is not the motion: a window that holds one, in any IMU, does not hold
    the rigid-body equations. Fed in the order the samples come, before anything turns the
    axes (a turn mixes a clipped axis into the others)."""

    level: float = 0.0
    stamps: list[np.ndarray] = field(default_factory=list)
    readings: int = 0
    #: Readings in the band just below the largest (:data:`FULL_SCALE_SPIKE`), and how often
    #: each value at it was read (at most :data:`FULL_SCALE_VALUES` values).
    below: int = 0
    values: dict[float, int] = field(default_factory=dict)

    def add(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        if len(values) == 0:
            return
        top = max(float(values.max()), -float(values.min()))  # two reductions, most batches
        if top < self.level * (1.0 - 2 * FULL_SCALE_TOLERANCE):  # none at or near the largest
            return
        if top > self.level * (1.0 + FULL_SCALE_TOLERANCE):  # a new largest: earlier peaks fall
            self.level, self.stamps, self.readings, self.below = top, [], 0, 0
            self.values = {}
        largest = np.abs(values).max(axis=1)
        at = largest >= self.level * (1.0 - FULL_SCALE_TOLERANCE)
        near = largest >= self.level * (1.0 - 2 * FULL_SCALE_TOLERANCE)
        self.below += int(np.count_nonzero(near & ~at))
        if self.level > 0.0 and at.any():
            self.stamps.append(np.asarray(t_ns)[at])
            self.readings += int(np.count_nonzero(at))
            for value in largest[at].tolist():
                if value in self.values or len(self.values) < FULL_SCALE_VALUES:
                    self.values[value] = self.values.get(value, 0) + 1

    @property
    def repeats(self) -> int:
        """The readings at the two values read most often at the largest (a register's two
        ends): a clipped axis's."""
        return sum(sorted(self.values.values())[-2:])

    def saturated(self, si_scale: float, minimum: float) -> bool:
        """Whether the triad saturates: its largest reading repeats (as one or two values), more
        often than the band below it is read, and is a full scale once made SI (times
        ``si_scale``) at least ``minimum``."""
        return (
            self.repeats >= FULL_SCALE_HITS
            and self.repeats > FULL_SCALE_SPIKE * self.below
            and self.level * si_scale >= minimum
        )

    def after(self, t_min_ns: int) -> np.ndarray:
        """The saturated readings' stamps (ns, sorted) from ``t_min_ns`` on; earlier ones are
        forgotten (the memory stays that of the samples still needed)."""
        stamps = np.sort(np.concatenate(self.stamps)) if self.stamps else np.zeros(0, np.int64)
        stamps = stamps[stamps >= t_min_ns]
        self.stamps = [stamps]
        return stamps


@dataclass
class Saturation:
    """Where one IMU read values that are not the motion: each triad's full scale
    (:class:`FullScale`, gyro then accelerometer) and the stamps (ns) of clipped samples
    reading dropped before they came (a run at the range)."""

    triads: tuple[FullScale, FullScale] = field(default_factory=lambda: (FullScale(), FullScale()))
    dropped: list[np.ndarray] = field(default_factory=list)

    def add(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        for triad, values in zip(self.triads, (gyro, accel), strict=True):
            triad.add(t_ns, values)

    def saturated(self, scales: tuple[float, float]) -> list[bool]:
        """Per triad whether it saturates, its readings made SI by ``scales``."""
        return [
            triad.saturated(scale, minimum)
            for triad, scale, minimum in zip(self.triads, scales, MIN_FULL_SCALE, strict=True)
        ]

    def after(self, t_min_ns: int, scales: tuple[float, float]) -> np.ndarray:
        """The stamps (ns, sorted) from ``t_min_ns`` on of readings not the motion: at the full
        scale of a triad that saturates, or dropped clipped. Earlier ones are forgotten."""
        dropped = np.concatenate([np.zeros(0, np.int64), *self.dropped])
        self.dropped = [dropped[dropped >= t_min_ns]]
        stamps = [self.dropped[0]]
        for triad, saturates in zip(self.triads, self.saturated(scales), strict=True):
            kept = triad.after(t_min_ns)
            if saturates:
                stamps.append(kept)
        return np.sort(np.concatenate(stamps))


def near(query: np.ndarray, stamps: np.ndarray, margin: float) -> np.ndarray:
    """Per query time, whether a stamp (sorted, same units) lies within ``margin`` of it."""
    if len(stamps) == 0:
        return np.zeros(len(query), dtype=bool)
    j = np.clip(np.searchsorted(stamps, query), 1, len(stamps))
    below = np.abs(query - stamps[j - 1])
    above = np.abs(stamps[np.minimum(j, len(stamps) - 1)] - query)
    return np.minimum(below, above) <= margin
