"""Gauss-Newton on the windows' moments, the biases eliminated by a banded Schur complement.

The model (:mod:`imucal_cli.core.model`) makes each window's cost and derivatives exact
functions of its moments, so iterating never revisits the signals. The relative biases are
piecewise linear with a knot per window; their block of the normal equations is banded (a
window couples two knots), so it is factored by LAPACK's banded Cholesky and eliminated, and
the small problem left in the globals takes the translation box of eq. 16 through
``scipy.optimize.lsq_linear`` where the box binds. Everything here returns figures.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from imucal_cli.core.model import (
    ACCEL_DATA,
    ACCEL_GLOBALS,
    GYRO_DATA,
    GYRO_GLOBALS,
    KNOT,
    N_PARAMETERS,
    PARAMETERS,
    ROTATION,
    START_FREE,
    TRANSLATION,
    BiasModel,
    Layout,
    Point,
    accel_coefficients,
    accel_derivatives,
    angular_acceleration_noise,
    gyro_coefficients,
    gyro_derivatives,
)
from imucal_cli.core.moments import (
    WindowMoments,
    assemble_moments,
    constant_moments,
    knot_numbers,
    shifted,
)
from imucal_cli.types import rotation_type

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

    from imucal_cli.core.signals import Lowpass


def cholesky_banded(band: np.ndarray, lower: bool = False) -> np.ndarray:
    """LAPACK's banded Cholesky factor (scipy's, imported when first used)."""
    from scipy.linalg import cholesky_banded as factor

    return factor(band, lower=lower)


def cho_solve_banded(factor: tuple[np.ndarray, bool], b: np.ndarray) -> np.ndarray:
    """Solve with a banded Cholesky factor (scipy's, imported when first used)."""
    from scipy.linalg import cho_solve_banded as solve

    return solve(factor, b)


def half_solve_banded(factor: tuple[np.ndarray, bool], b: np.ndarray) -> np.ndarray:
    """``U^-T b`` for the upper banded Cholesky factor ``U`` of ``H = U^T U``: half of a solve
    with ``H`` (``b^T H^-1 c = (U^-T b)^T (U^-T c)``). LAPACK's ``tbtrs``."""
    from scipy.linalg.lapack import dtbtrs

    assert not factor[1], "an upper factor"
    x, info = dtbtrs(factor[0], b, uplo="U", trans="T")
    if info != 0:
        raise np.linalg.LinAlgError(f"banded triangular solve failed (info {info})")
    return np.asarray(x)


#: Upper bandwidth of the biases' block of the normal equations: a window couples the biases
#: of its two knots, at most ``2 KNOT.size - 1`` apart.
BAND = 2 * KNOT.size - 1
#: Windows whose normal equations are formed together (bounds the estimator's scratch memory).
SOLVE_CHUNK = 128
#: The accelerometer's full moments are kept through the iterations up to this size (about 13 h
#: of 10 s windows); beyond it they are stacked again, a chunk at a time, every iteration.
SOLVE_CACHE_BYTES = 32 << 20
#: Relative resolution of a residual computed from second moments (double precision squares).
RESOLUTION = 1e-7


def bias_prior(gaps_s: np.ndarray, biases: BiasModel) -> np.ndarray:
    """Information of each bias component's random walk between knots (``gaps_s`` apart: one
    fewer than the knots) and its absolute prior at the first knot (where the walk starts: the
    Kalman filter's ``P0``), in LAPACK's upper banded storage
    (``BAND + 1`` rows, ``KNOT.size n_knots`` columns, knots in the order of :data:`KNOT`)."""
    width, n_knots = KNOT.size, len(gaps_s) + 1
    band = np.zeros((BAND + 1, width * n_knots))
    for c in range(width):
        info = biases.walk_information(c // 3, gaps_s)
        diagonal = np.zeros(n_knots)  # sum of d^T d: 1 at the ends, 2 inside (equal gaps)
        diagonal[:-1] += info
        diagonal[1:] += info
        diagonal[0] += biases.prior_information(c // 3)
        band[BAND, c::width] = diagonal
        band[BAND - width, width + c :: width] = -info  # between neighbouring knots
    return band


def _weighted_sum(w: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``sum_k w_k S_k`` of (K, d, e) matrices, as one matrix-vector product."""
    return (w @ S.reshape(len(S), -1)).reshape(S.shape[1:])


def band_times(band: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The symmetric matrix held in upper banded storage times ``x``."""
    u = len(band) - 1
    y = band[u] * x
    for d in range(1, u + 1):
        upper = band[u - d, d:]  # entries (i, i + d)
        y[:-d] += upper * x[d:]
        y[d:] += upper * x[:-d]
    return y


def window_equations(
    D: np.ndarray, S: np.ndarray, C: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per window, all of its Gauss-Newton normal equations but the globals' own block
    (:func:`globals_block`, which sums over windows): the globals' coupling to the window's two
    bias knots ``tr(D_p S D_b^T)`` (K, P, 6), the gradient ``tr(D_p S C^T)`` over the globals
    then the knots (K, P + 6), the cost ``tr(C S C^T)`` (K,) and the knots' block (K, 6, 6).
    ``D`` (P, 3, dim): the globals' derivatives, the same for every window; ``S`` (K, dim, dim)
    the moments; ``C`` (K, 3, dim) each window's coefficients.

    A bias knot's derivative is constant and sparse: the residual's row ``m`` takes ``-b_j`` on
    the constant column ``a`` of ``x`` and ``-(b_k - b_j)`` on the time column ``b`` (the last
    two of either data vector), so its products with ``S`` are entries of ``D S``, ``C S`` and
    ``S`` itself."""
    K, dim = len(S), S.shape[-1]
    P = len(D)
    a, b = dim - 2, dim - 1
    assert (a, b) in (
        (GYRO_DATA.index("one"), GYRO_DATA.index("u")),
        (ACCEL_DATA.index("one"), ACCEL_DATA.index("u")),
    )
    # the contractions as matrix products (BLAS), several times faster than np.einsum's loops
    D_rows = D.reshape(P * 3, dim)
    DS_a = (S[:, :, a] @ D_rows.T).reshape(K, P, 3)
    DS_b = (S[:, :, b] @ D_rows.T).reshape(K, P, 3)
    coupling = np.empty((K, P, 6))
    coupling[:, :, 0:3] = DS_b - DS_a  # b_j: -e_a + e_b on row m
    coupling[:, :, 3:6] = -DS_b  # b_k: -e_b on row m
    CS = C @ S
    g = np.empty((K, P + 6))
    # S symmetric: tr(D_p S C^T) = sum D_p * (C S)
    g[:, :P] = CS.reshape(K, 3 * dim) @ D.reshape(P, 3 * dim).T
    g[:, P : P + 3] = CS[:, :, b] - CS[:, :, a]
    g[:, P + 3 :] = -CS[:, :, b]
    cost = np.sum(CS * C, axis=(1, 2))
    bias = np.zeros((K, 6, 6))
    S_aa, S_ab, S_bb = S[:, a, a], S[:, a, b], S[:, b, b]
    for m in range(3):
        bias[:, m, m] = S_aa - 2.0 * S_ab + S_bb
        bias[:, m, 3 + m] = bias[:, 3 + m, m] = S_ab - S_bb
        bias[:, 3 + m, 3 + m] = S_bb
    return coupling, g, cost, bias


def globals_block(D: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``tr(D_p S D_q^T)`` (P, P) for moments ``S`` (dim, dim) summed over windows (weighted):
    the globals' derivatives are the same in every window, so their block of the normal
    equations needs only the sum of the windows' moments."""
    P, rows, dim = D.shape
    DS = (D.reshape(P * rows, dim) @ S).reshape(P, rows * dim)
    return DS @ D.reshape(P, rows * dim).T


def bounded_step(
    L: np.ndarray, s: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The step minimising ``|L^T x - L^-1 s|^2`` (``x^T S x / 2 - s^T x`` with ``S = L L^T``)
    inside the box ``[lower, upper]``, and the unconstrained minimiser ``S^-1 s``. The cost is
    strictly convex, so where the unconstrained minimiser lies in the box it is the answer;
    otherwise the box is taken by ``scipy.optimize.lsq_linear`` (bounded-variable least
    squares; imported only then)."""
    target = np.linalg.solve(L, s)
    free = np.linalg.solve(L.T, target)
    if np.all(free >= lower) and np.all(free <= upper):
        return free, free
    from scipy.optimize import lsq_linear

    bounded = lsq_linear(L.T, target, bounds=(lower, upper), method="bvls", tol=1e-12)
    return bounded.x, free


def kabsch_rotation(S_gyro: np.ndarray) -> Rotation:
    """``R_base_imu`` minimising ``sum |R^T w_B - w_I|^2`` over windows, each centred (eq. 10).

    From the gyro moments (K, 14, 14): centring per window removes a constant relative gyro
    bias. Kabsch/Horn: with the centred cross covariance ``sum w_I w_B^T = U diag(s) V^T``,
    ``R_imu_base = U diag(1, 1, det) V^T``.
    """
    one, w_I, w_B = GYRO_DATA.index("one"), GYRO_DATA["w_I"], GYRO_DATA["w_B"]
    n = S_gyro[:, one, one][:, None, None]  # (a window's samples: its constant's moment)
    mean_I, mean_B = S_gyro[:, w_I, one][:, :, None] / n, S_gyro[:, w_B, one][:, :, None] / n
    cross = np.sum(S_gyro[:, w_I, w_B] - n * mean_I @ mean_B.transpose(0, 2, 1), axis=0)
    U, _, Vt = np.linalg.svd(cross)
    d = np.sign(np.linalg.det(U @ Vt))
    R_imu_base = U @ np.diag([1.0, 1.0, d]) @ Vt
    return rotation_type().from_matrix(R_imu_base.T)


@dataclass
class Fit:
    """One Gauss-Newton solution of the joint problem and its Fisher information."""

    point: Point
    knots: np.ndarray  # (n_knots, KNOT.size)
    free: np.ndarray  # (N_PARAMETERS,) bool: the globals estimated
    scale_g: float  # residual std per grid sample (rad/s, m/s^2), from the fit
    scale_a: float
    #: Of the free globals (rotation: IMU axes).
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((N_PARAMETERS, N_PARAMETERS)))
    unconstrained_t: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the box not binding
    cost_g: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per window
    cost_a: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias_std: np.ndarray | None = None  # (KNOT.size,) of the last knot
    iterations: int = 0

    def std(self) -> np.ndarray:
        """(N_PARAMETERS,) standard deviations; inf where not estimated."""
        variance = np.clip(np.diag(self.covariance), 0.0, None)
        return np.where(self.free, np.sqrt(variance), np.inf)

    def rotation_covariance_base(self) -> np.ndarray:
        """3x3 covariance of the rotation about the base axes."""
        Rm = self.point.R.as_matrix()
        return Rm @ self.covariance[ROTATION, ROTATION] @ Rm.T


class Equations(NamedTuple):
    """One equation's normal equations at a point (:func:`window_equations`): the globals'
    derivatives and, per window, the rest."""

    D: np.ndarray  # (P, 3, dim)
    coupling: np.ndarray  # (K, P, 6)
    gradient: np.ndarray  # (K, P + 6)
    cost: np.ndarray  # (K,)
    bias: np.ndarray  # (K, 6, 6)


class Linearisation(NamedTuple):
    """Both equations' normal equations at a point, unweighted."""

    gyro: Equations
    accel: Equations

    @property
    def cost_g(self) -> np.ndarray:
        return self.gyro.cost

    @property
    def cost_a(self) -> np.ndarray:
        return self.accel.cost


class _Reduced(NamedTuple):
    """The normal equations with the biases eliminated: ``S step = s`` over the free globals."""

    S: np.ndarray
    s: np.ndarray
    factor: tuple[np.ndarray, bool]  # the biases' banded Cholesky factor
    H_gb: np.ndarray  # the free globals' coupling to the biases
    grad_b: np.ndarray
    Z: np.ndarray  # U^-T H_gb^T, with H_bb = U^T U


@dataclass(frozen=True)
class Settings:
    """What the solver takes from the calibration's options."""

    translation_prior: np.ndarray  # t_base_imu of the prior: the box's centre
    translation_bound_m: float
    biases: BiasModel
    max_iterations: int
    #: Blocks of :data:`PARAMETERS` no fit of the problem frees (the base gyro's axes of a base
    #: that declares none): left out of its linearisations, not worked out for every window.
    never_free: tuple[str, ...] = ()


#: Diagonal loads tried, in turn, on information whose Cholesky fails, each relative to its
#: own parameter's information (Jacobi scaling: a load relative to the largest entry would make
#: up information in units the rotation's dwarf): round-off in a direction the drive leaves
#: free (a gyro's y scale where it only turns about x, the lever arm along a wheel's axle)
#: makes it indefinite, and the load gives that direction a variance of ``1 / load`` times its
#: parameters' own, so it shows as not determined; the determined move by a part in ``1/load``.
DIAGONAL_LOADS = (0.0, 1e-12, 1e-9, 1e-6)


#: A fit has converged once its next step is below these: the rotation's (rad), the other
#: globals' (m, s and the IMUs' own errors).
CONVERGED = np.array([1e-10, 1e-8])


def spd_cholesky(S: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor of symmetric positive semi-definite information ``S``, with
    the least diagonal load of :data:`DIAGONAL_LOADS` that makes it factor (``L L^T = S +
    load diag(S)``)."""
    diagonal = np.diag(S)
    d = np.sqrt(np.where(diagonal > 0, diagonal, 1.0))
    scaled = S / d[:, None] / d[None, :]
    for load in DIAGONAL_LOADS:
        try:
            factor = np.linalg.cholesky(scaled + load * np.eye(len(S)) if load else scaled)
        except np.linalg.LinAlgError:
            continue
        return d[:, None] * factor
    raise np.linalg.LinAlgError("the information matrix is not positive semi-definite")


def _spd_inverse(S: np.ndarray) -> np.ndarray:
    """The inverse of a symmetric positive-definite matrix through its Cholesky factor:
    ``L^-T L^-1``, whose diagonal is a sum of squares. ``np.linalg.inv`` of an ill-conditioned
    information matrix (a short drive, many globals free) gave variances below zero."""
    from scipy.linalg.lapack import dtrtri

    L_inv, info = dtrtri(spd_cholesky(S), lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"triangular inverse failed (info {info})")
    return L_inv.T @ L_inv


class Problem:
    """The normal equations' parts of one sensor's selected windows that stay fixed over
    iterations: moments, where each window's entries go, the bias prior. :meth:`fit` solves it
    for any set of free globals, either equation alone, and any subset of windows (the
    jackknife)."""

    def __init__(
        self,
        windows: list[WindowMoments],
        settings: Settings,
        sigma: tuple[float, float],
        lowpass: Lowpass,
        dw_noise_var: float,
    ) -> None:
        used = [w for w in windows if w.info is not None and w.info.selected]
        self.used, self.settings, self.sigma, self.dw_noise_var = (
            used,
            settings,
            sigma,
            dw_noise_var,
        )
        #: Where each window's biases are: its knot, then the next.
        self.knot_numbers = knot_numbers([(w.number, w.span) for w in windows])
        self.numbers = np.searchsorted(self.knot_numbers, [w.number for w in used])
        #: Each window's clock offset beyond the one it was resampled at, where its clock was
        #: followed (:mod:`.clock`): its moments are moved by it (:func:`~.moments.shifted`),
        #: so the fit and its derivatives see each window at the track's offset.
        shifts = np.array([w.shift_s for w in used])
        self.shifts = shifts if np.any(shifts) else None
        self.n_knots = len(self.knot_numbers)
        self.S_g = self._moved(assemble_moments(used, "gyro"), 0, GYRO_DATA)  # (K, 14, 14)
        self.starts = range(0, len(used), SOLVE_CHUNK)
        # the accelerometer's moments, stacked once where they are small, else a chunk at a time
        small = len(used) * ACCEL_DATA.size**2 * 8 <= SOLVE_CACHE_BYTES
        self.cached = [self._S_a(a) for a in self.starts] if small else None
        self.samples_per_window = np.array([w.samples for w in used], dtype=float)
        self.samples = float(self.samples_per_window.sum())
        self.gain = lowpass.white_noise_gain()
        self._floors_and_signal()
        gaps = np.diff(self.knot_numbers) * settings.biases.spacing_s
        self.prior_band = bias_prior(gaps, settings.biases)
        #: The globals each equation holds here (:data:`GYRO_GLOBALS`, :data:`ACCEL_GLOBALS`
        #: less what is never free).
        kept = ~PARAMETERS.mask(*settings.never_free)
        self.globals_g, self.globals_a = (p[kept[p]] for p in (GYRO_GLOBALS, ACCEL_GLOBALS))
        self._layout_biases()
        self._last: tuple[bytes, Linearisation] | None = None

    def _floors_and_signal(self) -> None:
        """A cost from moments is a difference of large sums: below :data:`RESOLUTION` times
        the signal's RMS the residual is round-off, not noise (noise-free data). And the
        sensor's signal about each window's mean, per axis (RMS)."""
        used, f_I = self.used, ACCEL_DATA["f_I"]
        trace_f = float(sum(np.trace(w.rows_accel[:, f_I]) for w in used))
        w_I = GYRO_DATA["w_I"]
        self.floor_g = (
            (RESOLUTION**2) * np.trace(self.S_g[:, w_I, w_I].sum(axis=0)) / (3 * self.samples)
        )
        self.floor_a = (RESOLUTION**2) * trace_f / (3 * self.samples)

        def spread(rows: np.ndarray, own: slice, n: float, one: int) -> float:  # |x - mean|^2
            return float(np.trace(rows[:, own]) - rows[:, one] @ rows[:, one] / n)

        one_g, one_a = GYRO_DATA.index("one"), ACCEL_DATA.index("one")
        n_g, n_a = constant_moments(used, "gyro"), constant_moments(used, "accel")
        gyro = sum(spread(w.rows_gyro[w_I], w_I, n, one_g) for w, n in zip(used, n_g, strict=True))
        accel = sum(spread(w.rows_accel, f_I, n, one_a) for w, n in zip(used, n_a, strict=True))
        self.signal_rms = (
            float(np.sqrt(gyro / (3 * self.samples))),
            float(np.sqrt(accel / (3 * self.samples))),
        )

    def _layout_biases(self) -> None:
        """Where each window's normal equations go (the same every iteration). Unknowns: the
        globals, then the biases, per knot as :data:`KNOT`. A window's gyro equations hold
        their globals and its two knots' gyro biases, its accelerometer's likewise."""
        n_bias = self.n_bias = KNOT.size * self.n_knots
        width = KNOT.size

        def at_knots(block: slice) -> np.ndarray:  # (K, 6): the block at knot j, then j + 1
            own = np.arange(block.start, block.stop)
            return width * self.numbers[:, None] + np.concatenate([own, width + own])

        self.biases_g, self.biases_a = at_knots(KNOT["gyro_bias"]), at_knots(KNOT["accel_bias"])
        upper6 = self.upper6 = np.triu_indices(6)  # a window's bias indices increase

        def band_at(
            biases: np.ndarray,
        ) -> np.ndarray:  # flat index into the (BAND + 1, n_bias) band
            i, j = biases[:, upper6[0]], biases[:, upper6[1]]
            return ((BAND + i - j) * n_bias + j).ravel()

        self.band_g, self.band_a = band_at(self.biases_g), band_at(self.biases_a)
        self.cross_g = (self.globals_g[None, :, None] * n_bias + self.biases_g[:, None, :]).ravel()
        self.cross_a = (self.globals_a[None, :, None] * n_bias + self.biases_a[:, None, :]).ravel()

    def _S_a(self, a: int) -> np.ndarray:
        """The accelerometer's moments of a chunk of windows, less what the angular
        acceleration's noise adds to the ``vec A`` block (errors in variables: uncorrected,
        it counts as lever-arm information and pulls the lever arm towards the origin)."""
        windows = self.used[a : a + SOLVE_CHUNK]
        S = assemble_moments(windows, "accel")
        samples = np.array([w.samples for w in windows], dtype=float)
        vec_A = ACCEL_DATA["vec_A"]
        S[:, vec_A, vec_A] -= angular_acceleration_noise(samples, self.dw_noise_var)
        return self._moved(S, a, ACCEL_DATA)

    def _moved(self, S: np.ndarray, a: int, layout: Layout) -> np.ndarray:
        """Moments of the windows from ``a`` on, each moved by its clock shift (where any)."""
        if self.shifts is None:
            return S
        return shifted(S, self.shifts[a : a + len(S)], layout)

    def may_free(self, block: str) -> bool:
        """Whether a fit of this problem may free the block of :data:`PARAMETERS` named."""
        return block not in self.settings.never_free

    def accel_moments(self) -> list[np.ndarray]:
        """The accelerometer's moments, a chunk of windows at a time."""
        if self.cached is not None:
            return self.cached
        return [self._S_a(a) for a in self.starts]

    def linearised(self, point: Point, knots: np.ndarray) -> Linearisation:
        """Every window's unweighted normal equations at a point (:func:`window_equations`).
        The last point's are kept: the jackknife's replicates and the one-equation checks all
        take their one step from the same fit."""
        key = point.key() + knots.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        bj, bk = knots[self.numbers], knots[self.numbers + 1]
        gyro, accel = KNOT["gyro_bias"], KNOT["accel_bias"]
        Cg = gyro_coefficients(point, bj[:, gyro], bk[:, gyro])
        Ca = accel_coefficients(point, bj[:, accel], bk[:, accel])
        Dg, Da = gyro_derivatives(point, self.globals_g), accel_derivatives(point, self.globals_a)
        parts_a = [
            window_equations(Da, S_a, Ca[a : a + SOLVE_CHUNK])
            for a, S_a in zip(self.starts, self.accel_moments(), strict=True)
        ]
        accel_parts = [np.concatenate([p[i] for p in parts_a]) for i in range(4)]
        lin = Linearisation(
            Equations(Dg, *window_equations(Dg, self.S_g, Cg)), Equations(Da, *accel_parts)
        )
        self._last = (key, lin)
        return lin

    def weighted_moments(self, w_g: np.ndarray, w_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The windows' moments summed with weights, each equation's."""
        S_g = _weighted_sum(w_g, self.S_g)
        S_a = sum(
            _weighted_sum(w_a[a : a + SOLVE_CHUNK], S)
            for a, S in zip(self.starts, self.accel_moments(), strict=True)
        )
        return S_g, np.asarray(S_a)

    def translation_information_diagonal(self) -> np.ndarray:
        """Per axis, the lever arm's information ``sum (A - mean A)^T (A - mean A)`` over the
        windows (each centred), less the angular acceleration's noise (unit residual)."""
        total = np.zeros(3)
        one, vec_A = ACCEL_DATA.index("one"), ACCEL_DATA["vec_A"]
        for S in self.accel_moments():
            n = S[:, one, one]
            mean = S[:, vec_A, one] / n[:, None]
            centred = S[:, vec_A, vec_A] - n[:, None, None] * mean[:, :, None] * mean[:, None, :]
            blocks = centred.sum(axis=0).reshape(3, 3, 3, 3)  # (j, a, l, b) of vec A = A[a, j]
            total += np.einsum("jaja->j", blocks)
        return total

    def eiv_variance(self, t: np.ndarray) -> float:
        """Per-axis variance the angular acceleration's noise adds to the accelerometer's
        residual at lever arm ``t``: ``E |n x t|^2 / 3``."""
        return 2.0 / 3.0 * self.dw_noise_var * float(t @ t)

    def start(self) -> Fit:
        """The starting point: Kabsch/Horn over the windows (eq. 10), the prior's translation,
        the extrinsics and the clock free."""
        R = kabsch_rotation(self.S_g)
        scale_g, scale_a = (s * np.sqrt(self.gain) for s in self.sigma)
        free = START_FREE.copy()
        point = Point(R, self.settings.translation_prior.copy(), 0.0)
        return Fit(point, np.zeros((self.n_knots, KNOT.size)), free, scale_g, scale_a)

    def fit(
        self,
        start: Fit,
        free: np.ndarray,
        use: tuple[bool, bool] = (True, True),
        window_weights: np.ndarray | None = None,
        estimate_scale: bool = False,
        max_iterations: int | None = None,
        prior_std: np.ndarray | None = None,
    ) -> Fit:
        """Gauss-Newton from ``start`` over the ``free`` globals (and every bias knot), with the
        gyro and accelerometer equations as ``use`` says, each window weighted by
        ``window_weights`` (0 leaves it out). The residual scales are re-estimated from the
        fit where ``estimate_scale``, else kept from ``start``. ``prior_std`` (per global, 0:
        none; rad for the rotation) keeps what the data leave free defined: a rotation one
        equation alone leaves free, errors a drive does not determine."""
        point, knots = start.point, start.knots.copy()
        scales = (start.scale_g, start.scale_a)
        weights = np.ones(len(self.used)) if window_weights is None else window_weights
        free_idx = np.flatnonzero(free)
        unconstrained, reduced, S_inv, iterations = point.t.copy(), None, None, 0
        lin, last = None, None
        for iterations in range(1, (max_iterations or self.settings.max_iterations) + 1):
            lin = self.linearised(point, knots)
            if estimate_scale and iterations > 1:
                scales = self._scales(lin, weights, point.t)
            reduced = self._reduce(lin, scales, use, weights, knots, free_idx, prior_std)
            step, unconstrained = self._step(reduced, point.t, free_idx)
            step_bias = cho_solve_banded(
                reduced.factor, reduced.grad_b - reduced.H_gb.T @ step[free_idx]
            )
            point, knots = point.moved(step), knots + step_bias.reshape(self.n_knots, KNOT.size)
            S_inv = _spd_inverse(reduced.S)
            # the step taken, and the next one where the last two shrink at a steady rate
            size = np.array([np.max(np.abs(step[ROTATION])), np.max(np.abs(step[ROTATION.stop :]))])
            upcoming = size if last is None else size * np.minimum(size / last, 1.0)
            last = np.maximum(size, 1e-300)
            if np.all(upcoming < CONVERGED) and (iterations > 2 or not estimate_scale):
                break
        assert reduced is not None and S_inv is not None and lin is not None
        covariance = np.zeros((N_PARAMETERS, N_PARAMETERS))
        covariance[np.ix_(free_idx, free_idx)] = S_inv
        return Fit(
            point,
            knots,
            free.copy(),
            *scales,
            covariance,
            unconstrained,
            lin.cost_g,
            lin.cost_a,
            self._last_knot_std(reduced, S_inv),
            iterations,
        )

    def information(self, fit: Fit, free: np.ndarray) -> np.ndarray:
        """The Fisher information of the ``free`` globals at the fit's point, with its
        residual scales, the biases eliminated (the inverse covariance :meth:`fit` reports)."""
        lin = self.linearised(fit.point, fit.knots)
        weights = np.ones(len(self.used))
        scales = (fit.scale_g, fit.scale_a)
        free_idx = np.flatnonzero(free)
        return self._reduce(lin, scales, (True, True), weights, fit.knots, free_idx, None).S

    def _scales(
        self, lin: Linearisation, weights: np.ndarray, t: np.ndarray
    ) -> tuple[float, float]:
        """The residual std per grid sample from the fit, above what the moments resolve."""
        samples = float(np.sum(weights * self.samples_per_window))
        variance_g = np.dot(weights, lin.cost_g) / (3 * samples)
        variance_a = np.dot(weights, lin.cost_a) / (3 * samples) + self.eiv_variance(t)
        return float(np.sqrt(max(variance_g, self.floor_g))), float(
            np.sqrt(max(variance_a, self.floor_a))
        )

    def _reduce(
        self,
        lin: Linearisation,
        scales: tuple[float, float],
        use: tuple[bool, bool],
        weights: np.ndarray,
        knots: np.ndarray,
        free_idx: np.ndarray,
        prior_std: np.ndarray | None,
    ) -> _Reduced:
        """The weighted normal equations, the biases eliminated (Schur complement)."""
        wg = self.gain / scales[0] ** 2 * use[0] * weights
        wa = self.gain / scales[1] ** 2 * use[1] * weights
        H_gg_all, H_gb_all, H_bb, grad_g, grad_b = self._assemble(lin, wg, wa, knots)
        H_gg, H_gb = H_gg_all[np.ix_(free_idx, free_idx)], H_gb_all[free_idx]
        factor = (cholesky_banded(H_bb, lower=False), False)
        # H_gb H_bb^-1 H_gb^T as Z^T Z: one triangular solve, not two, and S symmetric
        Z = half_solve_banded(factor, H_gb.T)
        S = H_gg - Z.T @ Z
        s = grad_g[free_idx] - Z.T @ half_solve_banded(factor, grad_b[:, None])[:, 0]
        if prior_std is not None:
            held = np.flatnonzero(prior_std[free_idx] > 0)
            S[held, held] += 1.0 / prior_std[free_idx][held] ** 2
        return _Reduced(S, s, factor, H_gb, grad_b, Z)

    def _assemble(
        self, lin: Linearisation, wg: np.ndarray, wa: np.ndarray, knots: np.ndarray
    ) -> tuple[np.ndarray, ...]:
        """The normal equations with each window weighted (``wg``, ``wa``): the globals' block,
        their coupling to the biases, the biases' banded block (with the prior), and the
        gradient's two parts."""
        n_bias, gyro_globals, accel_globals = self.n_bias, self.globals_g, self.globals_a
        P_g, P_a = len(gyro_globals), len(accel_globals)
        g, a = lin.gyro, lin.accel
        S_g, S_a = self.weighted_moments(wg, wa)
        H_gg = np.zeros((N_PARAMETERS, N_PARAMETERS))
        H_gg[np.ix_(gyro_globals, gyro_globals)] += globals_block(g.D, S_g)
        H_gg[np.ix_(accel_globals, accel_globals)] += globals_block(a.D, S_a)
        H_gb = (
            np.bincount(
                self.cross_g, (wg[:, None, None] * g.coupling).ravel(), N_PARAMETERS * n_bias
            )
            + np.bincount(
                self.cross_a, (wa[:, None, None] * a.coupling).ravel(), N_PARAMETERS * n_bias
            )
        ).reshape(N_PARAMETERS, n_bias)
        size, u6 = (BAND + 1) * n_bias, self.upper6
        H_bb = (
            np.bincount(self.band_g, (wg[:, None] * g.bias[:, u6[0], u6[1]]).ravel(), size)
            + np.bincount(self.band_a, (wa[:, None] * a.bias[:, u6[0], u6[1]]).ravel(), size)
        ).reshape(BAND + 1, n_bias)
        H_bb += self.prior_band
        gg, ga = wg[:, None] * g.gradient, wa[:, None] * a.gradient
        grad_g = np.zeros(N_PARAMETERS)
        grad_g[accel_globals] -= ga[:, :P_a].sum(axis=0)
        grad_g[gyro_globals] -= gg[:, :P_g].sum(axis=0)
        grad_b = -(
            np.bincount(self.biases_g.ravel(), gg[:, P_g:].ravel(), n_bias)
            + np.bincount(self.biases_a.ravel(), ga[:, P_a:].ravel(), n_bias)
        )
        grad_b -= band_times(self.prior_band, knots.ravel())
        return H_gg, H_gb, H_bb, grad_g, grad_b

    def _step(
        self, reduced: _Reduced, t: np.ndarray, free_idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The step of the globals with the translation inside its box (eq. 16), and where the
        translation would go without the box."""
        prior, bound = self.settings.translation_prior, self.settings.translation_bound_m
        lower, upper = np.full(len(free_idx), -np.inf), np.full(len(free_idx), np.inf)
        translation = (free_idx >= TRANSLATION.start) & (free_idx < TRANSLATION.stop)
        axes = free_idx[translation] - TRANSLATION.start
        lower[translation] = prior[axes] - bound - t[axes]
        upper[translation] = prior[axes] + bound - t[axes]
        step_free, unbounded = bounded_step(spd_cholesky(reduced.S), reduced.s, lower, upper)
        step = np.zeros(N_PARAMETERS)
        step[free_idx] = step_free
        unconstrained = t.copy()
        unconstrained[axes] += unbounded[translation]
        return step, unconstrained

    def _last_knot_std(self, reduced: _Reduced, S_inv: np.ndarray) -> np.ndarray:
        """The std of the last knot's biases, the globals marginalised."""
        width = KNOT.size
        last = [width * (self.n_knots - 1) + a for a in range(width)]
        E = np.zeros((self.n_bias, width))
        E[last, np.arange(width)] = 1.0
        W = half_solve_banded(reduced.factor, E)  # E^T H_bb^-1 E = W^T W
        XtE = reduced.Z.T @ W  # H_gb H_bb^-1 E
        block = W.T @ W + XtE.T @ S_inv @ XtE
        return np.sqrt(np.clip(np.diag(block), 0.0, None))
