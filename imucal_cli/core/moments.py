"""Each window reduced to the second moments of its data vectors (:mod:`.model`'s layouts),
and the builder that does it for a block of windows (:func:`reduce_block`): the base's terms
low-passed once, every data vector side by side, one Gram matrix per window.

The base's part of each data vector is shared by every sensor, so a window's moments are held
as the base's block (upper triangles, once per window) and each sensor's own rows.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.clock import Offset, window_offsets
from imucal_cli.core.model import (
    ACCEL_BASE,
    ACCEL_DATA,
    ACCEL_OWN,
    GYRO_BASE,
    GYRO_DATA,
    GYRO_OWN,
    BiasModel,
    Layout,
)
from imucal_cli.core.resample import ALIAS_GAIN, Spline
from imucal_cli.core.segments import WindowInfo
from imucal_cli.core.signals import Lowpass, near, white_noise_density

#: Where each IMU's white noise is measured (Hz): above the motion the low-pass keeps, below
#: the internal filters of MEMS parts.
NOISE_BAND_HZ = (10.0, 20.0)


@dataclass(frozen=True)
class BaseMoments:
    """The base IMU's block of a window's moments, shared by every sensor (upper triangles)."""

    packed_gyro: np.ndarray  # of the (8, 8) block of x_g's base part (GYRO_BASE)
    packed_accel: np.ndarray  # of the (30, 30) block of x_a's base part (ACCEL_BASE)


@dataclass
class WindowMoments:
    """One window reduced to what the estimator needs: the second moments ``S = sum x x^T``,
    held as the base's block (shared between sensors) and the sensor's own rows."""

    number: int
    start_s: float
    end_s: float
    valid: bool  # no gap in either stream
    base: BaseMoments
    rows_gyro: np.ndarray  # (6, 14): [w_I, f_I]^T x_g
    rows_accel: np.ndarray  # (3, 33): f_I^T x_a
    samples: int
    info: WindowInfo | None = None  # observability, filled in (in bulk) when first needed
    offset_s: float = 0.0  # the sensor's clock offset it was resampled at (its middle)
    shift_s: float = 0.0  # the clock's track there beyond ``offset_s`` (the solve takes it)
    #: Window numbers it covers from ``number`` on (its bias knots: at ``number`` and
    #: ``number + span``), and how many windows it stands for: more than one where old windows
    #: were merged (:func:`merged`).
    span: int = 1
    count: int = 1
    left_out: int = 0  # of those, windows not used (no data, a gap, too little motion)


_UPPER = {"gyro": np.triu_indices(GYRO_BASE.size), "accel": np.triu_indices(ACCEL_BASE.size)}


def base_moments(G_gyro: np.ndarray, G_accel: np.ndarray) -> BaseMoments:
    """The base block from the Gram matrices ``X^T X`` of the base part of the data vectors,
    (8, 8) for the gyro and (30, 30) for the accelerometer."""
    return BaseMoments(G_gyro[_UPPER["gyro"]], G_accel[_UPPER["accel"]])


def assemble_moments(windows: Sequence[WindowMoments], which: str) -> np.ndarray:
    """The full moments ``S`` of several windows, (K, dim, dim), ``which`` "gyro" or "accel"."""
    if which == "gyro":
        dim, own = GYRO_DATA.size, GYRO_OWN
        rows = np.stack([w.rows_gyro for w in windows])
        packed = np.stack([w.base.packed_gyro for w in windows])
    else:
        dim, own = ACCEL_DATA.size, ACCEL_OWN
        rows = np.stack([w.rows_accel for w in windows])
        packed = np.stack([w.base.packed_accel for w in windows])
    upper = _UPPER[which]
    full = np.empty((len(windows), dim, dim))
    full[:, own + upper[0], own + upper[1]] = packed
    full[:, own + upper[1], own + upper[0]] = packed
    full[:, 0:own, :] = rows
    full[:, :, 0:own] = rows.transpose(0, 2, 1)
    return full


def constant_moments(windows: Sequence[WindowMoments], which: str) -> np.ndarray:
    """Each window's ``one`` column's own moment (``which`` "gyro" or "accel"): its samples, a
    merged stretch's weight of its constant; read from the base's block, nothing assembled."""
    layout, own = (GYRO_DATA, GYRO_OWN) if which == "gyro" else (ACCEL_DATA, ACCEL_OWN)
    i = layout.index("one") - own
    rows, columns = _UPPER[which]
    at = int(np.flatnonzero((rows == i) & (columns == i))[0])
    packed = [w.base.packed_gyro if which == "gyro" else w.base.packed_accel for w in windows]
    return np.array([p[at] for p in packed], dtype=float)


def noise_density(both: np.ndarray, rate: float) -> tuple[float, float]:
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


def upper_symmetric_products(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
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


def vec_of_sum(upper: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
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


def _base_terms(
    values: np.ndarray, first: np.ndarray, second: np.ndarray, gyro_bias: np.ndarray | None
) -> np.ndarray:
    """The terms of the base's side of the equations side by side (:data:`_TERMS`), each column
    contiguous (as the low-pass takes them), from the base spline's values and derivatives; the
    lever arm's terms from the rates less ``gyro_bias`` (the base gyro's, where known)."""
    T = _TERMS
    terms = np.empty((T.size, len(values))).T
    terms[:, T["w_f"]], terms[:, T["dw_df"]], terms[:, T["ddw"]] = values, first, second[:, 0:3]
    w_raw, dw_raw, f_raw = values[:, 0:3], first[:, 0:3], values[:, 3:6]
    if gyro_bias is not None:
        w_raw = w_raw - gyro_bias
    upper_symmetric_products(w_raw, w_raw, terms[:, T["ww"]])
    terms[:, T["ww"]] *= 0.5
    upper_symmetric_products(dw_raw, w_raw, terms[:, T["dw_w"]])
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
    vec_of_sum(rows[:, T["ww"]], dw, X[:, accel("vec_A")])
    vec_of_sum(rows[:, T["dw_w"]], ddw, X[:, accel("vec_dA")])


def _window_moments(
    X: np.ndarray,
    spans: list[tuple[int, float, float]],
    at: list[tuple[int, int, int]],
    names: list[str],
    covered: dict[str, np.ndarray],
) -> dict[str, list[WindowMoments]]:
    """Each window's moments, one Gram matrix of the block's columns per window (rows
    ``i0 .. i0 + n`` of ``X``, ``samples`` grid samples: each row stands for ``samples / n``
    of them): the base's block shared, each sensor's own rows."""
    n_g, n_a = GYRO_BASE.size, ACCEL_BASE.size
    out: dict[str, list[WindowMoments]] = {name: [] for name in names}
    for (number, start, end), (i0, n_win, samples) in zip(spans, at, strict=True):
        Xw = X[i0 : i0 + n_win]
        G = Xw.T @ Xw
        # each row stands for its share of the window's samples: the "one" column sums to
        # their count, as the moments' means and scatters take it
        if n_win and samples != n_win:
            G *= samples / n_win
        shared = base_moments(G[:n_g, :n_g], G[n_g : n_g + n_a, n_g : n_g + n_a])
        valid_base = bool(covered[""][i0 : i0 + n_win].all())
        for k, name in enumerate(names):
            gyro = slice(n_g + n_a + GYRO_OWN * k, n_g + n_a + GYRO_OWN * (k + 1))  # [w_I, f_I]
            f_I = GYRO_DATA.shifted("f_I", gyro.start)
            rows_g = np.hstack([G[gyro, gyro], G[gyro, :n_g]])  # [w_I, f_I]^T x_g
            rows_a = np.hstack([G[f_I, f_I], G[f_I, n_g : n_g + n_a]])  # f_I^T x_a
            valid = valid_base and bool(covered[name][i0 : i0 + n_win].all())
            out[name].append(
                WindowMoments(number, start, end, valid, shared, rows_g, rows_a, samples)
            )
    return out


def moment_step(lp: Lowpass) -> int:
    """Every how many grid samples one enters the moments, each standing for that many: the
    most that leaves the low-pass's response at the rate they are taken at below
    :data:`~.resample.ALIAS_GAIN`. The windows' sums are then the grid's to that (what the
    filter passes has nothing there to alias onto the sums), and every equation holds at
    each row taken as it does at every grid sample (exact on noise-free data)."""
    step = 1
    while lp.gain(np.array([lp.rate_hz / (step + 1)]))[0] <= ALIAS_GAIN:
        step += 1
    return step


def _window_rows(
    spans: list[tuple[int, float, float]], rate: float, step: int, phase: int
) -> list[tuple[int, int, int]]:
    """Per window of a block: its first row among the block's grid samples ``phase``,
    ``phase + step``, ..., how many rows it has, and how many grid samples it spans."""
    at = []
    block_start = spans[0][1]
    for _, start, end in spans:
        first, samples = round((start - block_start) * rate), round((end - start) * rate)
        i0 = -(-(first - phase) // step)
        at.append((i0, -(-(first + samples - phase) // step) - i0, samples))
    return at


def _time_columns(
    X: np.ndarray,
    spans: list[tuple[int, float, float]],
    at: list[tuple[int, int, int]],
    t_rows: np.ndarray,
    window_s: float,
) -> None:
    """The time columns ``u`` of x_g and x_a: each row's time in its window, in windows."""
    u_g, u_a = GYRO_BASE.index("u"), GYRO_BASE.size + ACCEL_BASE.index("u")
    X[:, u_g] = 0.0
    for (_, start, _), (i0, n_win, _) in zip(spans, at, strict=True):
        X[i0 : i0 + n_win, u_g] = (t_rows[i0 : i0 + n_win] - start) / window_s
    X[:, u_a] = X[:, u_g]


