"""Streaming calibration: memory flat in the log's length, an estimate after every window.

IMU samples are fed as they are read (:meth:`StreamingCalibrator.add`). Every window of
``window_s`` that all IMUs cover is conditioned once (cubic-spline resampling onto the grid and
the common zero-phase low-pass of :mod:`imucal_cli.core.signals`, computed on the window plus
:data:`PAD_S` of padding on each side, which reproduces a whole-log filter to round-off), its
observability is analysed (eqs. 18-19), and it is reduced to the second moments of the data
vectors of :mod:`imucal_cli.core.model` (:mod:`imucal_cli.core.moments`), the sensor resampled
at ``t + tau0`` (``tau0`` from the cross-correlation of ``|w|`` over the first minute). The raw
samples are dropped once a window is reduced; what is kept per window and sensor is two small
matrices, and :func:`imucal_cli.core.calibrate.solve` estimates from them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.lib.stride_tricks import as_strided

from imucal_cli.core.calibrate import (
    CalibrationOptions,
    ClockEvidence,
    SensorEstimate,
    solve,
    unobservable,
)
from imucal_cli.core.checks import Check, base_gravity
from imucal_cli.core.model import ACCEL_BASE, GYRO_BASE, GYRO_DATA, GYRO_OWN, Layout
from imucal_cli.core.moments import WindowMoments, assemble_moments, base_moments
from imucal_cli.core.segments import WindowInfo, window_infos_from_moments
from imucal_cli.core.signals import (
    Lowpass,
    Saturation,
    TooLittleData,
    derivative_noise_variance,
    near,
    true_runs,
    white_noise_density,
)
from imucal_cli.core.status import unsolved_sentence
from imucal_cli.core.timing import TimeOffset, refine_time_offset, time_offset_shown
from imucal_cli.errors import ImucalError
from imucal_cli.types import GAP_PERIODS, GRAVITY_MPS2, Transform

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
#: Where each IMU's white noise is measured (Hz): above the motion the low-pass keeps, below
#: the internal filters of MEMS parts.
NOISE_BAND_HZ = (10.0, 20.0)
#: Windows conditioned together (one spline and one filter pass per IMU and block).
BLOCK_WINDOWS = 6
#: An IMU with no sample for this long (s) while another goes on has stopped (a driver that
#: died, a topic not recorded): the others' windows go on without it, its own are not used.
STOPPED_S = 30.0
#: Windows whose observability is computed together (bounds scratch memory).
INFO_CHUNK = 128


@dataclass(frozen=True)
class SensorSetup:
    name: str
    prior_T_base_imu: Transform
    options: CalibrationOptions
    gyro_units: str = "auto"  # auto | radps | dps
    accel_units: str = "auto"  # auto | mps2 | g
    topic: str = ""  # where its samples come from, and its config's key path: for messages
    key: str = ""


#: Degrees per radian: how much larger a gyro's numbers are in deg/s.
DPS = float(np.degrees(1.0))
#: The base's |w| must vary by this much (rad/s std) before a gyro's units can be told.
MIN_UNIT_MOTION_RADPS = 0.005


class UnitsError(ImucalError):
    """An IMU's units cannot be told from its data: names the topic and the config key."""

    def __init__(self, topic: str, key: str, detail: str) -> None:
        self.topic, self.key = topic, key
        super().__init__(f"{topic}: {detail}; set {key} in the config")


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


class _Spline:
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
            step = _decimation(smooth, grid_rate)
            knots, both = filled(t, both, period)  # (the filter takes the samples as uniform)
            both, knots = smooth(both, step), knots[::step]
        elif anti_alias is not None:
            both = Lowpass(anti_alias, rate)(both)
        self.t = t
        self.period = period
        self.spline = _NaturalCubic(knots, both)

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
    all_t = np.concatenate([t, new_t])
    order = np.argsort(all_t, kind="stable")
    return all_t[order], np.concatenate([both, values])[order]


#: The largest response the low-pass may have above a decimated rate's Nyquist frequency.
ALIAS_GAIN = 1e-7


