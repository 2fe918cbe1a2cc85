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

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from imucal_cli.errors import ImucalError

#: Default cut-off of the common low-pass (Hz): above the 1-2 Hz road and suspension content
#: that carries the lever-arm information, far below the 50 Hz Nyquist of a 100 Hz IMU.
LOWPASS_HZ = 5.0
LOWPASS_ORDER = 4


class TooLittleData(ImucalError):
    """Not enough samples to calibrate."""


@dataclass(frozen=True)
class Lowpass:
    """A zero-phase Butterworth low-pass on a uniform grid (``scipy.signal.sosfiltfilt``)."""

    cutoff_hz: float
    rate_hz: float
    order: int = LOWPASS_ORDER
    sos: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        sos = signal.butter(self.order, self.cutoff_hz, fs=self.rate_hz, output="sos")
        object.__setattr__(self, "sos", sos)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter along axis 0 (any trailing shape)."""
        x = np.asarray(x, dtype=np.float64)
        padlen = min(3 * 2 * self.order * 3, len(x) - 1)
        return signal.sosfiltfilt(self.sos, x, axis=0, padlen=max(padlen, 0))

    def white_noise_gain(self) -> float:
        """Variance of the filtered output of unit white noise: ``sum h^2`` of the zero-phase
        impulse response. An estimate's covariance computed from filtered residuals, as if they
        were independent, must be divided by this to be honest."""
        n = int(20 * self.rate_hz / self.cutoff_hz) | 1
        impulse = np.zeros(n)
        impulse[n // 2] = 1.0
        h = signal.sosfiltfilt(self.sos, impulse)
        return float(np.sum(h**2))


def white_noise_std(x: np.ndarray) -> np.ndarray:
    """Per-axis white-noise standard deviation of a sampled signal (N, 3).

    From second differences, where a smooth signal nearly cancels and white noise of variance
    ``s^2`` has variance ``6 s^2``; the median absolute deviation makes it robust to the few
    samples with sharp motion.
    """
    d2 = np.diff(np.asarray(x, dtype=np.float64), n=2, axis=0)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(6.0)