def reduce_block(
    spans: list[tuple[int, float, float]],
    rate: float,
    window_s: float,
    lp: Lowpass,
    n_pad: int,
    n_block: int,
    n_after: int,
    base_name: str,
    samples: dict[str, tuple[Offset, np.ndarray, np.ndarray, np.ndarray]],
    measured: dict[str, list[tuple[float, float] | None]] | None = None,
    base_gyro_bias: np.ndarray | None = None,
) -> dict[str, list[WindowMoments]]:
    """Condition a block of consecutive windows once (per IMU its clock offset as a function
    of the grid's times, stamps in s, ``[gyro, accel]`` and the stamps of saturated
    readings in ``samples``) and reduce each window, for every sensor, to its moments. A window
    within the low-pass's length of a saturated reading is not valid. Sensors named in
    ``measured`` get each window's offset beyond theirs there (:func:`~.clock.window_offsets`)."""
    reach = lp.reach_s
    block_start = spans[0][1]
    grid = block_start + np.arange(-n_pad, n_block + n_after) / rate
    _, t_b, both_b, saturated_b = samples[base_name]
    base = Spline(t_b, both_b, rate)
    # one zero-phase low-pass for every term of every equation (linear filters commute);
    # the symmetric 3x3 terms are filtered by their upper triangles; the moments take every
    # step-th row (:func:`moment_step`)
    step = moment_step(lp)
    phase = -round(block_start * rate) % step  # (rows on the log's grid, however blocked)
    values, first, second = base(grid, 2)
    rows = lp(_base_terms(values, first, second, base_gyro_bias))[
        n_pad + phase : n_pad + n_block : step
    ]
    t_rows = grid[n_pad + phase : n_pad + n_block : step]
    # every data vector of the block side by side, so that each window's moments are one
    # Gram matrix: the base's part of x_g, of x_a, then each sensor's [w_I, f_I]; each
    # column written once into X
    names = [name for name in samples if name != base_name]
    n_base = GYRO_BASE.size + ACCEL_BASE.size
    X = np.empty((len(t_rows), n_base + GYRO_OWN * len(names)))
    _base_columns(rows, X)
    at = _window_rows(spans, rate, step, phase)
    _time_columns(X, spans, at, t_rows, window_s)
    # where each stream has data (no gap) and reads the motion (no saturated reading)
    covered = {"": base.covered(t_rows) & ~near(t_rows, saturated_b, reach)}
    for k, name in enumerate(names):
        tau, t_s, both_s, saturated_s = samples[name]
        # the sensor's samples are low-passed at their own rate (with the anti-alias filter)
        sensor = Spline(t_s, both_s, rate, smooth=lp)
        own = n_base + GYRO_OWN * k  # the sensor's [w_I, f_I], as x_g starts
        at_s = t_rows + tau(t_rows)
        X[:, own : own + GYRO_OWN] = sensor(at_s)[0]
        covered[name] = sensor.covered(at_s) & ~near(at_s, saturated_s, reach)
        if measured is not None and name in measured:
            B_g = GYRO_BASE
            valid = covered[name] & covered[""]
            w_B, dw_B = X[:, B_g["w_B"]], X[:, B_g["dw_B"]]
            gain = lp.white_noise_gain() * step  # (the rows are step grid samples apart)
            rows_at = [(i0, n) for i0, n, _ in at]
            measured[name] = window_offsets(w_B, dw_B, X[:, own : own + 3], valid, rows_at, gain)
    return _window_moments(X, spans, at, names, covered)


