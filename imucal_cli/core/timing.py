"""Clock offset between a sensor IMU and the base IMU.

The magnitude of the angular velocity is the same in every frame of a rigid body, so ``|w|`` of
the sensor and of the base can be compared before the rotation between them is known. Their
cross-correlation peaks at the clock offset; a parabola through the peak and its neighbours
refines it below one sample. (The joint calibration then refines it further.)
"""

from __future__ import annotations

import numpy as np


def estimate_time_offset(
    grid_s: np.ndarray,
    speed_base: np.ndarray,
    speed_sensor: np.ndarray,
    max_offset_s: float,
) -> tuple[float, float]:
    """Offset ``tau`` (s) maximising the correlation of ``|w_sensor|(t + tau)`` with ``|w_base|(t)``.

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
    corr = np.array([np.dot(b[max(k, 0) : n + min(k, 0)], a[max(-k, 0) : n - max(k, 0)]) for k in lags])
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