def _decimation(smooth: Lowpass, grid_rate: float) -> int:
    """Every how many samples the low-passed signal can be kept: the most that leaves a rate
    of at least the grid's and the filter's response below :data:`ALIAS_GAIN` at the new
    Nyquist frequency (a spline through them then misses nothing the filter passes)."""
    step = max(1, int(smooth.rate_hz / grid_rate + 1e-9))
    while step > 1 and smooth.gain(np.array([smooth.rate_hz / step / 2]))[0] > ALIAS_GAIN:
        step -= 1
    return step


class _NaturalCubic:
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


def _noise_density(both: np.ndarray, rate: float) -> tuple[float, float]:
    """White-noise densities of the gyro and the accelerometer (columns 0-2 and 3-5)."""
    density = white_noise_density(both, rate, NOISE_BAND_HZ)
    return float(np.sqrt(np.mean(density[:3] ** 2))), float(np.sqrt(np.mean(density[3:] ** 2)))


#: Column of the packed upper triangle of each entry of a symmetric 3x3 matrix (row-major).
_FROM_UPPER = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]]).ravel()
#: Entries of ``[v]x`` off its diagonal: (row, column, sign, component of v).
_SKEW_ENTRIES = (
    (0, 1, -1, 2),
    (0, 2, 1, 1),
    (1, 0, 1, 2),
    (1, 2, -1, 0),
    (2, 0, -1, 1),
    (2, 1, 1, 0),
)