#: Fewest samples of an IMU in a block for its windows there to be reduced.
MIN_SPAN_SAMPLES = 8


def shifted(S: np.ndarray, shifts_s: np.ndarray, layout: Layout) -> np.ndarray:
    """Windows' moments ``S`` (K, dim, dim) as if each had been resampled ``shifts_s`` later
    on the base's clock (the clock's track there beyond the offset it was resampled at):
    ``M S M^T`` with ``x' = M x = x + s E x`` the base's terms less ``s`` times their
    derivatives, since the model's ``dtau`` columns are those derivatives
    (``C(dtau + s) x = C(dtau) M x``, exact: the coefficients are linear in ``dtau``)."""
    E = np.zeros((layout.size, layout.size))
    pairs = (("w_B", "dw_B"),) if "w_B" in layout.slices else (("f_B", "df_B"), ("vec_A", "vec_dA"))
    for term, derivative in pairs:
        E[layout[term], layout[derivative]] = -np.eye(layout[term].stop - layout[term].start)
    s = np.asarray(shifts_s, dtype=float)[:, None, None]
    ES = E @ S
    return S + s * (ES + ES.transpose(0, 2, 1)) + s**2 * (ES @ E.T)


def used(window: WindowMoments) -> bool:
    """Whether the window's moments enter the estimate: it has data, no gap, and its motion
    selected it (a merged stretch, whose observability is computed when first needed, is of
    selected windows only)."""
    if not (window.valid and window.samples):
        return False
    return window.info.selected if window.info is not None else window.count > 1


