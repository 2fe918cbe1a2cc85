"""The clock offset from the cross-correlation of |w|."""

from __future__ import annotations

import numpy as np

from imucal_cli.core.timing import estimate_time_offset


def test_time_offset_estimator_is_sub_sample():
    rate = 100.0
    grid = np.arange(0, 60, 1 / rate)
    rng = np.random.default_rng(0)
    freqs, phases = rng.uniform(0.1, 2.0, 8), rng.uniform(0, 2 * np.pi, 8)

    def speed(t):
        return 0.3 + np.sum(
            0.05 * np.sin(2 * np.pi * freqs[:, None] * t[None, :] + phases[:, None]), axis=0
        )

    for tau in (0.0123, -0.0371, 0.0):
        estimate, peak = estimate_time_offset(grid, speed(grid), speed(grid - tau), 0.1)
        assert abs(estimate - tau) < 1e-3 and peak > 0.99
