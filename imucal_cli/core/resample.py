"""Each IMU's samples onto the common grid: dropped samples put back, the anti-alias filter
(and the calibration's low-pass) applied at the IMU's own rate and decimated in the same
pass, and a natural cubic spline through what is left, evaluated with its derivatives."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.lib.stride_tricks import as_strided

from imucal_cli.core.signals import Lowpass, TooLittleData, true_runs
from imucal_cli.types import GAP_PERIODS


class Spline:
    """A cubic interpolating spline of one IMU segment, gyro and accelerometer together
    (columns 0-2 and 3-5, or the gyro alone), with an anti-alias filter where the IMU runs
    well above the grid.

    With ``smooth`` (the calibration's low-pass), the samples are low-passed by it first, at
    the IMU's own rate and in the same pass as the anti-alias filter: what the spline then gives
    on the grid is what low-passing its values on the grid would give, without filtering them
    again there.
    """

    def __init__(
        self, t: np.ndarray, both: np.ndarray, grid_rate: float, smooth: Lowpass | None = None
    ) -> None:
        period = float(np.median(np.diff(t)))
        rate = 1.0 / period
        anti_alias = 0.4 * grid_rate if rate > 1.5 * grid_rate else None
        knots = t
        if smooth is not None:
            smooth = replace(smooth, rate_hz=rate, second_cutoff_hz=anti_alias)
            step = decimation(smooth, grid_rate)
            knots, both = filled(t, both, period)  # (the filter takes the samples as uniform)
            both, knots = smooth(both, step), knots[::step]
        elif anti_alias is not None:
            both = Lowpass(anti_alias, rate)(both)
        self.t = t
        self.period = period
        self.spline = NaturalCubic(knots, both)

    def gyro(self, query: np.ndarray) -> np.ndarray:
        return self.spline(query)[:, 0:3]

    def __call__(self, query: np.ndarray, upto: int = 0) -> list[np.ndarray]:
        """(n, 6) each: gyro and accelerometer, and their derivatives up to ``upto``."""
        return self.spline.derivatives(query, upto)

    def covered(self, query: np.ndarray) -> np.ndarray:
        """Per query time: inside the samples and not in a gap (of more than ``GAP_PERIODS``
        median periods)."""
        j = np.clip(np.searchsorted(self.t, query), 1, len(self.t) - 1)
        inside = (query >= self.t[0]) & (query <= self.t[-1])
        return inside & (self.t[j] - self.t[j - 1] <= GAP_PERIODS * self.period)


def filled(t: np.ndarray, both: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The samples (stamps ``t`` in s, strictly increasing) with each dropped one put back, from
    the cubic through the two samples on each side of its step: a step of ``k`` periods (``k``
    from 2 to :data:`GAP_PERIODS`) gets ``k - 1`` samples. A filter that runs over the samples
    as a uniform series would shift everything after a dropped sample by a period (a 10 ms lag
    of a gravity turning at 3 Hz in a wheel's IMU: residuals of m/s^2); longer gaps are gaps."""
    steps = np.diff(t)
    missing = np.rint(steps / period).astype(np.int64) - 1
    missing[(missing < 0) | (steps > GAP_PERIODS * period)] = 0
    where = np.flatnonzero(missing)
    if not len(where) or len(t) < 4:
        return t, both
    counts = missing[where]
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    fraction = k / np.repeat(counts + 1, counts)
    left = np.repeat(where, counts)
    new_t = t[left] + fraction * steps[left]
    # Lagrange's cubic through samples first .. first + 3 around the step (inside the ends)
    first = np.clip(left - 1, 0, len(t) - 4)
    nodes = t[first[:, None] + np.arange(4)]
    weights = np.ones((len(new_t), 4))
    for i in range(4):
        for j in range(4):
            if i != j:
                weights[:, i] *= (new_t - nodes[:, j]) / (nodes[:, i] - nodes[:, j])
    values = np.einsum("qk,qkc->qc", weights, both[first[:, None] + np.arange(4)])
    # each before the sample that ends its step, in order (np.insert keeps the given order
    # where several go before one sample): no sort of the block
    return np.insert(t, left + 1, new_t), np.insert(both, left + 1, values, axis=0)


#: The largest response the low-pass may have above a decimated rate's Nyquist frequency.
ALIAS_GAIN = 1e-7


def decimation(smooth: Lowpass, grid_rate: float) -> int:
    """Every how many samples the low-passed signal can be kept: the most that leaves a rate
    of at least the grid's and the filter's response below :data:`ALIAS_GAIN` at the new
    Nyquist frequency (a spline through them then misses nothing the filter passes)."""
    step = max(1, int(smooth.rate_hz / grid_rate + 1e-9))
    while step > 1 and smooth.gain(np.array([smooth.rate_hz / step / 2]))[0] > ALIAS_GAIN:
        step -= 1
    return step


class NaturalCubic:
    """The natural cubic spline through ``(t, y)`` (y: (n, m)), kept as its samples and its
    second derivatives ``M`` at them.

    ``M`` solves a symmetric positive-definite tridiagonal system (LAPACK ``ptsv``), several
    times cheaper than the general banded B-spline collocation; the end conditions differ from
    not-a-knot only within a few samples of the ends, which lie in the padding. It is evaluated
    in the two-point form ``A y_j + B y_j+1 + ((A^3 - A) M_j + (B^3 - B) M_j+1) h^2 / 6``
    (``B`` the query's fraction of its interval ``j``, ``A = 1 - B``), from the samples around
    each query only: no coefficients are formed for intervals nobody asks about (half of them
    when a 200 Hz IMU is resampled to 100 Hz).
    """

    def __init__(self, t: np.ndarray, y: np.ndarray) -> None:
        if len(t) < 3:
            raise TooLittleData("too little data: fewer than 3 samples to interpolate")
        n, m = y.shape
        h = t[1:] - t[:-1]
        slope = y[1:] - y[:-1]
        slope /= h[:, None]
        rhs = slope[1:] - slope[:-1]
        rhs *= 6.0
        diagonal = h[:-1] + h[1:]
        diagonal *= 2.0
        # with stamps strictly increasing (the buffers are cleaned) the system is diagonally
        # dominant, so positive definite
        from scipy.linalg.lapack import dptsv  # (imported when first used)

        _, _, inner, info = dptsv(diagonal, h[1:-1], rhs, overwrite_b=True)
        if info != 0:
            raise ValueError("spline stamps must strictly increase")
        # [y, M] side by side; row j of `pairs` is [y_j, M_j, y_j+1, M_j+1] (a view), so one
        # gather fetches all a query needs
        self.y_M = np.zeros((n, 2 * m))
        self.y_M[:, :m] = y
        self.y_M[1:-1, m:] = inner
        self.pairs = as_strided(
            self.y_M, (n - 1, 4 * m), (self.y_M.strides[0], self.y_M.strides[1]), writeable=False
        )
        self.t, self.h, self.m = t, h, m

    def __call__(self, query: np.ndarray, nu: int = 0) -> np.ndarray:
        """Values (``nu`` = 0) or the ``nu``-th derivative (1, 2) at ``query``, (len(query), m)."""
        return self.derivatives(query, nu)[nu]

    def derivatives(self, query: np.ndarray, upto: int = 2) -> list[np.ndarray]:
        """Values and the derivatives up to ``upto`` at ``query``, (len(query), m) each."""
        j = np.searchsorted(self.t, query, side="right") - 1
        np.clip(j, 0, len(self.t) - 2, out=j)  # the end intervals extend outside
        h = self.h[j]
        B = query - self.t[j]
        B /= h
        A = 1.0 - B
        samples = self.pairs[j].reshape(len(query), 4, self.m)
        # weights of [y_j, M_j, y_j+1, M_j+1] for each derivative
        weights = np.empty((len(query), 4))
        h2_6 = h * h / 6.0
        weights[:, 0], weights[:, 1], weights[:, 2], weights[:, 3] = (
            A,
            (A * A - 1.0) * A * h2_6,
            B,
            (B * B - 1.0) * B * h2_6,
        )
        out = [np.einsum("qk,qkc->qc", weights, samples)]
        if upto >= 1:
            weights[:, 0], weights[:, 2] = -1.0 / h, 1.0 / h
            weights[:, 1], weights[:, 3] = (
                (1.0 - 3.0 * A * A) * h / 6.0,
                (3.0 * B * B - 1.0) * h / 6.0,
            )
            out.append(np.einsum("qk,qkc->qc", weights, samples))
        if upto >= 2:
            out.append(np.einsum("qk,qkc->qc", np.stack([A, B], axis=1), samples[:, 1::2]))
        return out


def longest_covered(grid: np.ndarray, covered: list[np.ndarray], margin: int) -> np.ndarray:
    """The longest stretch of ``grid`` that every IMU covers (no gap), less ``margin`` points at
    each end (where a filter would reach into the gap): the boot's units and clock offsets are
    measured on it, never across a gap."""
    runs = true_runs(np.logical_and.reduce(covered))
    if not runs:
        return grid[:0]
    a, b = max(runs, key=lambda r: r[1] - r[0])
    return grid[a + margin : b - margin]