def merged(
    windows: Sequence[WindowMoments],
    shifts_s: np.ndarray,
    offset_s: float,
    biases: BiasModel,
    sigma: tuple[float, float],
) -> WindowMoments:
    """Consecutive windows as one stretch between their first and last bias knots: each moved
    to the clock offset the track gives it (``shifts_s`` beyond the one it was resampled at),
    and the knots between them eliminated under the biases' random walk and prior
    (:func:`stretch_moments`), so that the fit of the stretch is the fit of its windows, at the
    residual std ``sigma`` (gyro, accelerometer) the fit starts from. Windows not used
    (``valid`` False or not selected) are counted and add no data; their knots still walk."""
    first, last = windows[0], windows[-1]
    units = [(w.number, w.span) for w in windows]
    totals = []
    for k, (which, layout, own) in enumerate(
        (("gyro", GYRO_DATA, GYRO_OWN), ("accel", ACCEL_DATA, ACCEL_OWN))
    ):
        moved = assemble_moments(windows, which)
        moved[[not used(w) for w in windows]] = 0.0  # (a window not used adds no data)
        if np.any(shifts_s):
            moved = shifted(moved, shifts_s, layout)
        totals.append((stretch_moments(moved, units, layout, sigma[k], biases, k), own))
    (S_g, own_g), (S_a, own_a) = totals
    kept = [w for w in windows if used(w)]
    whole = all(w.valid for w in windows)  # (no gap in any: what was not used lacked motion)
    count = sum(w.count for w in windows)
    left_out = sum(w.left_out if used(w) else w.count for w in windows)
    info = None  # (its observability: computed when first needed, as a window's)
    if not kept:
        info = WindowInfo(
            first.start_s,
            last.end_s,
            0.0,
            float("inf"),
            False,
            np.full(3, np.inf),
            np.zeros(3, dtype=bool),
            whole,
            count,
            count,
        )
    return WindowMoments(
        first.number,
        first.start_s,
        last.end_s,
        bool(kept) or whole,
        base_moments(S_g[own_g:, own_g:], S_a[own_a:, own_a:]),
        S_g[:own_g].copy(),
        S_a[:own_a].copy(),
        sum(w.samples for w in kept),
        info,
        offset_s,
        0.0,
        last.number + last.span - first.number,
        count,
        left_out,
    )


#: A unit's ``one`` and ``u`` columns' coefficients from its two knots ``(b_j, b_k)``: ``-b_j``
#: and ``b_j - b_k`` (its bias is ``b_j (1 - u) + b_k u``), and back.
_TO_KNOTS = np.array([[-1.0, 0.0], [1.0, -1.0]])
_FROM_KNOTS = np.linalg.inv(_TO_KNOTS)