def _upper_symmetric_products(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out`` (n, 6) = the upper triangle (row-major: 00 01 02 11 12 22) of
    ``[a]x[b]x + [b]x[a]x = a b^T + b a^T - 2 (a . b) I`` for stacks (n, 3); with ``a = b``
    twice ``[a]x^2``. Element by element: no (n, 3, 3) stacks of small products."""
    dot = np.einsum("ni,ni->n", a, b)
    k = 0
    for r in range(3):
        for c in range(r, 3):
            np.multiply(a[:, r], b[:, c], out=out[:, k])
            out[:, k] += a[:, c] * b[:, r]
            if r == c:
                out[:, k] -= 2.0 * dot
            k += 1


def _vec_of_sum(upper: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """``out`` (n, 9) = the column-major vec of ``S + [v]x`` (``A t = (t^T x I) vec A``), with
    ``S`` symmetric given by its upper triangle (n, 6) and ``v`` (n, 3): one column at a time,
    straight into ``out``."""
    for r in range(3):
        out[:, 4 * r] = upper[:, _FROM_UPPER[4 * r]]  # the diagonal: [v]x has none
    for r, c, sign, component in _SKEW_ENTRIES:
        (np.add if sign > 0 else np.subtract)(
            upper[:, _FROM_UPPER[3 * r + c]], v[:, component], out=out[:, r + 3 * c]
        )


#: The base's terms the low-pass filters: [w, f], [dw, df], ddw, the symmetric 3x3 terms by
#: their upper triangles, [w]x^2 and [dw]x[w]x + [w]x[dw]x (halved: the sum of a, b and b, a),
#: and the tilt terms.
_TERMS = Layout(("w_f", 6), ("dw_df", 6), ("ddw", 3), ("ww", 6), ("dw_w", 6), ("q", 4))


def _base_terms(values: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The terms of the base's side of the equations side by side (:data:`_TERMS`), each column
    contiguous (as the low-pass takes them), from the base spline's values and derivatives."""
    T = _TERMS
    terms = np.empty((T.size, len(values))).T
    terms[:, T["w_f"]], terms[:, T["dw_df"]], terms[:, T["ddw"]] = values, first, second[:, 0:3]
    w_raw, dw_raw, f_raw = values[:, 0:3], first[:, 0:3], values[:, 3:6]
    _upper_symmetric_products(w_raw, w_raw, terms[:, T["ww"]])
    terms[:, T["ww"]] *= 0.5
    _upper_symmetric_products(dw_raw, w_raw, terms[:, T["dw_w"]])
    # the tilt terms of a mount leaning with the specific force (model.tilt_columns):
    # [f_y f_z, f_y^2, f_x f_z, f_x^2]
    q = T["q"].start
    for k, (i, j) in enumerate(((1, 2), (1, 1), (0, 2), (0, 0))):
        np.multiply(f_raw[:, i], f_raw[:, j], out=terms[:, q + k])
    return terms


def _base_columns(rows: np.ndarray, X: np.ndarray) -> None:
    """The base's parts of x_g and x_a (in that order, from column 0 of ``X``) from the
    low-passed terms; the time columns ``u`` are the caller's."""
    T, B_g, n_g = _TERMS, GYRO_BASE, GYRO_BASE.size

    def accel(name: str) -> slice:  # x_a's base part, after x_g's in X
        return ACCEL_BASE.shifted(name, n_g)

    w, f = rows[:, T["w_f"]][:, 0:3], rows[:, T["w_f"]][:, 3:6]
    dw, df, ddw = rows[:, T["dw_df"]][:, 0:3], rows[:, T["dw_df"]][:, 3:6], rows[:, T["ddw"]]
    X[:, B_g["w_B"]], X[:, B_g["dw_B"]], X[:, B_g["one"]] = w, dw, 1.0
    X[:, accel("f_B")], X[:, accel("df_B")], X[:, accel("one")] = f, df, 1.0
    X[:, accel("tilt_terms")] = rows[:, T["q"]]
    # vec A = vec([w]x^2 + [dw]x) (column-major), from the symmetric part's upper triangle and
    # the skew part (eq. 12); vec dA likewise from ([dw]x[w]x + [w]x[dw]x) and [ddw]x
    _vec_of_sum(rows[:, T["ww"]], dw, X[:, accel("vec_A")])
    _vec_of_sum(rows[:, T["dw_w"]], ddw, X[:, accel("vec_dA")])


def _window_moments(
    X: np.ndarray,
    spans: list[tuple[int, float, float]],
    at: list[tuple[int, int]],
    names: list[str],
    covered: dict[str, np.ndarray],
) -> dict[str, list[WindowMoments]]:
    """Each window's moments, one Gram matrix of the block's columns per window: the base's
    block shared, each sensor's own rows."""
    n_g, n_a = GYRO_BASE.size, ACCEL_BASE.size
    out: dict[str, list[WindowMoments]] = {name: [] for name in names}
    for (number, start, end), (i0, n_win) in zip(spans, at, strict=True):
        Xw = X[i0 : i0 + n_win]
        G = Xw.T @ Xw
        shared = base_moments(G[:n_g, :n_g], G[n_g : n_g + n_a, n_g : n_g + n_a])
        valid_base = bool(covered[""][i0 : i0 + n_win].all())
        for k, name in enumerate(names):
            gyro = slice(n_g + n_a + GYRO_OWN * k, n_g + n_a + GYRO_OWN * (k + 1))  # [w_I, f_I]
            f_I = GYRO_DATA.shifted("f_I", gyro.start)
            rows_g = np.hstack([G[gyro, gyro], G[gyro, :n_g]])  # [w_I, f_I]^T x_g
            rows_a = np.hstack([G[f_I, f_I], G[f_I, n_g : n_g + n_a]])  # f_I^T x_a
            valid = valid_base and bool(covered[name][i0 : i0 + n_win].all())
            out[name].append(
                WindowMoments(number, start, end, valid, shared, rows_g, rows_a, n_win)
            )
    return out


def _reduce_block(
    spans: list[tuple[int, float, float]],
    rate: float,
    window_s: float,
    lp: Lowpass,
    n_pad: int,
    n_block: int,
    n_after: int,
    base_name: str,
    samples: dict[str, tuple[float, np.ndarray, np.ndarray, np.ndarray]],
) -> dict[str, list[WindowMoments]]:
    """Condition a block of consecutive windows once (per IMU its clock offset, stamps in s,
    ``[gyro, accel]`` and the stamps of saturated readings in ``samples``) and reduce each
    window, for every sensor, to its moments. A window within the low-pass's length of a
    saturated reading is not valid."""
    reach = lp.reach_s
    block_start = spans[0][1]
    grid = block_start + np.arange(-n_pad, n_block + n_after) / rate
    _, t_b, both_b, saturated_b = samples[base_name]
    base = _Spline(t_b, both_b, rate)
    # one zero-phase low-pass for every term of every equation (linear filters commute);
    # the symmetric 3x3 terms are filtered by their upper triangles
    rows = lp(_base_terms(*base(grid, 2)))[n_pad : n_pad + n_block]
    t_rows = grid[n_pad : n_pad + n_block]
    # every data vector of the block side by side, so that each window's moments are one
    # Gram matrix: the base's part of x_g, of x_a, then each sensor's [w_I, f_I]; each
    # column written once into X
    names = [name for name in samples if name != base_name]
    n_base = GYRO_BASE.size + ACCEL_BASE.size
    X = np.empty((n_block, n_base + GYRO_OWN * len(names)))
    _base_columns(rows, X)
    at = [
        (round((start - block_start) * rate), round((end - start) * rate))
        for _, start, end in spans
    ]
    u_g, u_a = GYRO_BASE.index("u"), GYRO_BASE.size + ACCEL_BASE.index("u")
    X[:, u_g] = 0.0
    for (_, start, _), (i0, n_win) in zip(spans, at, strict=True):
        X[i0 : i0 + n_win, u_g] = (t_rows[i0 : i0 + n_win] - start) / window_s
    X[:, u_a] = X[:, u_g]
    # where each stream has data (no gap) and reads the motion (no saturated reading)
    covered = {"": base.covered(t_rows) & ~near(t_rows, saturated_b, reach)}
    for k, name in enumerate(names):
        tau, t_s, both_s, saturated_s = samples[name]
        # the sensor's samples are low-passed at their own rate (with the anti-alias filter)
        sensor = _Spline(t_s, both_s, rate, smooth=lp)
        own = n_base + GYRO_OWN * k  # the sensor's [w_I, f_I], as x_g starts
        X[:, own : own + GYRO_OWN] = sensor(t_rows + tau)[0]
        covered[name] = sensor.covered(t_rows + tau) & ~near(t_rows + tau, saturated_s, reach)
    return _window_moments(X, spans, at, names, covered)


#: Fewest samples of an IMU in a block for its windows there to be reduced.
MIN_SPAN_SAMPLES = 8


def _unused(number: int, start: float, end: float) -> WindowMoments:
    """A window of an IMU that has no samples there (it stopped): kept in the count, not used."""
    dim_g, dim_a = GYRO_BASE.size, ACCEL_BASE.size
    shared = base_moments(np.zeros((dim_g, dim_g)), np.zeros((dim_a, dim_a)))
    info = WindowInfo(
        start, end, 0.0, float("inf"), False, np.full(3, np.inf), np.zeros(3, dtype=bool), False
    )
    return WindowMoments(
        number,
        start,
        end,
        False,
        shared,
        np.zeros((6, 6 + dim_g)),
        np.zeros((3, 3 + dim_a)),
        0,
        info,
    )


def _longest_covered(grid: np.ndarray, covered: list[np.ndarray], margin: int) -> np.ndarray:
    """The longest stretch of ``grid`` that every IMU covers (no gap), less ``margin`` points at
    each end (where a filter would reach into the gap): the boot's units and clock offsets are
    measured on it, never across a gap."""
    runs = true_runs(np.logical_and.reduce(covered))
    if not runs:
        return grid[:0]
    a, b = max(runs, key=lambda r: r[1] - r[0])
    return grid[a + margin : b - margin]


class StreamingCalibrator:
    """Feed IMU samples as they are read; ask for the estimate at any time.

    Windows are reduced ``block_windows`` at a time (faster in batch); a live system that wants
    an estimate after every window passes ``block_windows=1``. Memory holds the raw samples of
    about one block plus two small matrices per window and sensor.

    >>> cal = StreamingCalibrator(sensors, base_name="base")        # doctest: +SKIP
    >>> for imu, t_ns, gyro, accel in batches:                      # doctest: +SKIP
    ...     cal.add(imu, t_ns, gyro, accel)
    >>> estimates = cal.finish()                                    # doctest: +SKIP
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
    ) -> None:
        if not sensors:
            raise ValueError("no sensors")
        sensors = self._place_base(sensors, base_pose)
        self.sensors = {s.name: s for s in sensors}
        self.base_name = base_name
        opts = sensors[0].options
        self.rate = opts.resample_hz
        self.window_s = opts.window_s
        self.max_offset = max(s.options.max_time_offset_s for s in sensors)
        self.lowpass = Lowpass(opts.lowpass_hz, self.rate)
        self.buffers = {base_name: _Buffer(), **{name: _Buffer() for name in self.sensors}}
        self.t_ref_ns: int | None = None
        self.next_window = 0
        self.windows: dict[str, list[WindowMoments]] = {name: [] for name in self.sensors}
        self.tau0: dict[str, float] = {}
        #: Each sensor's clock offset as the boot's correlation placed it (None: not estimated).
        self.time_offsets: dict[str, TimeOffset | None] = {}
        #: Per IMU, the factors (gyro, accelerometer) that made its samples SI, from the boot on.
        self.scales: dict[str, tuple[float, float]] = {}
        self.unit_warnings: dict[str, list[str]] = {}
        self.base_units = base_units
        #: Per IMU, (topic, config key path) for messages.
        self.labels = {base_name: base_label, **{s.name: (s.topic, s.key) for s in sensors}}
        self.dw_noise_var = 0.0
        self._boot_horizon_s = BOOT_S
        self.noise: dict[str, tuple[float, float]] = {}
        self.sigma: dict[str, tuple[float, float]] = {}
        #: Median sample rate of every IMU (Hz), measured at boot.
        self.rates_hz: dict[str, float] = {}
        self.finished = False
        #: Checks of the whole rig made at boot, counted in every sensor's status.
        self.given_checks: tuple[Check, ...] = ()
        self.block_windows = max(1, int(block_windows))
        #: How far out of order stamps may arrive (s): windows wait this long for them.
        self.reorder_s = reorder_s
        #: Per IMU that stopped sending while the others went on: [from, to] seconds from the
        #: origin of each silence (``to`` None while it lasts).
        self.silences: dict[str, list[list[float | None]]] = {}
        #: Per IMU, where it read values that are not the motion (its readings as sent).
        self.saturation = {name: Saturation() for name in self.buffers}

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
        unit_warnings: dict[str, list[str]] = {}
        splines = {  # the gyros': the boot reads only |w| (half the work of both triads)
            n: _Spline(self._seconds(t), b[:, :3], self.rate) for n, (t, b) in samples.items()
        }
        grid = _longest_covered(
            grid, [spline.covered(grid) for spline in splines.values()], self.lowpass.pad
        )
        if len(grid) < self.lowpass.pad:
            return False  # no stretch that every IMU covers yet
        raw_speeds = {
            name: np.linalg.norm(self.lowpass(spline.gyro(grid)), axis=1)
            for name, spline in splines.items()
        }
        scales = self._units(samples, raw_speeds, unit_warnings, final=not patient)
        if scales is None:
            return False  # not enough motion yet to tell the gyros' units
        speeds = {name: raw_speeds[name] * scales[name][0] for name in samples}  # |w| scales
        sigma = self._noise_levels(samples, scales)
        offsets = self._clock_offsets(grid, speeds, sigma, splines, scales)
        if patient and not all(o.shown for o in offsets.values()):
            return False  # not enough motion yet to place every clock offset
        # booted: the buffers from now on in SI
        for name, (_, both) in full.items():
            if scales[name] != (1.0, 1.0):
                both *= np.repeat(scales[name], 3)  # the stored samples, in place
        self.scales, self.unit_warnings, self.sigma = scales, unit_warnings, sigma
        # the base's mean specific force over the boot, in B's axes (turned as it came)
        self.given_checks = (base_gravity(samples[self.base_name][1][:, 3:].mean(axis=0)),)
        self.dw_noise_var = derivative_noise_variance(self.lowpass, self.noise[self.base_name][0])
        for name in self.sensors:
            offset = offsets.get(name)
            self.time_offsets[name] = offset
            self.tau0[name] = offset.tau_s if offset is not None and offset.shown else 0.0
        return True

    def _noise_levels(
        self,
        samples: dict[str, tuple[np.ndarray, np.ndarray]],
        scales: dict[str, tuple[float, float]],
    ) -> dict[str, tuple[float, float]]:
        """Each IMU's rate and white noise (kept), and each sensor's residual noise per grid
        sample against the base (gyro, accelerometer)."""
        for name, (t, both) in samples.items():
            rate = 1.0 / (float(np.median(np.diff(t))) * 1e-9)  # the IMU's own, as _Spline takes it
            _, uniform = filled((t - t[0]) * 1e-9, both, 1.0 / rate)  # (as a uniform series)
            self.noise[name] = _noise_density(uniform * np.repeat(scales[name], 3), rate)
            self.rates_hz[name] = rate
        gb, ab = self.noise[self.base_name]
        sigma = {}
        for name in self.sensors:
            gs, as_ = self.noise[name]
            sigma[name] = (
                float(np.sqrt((gs**2 + gb**2) * self.rate)),
                float(np.sqrt((as_**2 + ab**2) * self.rate)),
            )
        return sigma

    def _refine_offsets(
        self,
        offsets: dict[str, TimeOffset],
        grid: np.ndarray,
        splines: dict[str, _Spline],
        speeds: dict[str, np.ndarray],
        scales: dict[str, tuple[float, float]],
    ) -> None:
        """Each placed offset refined below the grid's step, by the sensor's own spline: the
        one minimising the squared difference of the two ``|w|`` (:func:`refine_time_offset`)."""
        base_speed = speeds[self.base_name] - speeds[self.base_name].mean()
        for name, found in offsets.items():
            if not found.shown:
                continue

            def misfit(
                tau: float, spline: _Spline = splines[name], k: float = scales[name][0]
            ) -> float:
                speed = k * np.linalg.norm(self.lowpass(spline.gyro(grid + tau)), axis=1)
                return -float(np.sum((speed - speed.mean() - base_speed) ** 2))

            tau = refine_time_offset(found.tau_s, 1.0 / self.rate, misfit)
            offsets[name] = replace(found, tau_s=tau)

    def _clock_offsets(
        self,
        grid: np.ndarray,
        speeds: dict[str, np.ndarray],
        sigma: dict[str, tuple[float, float]],
        splines: dict[str, _Spline],
        scales: dict[str, tuple[float, float]],
    ) -> dict[str, TimeOffset]:
        """Each sensor's clock offset from the correlation of ``|w|`` with the base's, refined
        by its own spline (:meth:`_refine_offsets`)."""
        offsets = {}
        gain = self.lowpass.white_noise_gain()
        for name, setup in self.sensors.items():
            if setup.options.max_time_offset_s > 0:
                offsets[name] = time_offset_shown(
                    grid,
                    speeds[self.base_name],
                    speeds[name],
                    setup.options.max_time_offset_s,
                    sigma[name][0],
                    gain,
                )
        self._refine_offsets(offsets, grid, splines, speeds, scales)
        return offsets

    def _label(self, name: str, key: str) -> tuple[str, str]:
        topic, path = self.labels.get(name, ("", ""))
        return topic or name, f"{path or name}.{key}"

    def _accel_scale(
        self, name: str, both: np.ndarray, accel_units: str, notes: dict[str, list[str]]
    ) -> float:
        """The factor that makes an accelerometer's samples m/s^2: as declared, or (``auto``)
        by its mean ``|f|``, about 1 for g and 9.8 for m/s^2."""
        if accel_units != "auto":
            return GRAVITY_MPS2 if accel_units == "g" else 1.0
        mean = float(np.mean(np.linalg.norm(both[:, 3:], axis=1)))
        if 0.5 <= mean <= 2.0:
            notes.setdefault(name, []).append(
                f"accelerometer publishes g (mean |f| {mean:.3f}): converted to m/s^2"
            )
            return GRAVITY_MPS2
        if not 5.0 <= mean <= 20.0:
            raise UnitsError(
                *self._label(name, "accel_units"),
                f"the accelerometer's mean |f| is {mean:.3g}: neither m/s^2 (about 9.8) "
                "nor g (about 1)",
            )
        return 1.0

    def _units(
        self,
        samples: dict[str, tuple[np.ndarray, np.ndarray]],
        speeds: dict[str, np.ndarray],
        notes: dict[str, list[str]],
        final: bool,
    ) -> dict[str, tuple[float, float]] | None:
        """Per IMU, the factors (gyro, accelerometer) that make its samples SI: as its setup
        says, or, for ``auto``, an accelerometer whose ``|f|`` averages about 1 publishes g and
        a gyro whose ``|w|`` varies 57.3 times as much as the base's (or the base's as much as
        a sensor's / 57.3) publishes deg/s. None while the base has not moved enough to tell."""
        units = {
            self.base_name: self.base_units,
            **{name: (s.gyro_units, s.accel_units) for name, s in self.sensors.items()},
        }
        scales: dict[str, list[float]] = {}
        for name, (gyro_units, accel_units) in units.items():
            accel = self._accel_scale(name, samples[name][1], accel_units, notes)
            scales[name] = [{"dps": np.radians(1.0)}.get(gyro_units, 1.0), accel]
        auto = [name for name, (gyro_units, _) in units.items() if gyro_units == "auto"]
        spread = {name: float(np.std(speed)) * scales[name][0] for name, speed in speeds.items()}
        moving = spread[self.base_name] >= MIN_UNIT_MOTION_RADPS
        if auto and not moving and not final:
            return None
        if auto and moving:  # (never moving: taken as declared)
            ratios = {name: spread[name] / spread[self.base_name] for name in self.sensors}
            if self.base_name in auto and any(
                abs(np.log(r * DPS)) < np.log(2.0) for r in ratios.values()
            ):
                scales[self.base_name][0] = np.radians(1.0)
                notes.setdefault(self.base_name, []).append(
                    "gyro publishes deg/s (the sensors' |w| varies 57.3 times less): converted to "
                    "rad/s"
                )
                ratios = {name: r * DPS for name, r in ratios.items()}
            for name, ratio in ratios.items():
                if name not in auto:
                    continue
                if abs(np.log(ratio / DPS)) < np.log(2.0):
                    scales[name][0] = np.radians(1.0)
                    notes.setdefault(name, []).append(
                        f"gyro publishes deg/s (|w| varies {ratio:.1f} times the base's): "
                        "converted to rad/s"
                    )
                elif abs(np.log(ratio)) >= np.log(2.0):
                    raise UnitsError(
                        *self._label(name, "gyro_units"),
                        f"the gyro's |w| varies {ratio:.3g} times the base's: neither rad/s (1) "
                        "nor deg/s (57.3)",
                    )
        return {name: (g, a) for name, (g, a) in scales.items()}

    def process(self, final: bool = False, whole_blocks: bool = True) -> int:
        """Reduce every window all IMUs now cover, ``block_windows`` at a time (one spline and
        one filter pass per IMU and block); returns how many. Without ``whole_blocks`` (a
        follower that caught up with the recording), the windows covered so far are reduced
        in a block that is not whole."""
        need = self.block_windows if whole_blocks else 1
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
                        end = min(end, covered - self.max_offset - PAD_S)
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
            keep_from = spans[-1][1] + self.window_s - PAD_S - self.max_offset - 1.0
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
        return end + PAD_S + self.max_offset + (0.0 if final else self.reorder_s)

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
        """Condition a block of consecutive windows once and reduce each to its moments."""
        block_start, block_end = spans[0][1], spans[-1][2]
        n_pad = round(PAD_S * self.rate)
        n_block = round((block_end - block_start) * self.rate)
        last = self._covered_until() - self.max_offset - 2.0 / self.rate  # never extrapolate
        n_after = int(np.clip(np.floor((last - block_end) * self.rate), 0, n_pad))
        # the samples the grid needs (as in _reduce_block), with a margin
        grid_first, grid_last = block_start + np.array([-n_pad, n_block + n_after - 1]) / self.rate
        first_s, last_s = grid_first - 3.0 / self.rate - 0.1, grid_last + 3.0 / self.rate + 0.1
        samples = {}
        for name, tau in [
            (self.base_name, 0.0),
            *((name, self.tau0[name]) for name in self.sensors),
        ]:
            t, both = self.buffers[name].cleaned()
            t = self._seconds(t)  # sorted (cleaned): the samples in the span are a slice
            a, b = (
                int(np.searchsorted(t, first_s + tau, side="left")),
                int(np.searchsorted(t, last_s + tau, side="right")),
            )
            if b - a >= MIN_SPAN_SAMPLES:  # an IMU that stopped has none: its windows are not used
                saturated = self._saturated(name, first_s + tau - self.lowpass.reach_s)
                samples[name] = (tau, t[a:b], both[a:b], saturated)
        args = (spans, self.rate, self.window_s, self.lowpass, n_pad, n_block, n_after)
        has_base = self.base_name in samples
        reduced = _reduce_block(*args, self.base_name, samples) if has_base else {}
        for name in self.sensors:
            self.windows[name].extend(
                reduced.get(name) or [_unused(number, start, end) for number, start, end in spans]
            )

    def _saturated(self, name: str, from_s: float) -> np.ndarray:
        """The stamps (s) from ``from_s`` on where IMU ``name`` read its full scale (either
        triad, where it saturates, and the clipped samples reading dropped)."""
        assert self.t_ref_ns is not None
        from_ns = self.t_ref_ns + int(from_s * 1e9)
        stamps = self.saturation[name].after(from_ns, self.scales.get(name, (1.0, 1.0)))
        return self._seconds(stamps)

    def _ensure_infos(self, name: str) -> list[WindowMoments]:
        """Fill in the observability of windows that lack it (all at once)."""
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
                window.info = info
        return windows

    # ---------------------------------------------------------------- output

    def finish(self) -> dict[str, SensorEstimate]:
        """Reduce what is left and return the final estimates."""
        if self.t_ref_ns is None:
            raise TooLittleData(
                "too little data: no samples from "
                + ", ".join(n for n, b in self.buffers.items() if b.first_ns is None)
            )
        self.process(final=True)
        self.finished = True
        return self.estimates()

    def estimates(self) -> dict[str, SensorEstimate]:
        """The estimate from the windows reduced so far (every sensor)."""
        return {name: self.estimate(name) for name in self.sensors}

    def estimate(self, name: str) -> SensorEstimate:
        """One sensor's estimate from the windows reduced so far (each sensor's is independent
        of the others': they may be solved apart, in any order)."""
        setup = self.sensors[name]
        windows = self._ensure_infos(name)
        tau0 = self.tau0.get(name, 0.0)
        offset = self.time_offsets.get(name)
        if not any(w.info is not None and w.info.selected for w in windows):
            estimate = unobservable(
                setup.prior_T_base_imu, [w.info for w in windows if w.info], tau0
            )
        else:
            clock = ClockEvidence(
                tau0, offset is None or offset.shown, offset.reason if offset is not None else ""
            )
            try:
                estimate = solve(
                    windows,
                    setup.prior_T_base_imu,
                    setup.options,
                    clock,
                    self.sigma[name],
                    self.lowpass,
                    dw_noise_var=self.dw_noise_var,
                    given=self.given_checks,
                )
            except np.linalg.LinAlgError as exc:  # the solver's to say, never the log's fault
                infos = [w.info for w in windows if w.info]
                estimate = unobservable(setup.prior_T_base_imu, infos, tau0)
                estimate = replace(estimate, warnings=[unsolved_sentence(str(exc))])
        T = estimate.T_base_imu  # from the base IMU's position back to B's origin
        T = Transform(T.rotation, T.translation + self.t_base_baseimu)
        return replace(estimate, T_base_imu=T, warnings=self._unit_notes(name) + estimate.warnings)

    def _unit_notes(self, name: str) -> list[str]:
        """The units converted on the way, the IMUs that saturate and those that stopped while
        others went on, the base's first."""
        notes = [
            f"base: {w}" for w in self.unit_warnings.get(self.base_name, [])
        ] + self.unit_warnings.get(name, [])
        for imu in (self.base_name, name):
            notes += self._saturation_notes(imu)
            for start, end in self.silences.get(imu, []):
                topic = self.labels[imu][0] or imu
                notes.append(
                    f"{topic} sent nothing from {start:.1f} s"
                    + (f" to {end:.1f} s" if end is not None else " to the end of the log")
                    + " while the other IMUs went on: the windows there are not used for "
                    + ("any sensor" if imu == self.base_name else "this sensor")
                )
        return notes

    def _saturation_notes(self, imu: str) -> list[str]:
        scales = self.scales.get(imu, (1.0, 1.0))
        topic = self.labels[imu][0] or imu
        saturation = self.saturation[imu]
        return [
            f"{topic}: the {triad_name} saturates at {triad.level * scale:.4g} {unit} "
            f"({triad.readings} readings there): the windows that hold one are not used"
            for triad, triad_name, unit, scale, saturates in zip(
                saturation.triads,
                ("gyro", "accelerometer"),
                ("rad/s", "m/s^2"),
                scales,
                saturation.saturated(scales),
                strict=True,
            )
            if saturates
        ]

    def window_infos(self, name: str) -> list[WindowInfo]:
        return [w.info for w in self._ensure_infos(name) if w.info is not None]

    def duplicates(self, imu: str) -> int:
        return self.buffers[imu].duplicates
