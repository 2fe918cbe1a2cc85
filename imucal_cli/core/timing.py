"""Clock offset between a sensor IMU and the base IMU.

The magnitude of the angular velocity is the same in every frame of a rigid body, so ``|w|`` of
the sensor and of the base can be compared before the rotation between them is known. Their
cross-correlation peaks at the clock offset; a parabola through the peak and its neighbours
refines it below one sample. (The joint calibration then refines it further.)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: A clock offset counts as shown by the drive when its std is below this (s).
TIME_OFFSET_MAX_STD_S = 0.002


@dataclass(frozen=True)
class TimeOffset:
    """The correlation's clock offset and whether the drive shows it."""

    tau_s: float
    peak: float  # correlation coefficient at the peak
    std_s: float  # Cramer-Rao std of the delay of the base's |w| in the sensor's noise
    shown: bool  # a peak inside the search, sharper than TIME_OFFSET_MAX_STD_S
    reason: str = ""  # why not, where not


def time_offset_shown(
    grid_s: np.ndarray,
    speed_base: np.ndarray,
    speed_sensor: np.ndarray,
    max_offset_s: float,
    noise_std: float,
    noise_gain: float,
) -> TimeOffset:
    """:func:`estimate_time_offset` with a uniqueness test.

    The delay of a signal ``a(t)`` seen in white noise of ``noise_std`` per sample (low-passed,
    ``noise_gain`` its variance gain) has the Cramer-Rao std
    ``noise_std sqrt(noise_gain / sum a'(t_k)^2)``: a drive whose ``|w|`` hardly changes (a
    straight highway) does not show the offset, whatever the correlation's peak says. A peak on
    the search's edge is no peak either.
    """
    tau, peak = estimate_time_offset(grid_s, speed_base, speed_sensor, max_offset_s)
    dt = float(grid_s[1] - grid_s[0])
    slope = np.gradient(speed_base, dt)
    energy = float(np.sum(slope**2))
    std = float(noise_std * np.sqrt(noise_gain / energy)) if energy > 0 else float("inf")
    if abs(tau) >= max_offset_s - 1.5 * dt:
        return TimeOffset(
            tau,
            peak,
            std,
            False,
            f"the |w| correlation peaks at the edge of the search (+-{max_offset_s:g} s)",
        )
    if not std <= TIME_OFFSET_MAX_STD_S:
        return TimeOffset(tau, peak, std, False, f"|w| changes too little: std {std * 1e3:.1f} ms")
    return TimeOffset(tau, peak, std, True)


def refine_time_offset(
    tau_s: float, step_s: float, correlation: Callable[[float], float], rounds: int = 4
) -> float:
    """The offset maximising ``correlation(tau)`` from ``tau_s``: a parabola through three
    offsets ``step_s`` apart, the step quartered each round.

    The streaming calibrator passes minus the squared difference of the two ``|w|`` (the
    sensor's evaluated at ``t + tau`` by its own spline): zero at the true offset of a
    noise-free drive. The cross-correlation on the grid's lags (:func:`estimate_time_offset`)
    is biased by milliseconds, by its parabola and by the ends of the stretch (its derivative
    at the true offset is half the difference of the squares at the ends); the solve corrects
    the rest only to first order, which left a millimetre in the lever arm."""
    for _ in range(rounds):
        y0, y1, y2 = (correlation(tau_s + k * step_s) for k in (-1, 0, 1))
        denominator = y0 - 2.0 * y1 + y2
        if denominator < 0:
            tau_s += float(np.clip(0.5 * (y0 - y2) / denominator, -1.0, 1.0)) * step_s
        step_s /= 4.0
    return tau_s


def estimate_time_offset(
    grid_s: np.ndarray, speed_base: np.ndarray, speed_sensor: np.ndarray, max_offset_s: float
) -> tuple[float, float]:
    """Offset ``tau`` (s) maximising the correlation of ``|w_sensor|(t + tau)`` with
    ``|w_base|(t)``.

    Parameters
    ----------
    grid_s : (N,) uniform times, s.
    speed_base, speed_sensor : (N,) ``|w|`` of each IMU on that grid, the sensor's by its own
        stamps (so a positive ``tau`` means the sensor's stamps run ahead of the base's).
    max_offset_s : search range ``|tau| <= max_offset_s``.

    Returns
    -------
    (tau, peak correlation coefficient)
    """
    dt = float(grid_s[1] - grid_s[0])
    a = speed_base - np.mean(speed_base)
    b = speed_sensor - np.mean(speed_sensor)
    max_lag = max(1, int(np.ceil(max_offset_s / dt)))
    n = len(a)
    max_lag = min(max_lag, n - 2)
    lags = np.arange(-max_lag, max_lag + 1)
    # c[k] = sum_n b[n + k] a[n], only over the few lags searched
    corr = np.array(
        [np.dot(b[max(k, 0) : n + min(k, 0)], a[max(-k, 0) : n - max(k, 0)]) for k in lags.tolist()]
    )
    norm = np.sqrt(np.sum(a**2) * np.sum(b**2))
    if norm == 0:
        return 0.0, 0.0
    i = int(np.argmax(corr))
    shift = float(lags[i])
    if 0 < i < len(corr) - 1:
        y0, y1, y2 = corr[i - 1], corr[i], corr[i + 1]
        denominator = y0 - 2 * y1 + y2
        if denominator < 0:
            shift += 0.5 * (y0 - y2) / denominator
    return float(np.clip(shift * dt, -max_offset_s, max_offset_s)), float(corr[i] / norm)