def stretch_moments(
    S: np.ndarray,
    units: Sequence[tuple[int, int]],
    layout: Layout,
    sigma: float,
    biases: BiasModel,
    kind: int,
) -> np.ndarray:
    """The moments of consecutive units (``S``, (K, dim, dim); ``units`` their first window's
    number and how many they span, between their two bias knots) as one unit between the first
    and the last knot: exact for the fit.

    A unit's residual on each axis is ``c . x - b_j (1 - u) - b_k u``: linear in its knots,
    which enter through the ``one`` and ``u`` columns. Over ``y = [c, knots]`` (the units' ends
    and every window's knot where the units leave a gap) the cost is ``y^T Q y``: the units'
    moments and, in the moments' units (the fit weighs them by ``1 / sigma^2``), the random
    walk between neighbouring knots (``biases``', of its ``kind``: 0 the gyro's, 1 the
    accelerometer's; the walk's prior at its start is the fit's, at its first knot). The inner knots
    are eliminated (Schur complement), and what is left less the walk between the two ends
    (the fit's prior holds that one: they are its knots) is written back over the data
    vector's columns. For any ``c`` and end knots the stretch's cost is then the least of the
    units' over the inner knots, as the fit of the units themselves finds it: the biases keep
    their walk inside the stretch (one line over minutes is not what a wandering bias does,
    and the std would not know its error). Every axis takes the same moments: their knots walk
    alike."""
    r = layout.size - 2
    assert (layout.index("one"), layout.index("u")) == (r, r + 1)  # (the last two columns)
    numbers = knot_numbers(units).tolist()  # (the ends, and every knot where units leave a gap)
    at = {number: i for i, number in enumerate(numbers)}
    Q = np.zeros((r + len(numbers), r + len(numbers)))  # over y = [c, knots]
    Q[:r, :r] = S[:, :r, :r].sum(axis=0)
    for S_k, (number, span) in zip(S, units, strict=True):
        knots = r + np.array([at[number], at[number + span]])
        Q[:r, knots] += S_k[:r, r:] @ _TO_KNOTS
        Q[knots[:, None], knots] += _TO_KNOTS.T @ S_k[r:, r:] @ _TO_KNOTS
    Q[r:, :r] = Q[:r, r:].T
    var = sigma**2
    for a, b in itertools.pairwise(numbers):
        info = float(biases.walk_information(kind, (b - a) * biases.spacing_s))
        _add_walk(Q, r + at[a], r + at[b], var * info)
    n = len(Q)
    inner = np.arange(r + 1, n - 1)
    # [c, b_0, b_m] first, the inner knots after them
    ends_first = np.r_[0 : r + 1, n - 1, inner]
    Q = Q[ends_first][:, ends_first]
    kept = r + 2
    # (pinv: without noise, an inner knot no data reach has no information at all)
    eliminated = Q[:kept, kept:] @ _pinv(Q[kept:, kept:])
    marginal = Q[:kept, :kept] - eliminated @ Q[kept:, :kept]
    ends = float(biases.walk_information(kind, (numbers[-1] - numbers[0]) * biases.spacing_s))
    _add_walk(marginal, r, r + 1, -var * ends)
    # back over the data vector's columns: b_0 = -one and b_m = -one - u
    from_columns = np.eye(r + 2)
    from_columns[r:, r:] = _FROM_KNOTS
    out = from_columns.T @ marginal @ from_columns
    return 0.5 * (out + out.T)


def knot_numbers(units: Sequence[tuple[int, int]]) -> np.ndarray:
    """The window numbers where the biases have knots, for units given by their first window's
    number and how many windows they span: every window's start and end from the first unit's
    on (none before it: a stretch after a move is as cheap as a log of its own), but none
    inside a merged stretch (:func:`merged`: its inner knots eliminated)."""
    every = np.arange(min(n for n, _ in units), max(n + span for n, span in units) + 1)
    inside = [np.arange(n + 1, n + span) for n, span in units if span > 1]
    return np.setdiff1d(every, np.concatenate(inside)) if inside else every


def _pinv(H: np.ndarray) -> np.ndarray:
    """The pseudo-inverse of a symmetric positive semi-definite ``H``; the one knot between two
    neighbours (the merges' rule) without a decomposition."""
    if H.shape == (1, 1):
        h = float(H[0, 0])
        return np.array([[1.0 / h if h > 1e-300 else 0.0]])
    return np.linalg.pinv(H, hermitian=True)


def _add_walk(Q: np.ndarray, a: int, b: int, info: float) -> None:
    """``info (y_a - y_b)^2`` added to the quadratic form ``Q``."""
    Q[a, a] += info
    Q[b, b] += info
    Q[a, b] -= info
    Q[b, a] -= info


def unused_window(number: int, start: float, end: float) -> WindowMoments:
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
