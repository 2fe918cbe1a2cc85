"""Extrinsics of one sensor IMU in the base frame from the two IMUs' signals (paper eqs. 10-17).

This module holds the estimator; :mod:`imucal_cli.core.streaming` reduces the signals to the
per-window sufficient statistics it works on.

The paper solves the rotation by Kabsch/Horn (eq. 10) and then the translation by bounded least
squares (eq. 16). Here the Kabsch/Horn solution over the selected windows only initialises a
joint Gauss-Newton estimate of everything the two signals share:

- gyro (eq. 10): ``w_I(t + tau) = R^T w_B(t) + b_g(t)``
- accelerometer (eq. 11): ``f_I(t + tau) = R^T (f_B + ([dw_B]x + [w_B]x^2) t_BI)(t) + b_a(t)``

with ``R = R_base_imu``, ``t_BI = t_base_imu``, the clock offset ``tau`` (stamp of the sensor
minus stamp of the base) and the sensor's biases relative to the base as piecewise-linear
functions of time with a knot every window (they drift). The accelerometer equation constrains
the rotation too (through gravity and the vehicle's accelerations), so the axis that yaw-only
driving leaves free in eq. 10 is fixed by gravity. Both sides are resampled onto one grid and
pass through the same zero-phase low-pass (:mod:`imucal_cli.core.signals`); the angular
acceleration is the derivative of the base gyro's interpolating spline, filtered alike.

Every window is reduced to the second moments of its data vectors (see
:mod:`imucal_cli.core.streaming`); each window's cost and its Gauss-Newton derivatives are exact
functions of them, so iterating never revisits the signals. The biases are eliminated by a
Schur complement (their block of the normal equations is banded: a window couples two knots;
LAPACK's banded Cholesky), so the remaining 7x7 problem in ``(rotation, translation, tau)``
takes the translation box of eq. 16 through ``scipy.optimize.lsq_linear`` (where the box
binds). The covariance is the inverse Fisher information with the residual variance estimated
from the fit, corrected for the low-pass's correlation of neighbouring residuals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.spatial.transform import Rotation

from imucal_cli.core.segments import OBSERVABLE_FRACTION_OF_BOUND, WindowInfo
from imucal_cli.core.signals import LOWPASS_HZ, Lowpass
from imucal_cli.core.so3 import skew
from imucal_cli.types import Transform

#: Random walk of the accelerometer bias allowed between knots (m/s^2/sqrt(s)): loose, a few
#: times what MEMS parts drift, so the data decide.
ACCEL_BIAS_WALK = 0.01
#: Prior standard deviation of the accelerometer bias (m/s^2): keeps knots without data defined.
ACCEL_BIAS_PRIOR_STD = 1.0
#: A gap is a step between stamps longer than this many median periods: windows holding one
#: are not used (the spline cannot bridge it).
GAP_PERIODS = 3.0


@dataclass(frozen=True)
class CalibrationOptions:
    resample_hz: float = 100.0
    max_time_offset_s: float = 0.1
    window_s: float = 10.0
    max_rotation_std_deg: float = 1.0
    translation_bound_m: float = 0.3
    gyro_bias_walk: float = np.radians(0.1)  # rad/s/sqrt(s), config gyro_bias.process_noise_dps
    gyro_bias_prior_std: float = np.radians(0.3)  # rad/s, config gyro_bias.initial_std_dps
    lowpass_hz: float = LOWPASS_HZ
    max_iterations: int = 12


@dataclass(frozen=True)
class SensorEstimate:
    """The estimate for one sensor IMU and how well the drive determines it."""

    status: str  # ok | partial | unobservable
    T_base_imu: Transform
    covariance: np.ndarray | None  # 6x6 of [rotation (rad, about base axes), t_base_imu (m)]
    translation_observable: np.ndarray  # (3,) bool
    time_offset_s: float
    time_offset_std_s: float | None
    gyro_bias: np.ndarray  # (3,) final relative gyro bias (rad/s, IMU frame)
    gyro_bias_std: np.ndarray | None
    accel_bias: np.ndarray  # (3,) final relative accelerometer bias (m/s^2, IMU frame)
    accel_bias_std: np.ndarray | None
    bias_knots_s: np.ndarray  # (K,) knot times on the grid clock
    gyro_bias_knots: np.ndarray  # (K, 3)
    accel_bias_knots: np.ndarray  # (K, 3)
    windows: list[WindowInfo]
    residual_rms_gyro: float | None
    residual_rms_accel: float | None
    iterations: int = 0
    noise_std: dict[str, float] = field(default_factory=dict)

    @property
    def rotation_std_deg(self) -> np.ndarray | None:
        if self.covariance is None:
            return None
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def translation_std_m(self) -> np.ndarray | None:
        if self.covariance is None:
            return None
        return np.sqrt(np.diag(self.covariance)[3:])

    def lidar_covariance(self, T_imu_lidar: Transform) -> np.ndarray | None:
        """6x6 covariance of ``T_base_lidar = T_base_imu T_imu_lidar`` (rotation about base axes)."""
        if self.covariance is None:
            return None
        lever = self.T_base_imu.rotation.apply(T_imu_lidar.translation)
        J = np.eye(6)
        J[3:, :3] = -skew(lever)  # d(R t_IL) = [dtheta]x R t_IL = -[R t_IL]x dtheta
        return J @ self.covariance @ J.T


#: Bias unknowns per knot: the relative gyro bias (3), then the accelerometer's (3).
_KNOT = 6
#: Upper bandwidth of the biases' block of the normal equations: a window couples the biases
#: of its two knots, at most ``2 _KNOT - 1`` apart.
_BAND = 2 * _KNOT - 1


def _bias_prior(n_knots: int, spacing_s: float, walks: tuple[float, float], prior_stds: tuple[float, float]) -> np.ndarray:
    """Information of each bias component's random walk between knots plus a weak absolute
    prior (gyro, then accelerometer), in LAPACK's upper banded storage (``_BAND + 1`` rows,
    ``6 n_knots`` columns; per knot ``[gyro (3), accel (3)]``)."""
    band = np.zeros((_BAND + 1, _KNOT * n_knots))
    for c in range(_KNOT):
        walk, prior_std = walks[c // 3], prior_stds[c // 3]
        info = 1.0 / (walk**2 * spacing_s)
        diagonal = np.full(n_knots, 2.0 * info)  # sum of d^T d: 1 at the ends, 2 inside
        diagonal[[0, -1]] = info if n_knots > 1 else 0.0
        band[_BAND, c::_KNOT] = diagonal + 1.0 / prior_std**2
        band[_BAND - _KNOT, _KNOT + c :: _KNOT] = -info  # between neighbouring knots
    return band


def _band_times(band: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The symmetric matrix held in upper banded storage times ``x``."""
    u = len(band) - 1
    y = band[u] * x
    for d in range(1, u + 1):
        upper = band[u - d, d:]  # entries (i, i + d)
        y[:-d] += upper * x[d:]
        y[d:] += upper * x[:-d]
    return y


def unobservable(prior: Transform, windows: list[WindowInfo], tau: float) -> SensorEstimate:
    return SensorEstimate(
        status="unobservable",
        T_base_imu=prior,
        covariance=None,
        translation_observable=np.zeros(3, dtype=bool),
        time_offset_s=tau,
        time_offset_std_s=None,
        gyro_bias=np.zeros(3),
        gyro_bias_std=None,
        accel_bias=np.zeros(3),
        accel_bias_std=None,
        bias_knots_s=np.zeros(0),
        gyro_bias_knots=np.zeros((0, 3)),
        accel_bias_knots=np.zeros((0, 3)),
        windows=windows,
        residual_rms_gyro=None,
        residual_rms_accel=None,
    )


GYRO_DIM = 11
ACCEL_DIM = 29
#: Relative resolution of a residual computed from second moments (double precision squares).
RESOLUTION = 1e-7


@dataclass(frozen=True)
class BaseMoments:
    """The base IMU's block of a window's moments, shared by every sensor (upper triangles)."""

    packed_gyro: np.ndarray  # of the (8, 8) block of x_g's base part [w_B, dw_B, 1, u]
    packed_accel: np.ndarray  # of the (26, 26) block of x_a's base part


@dataclass
class WindowMoments:
    """One window reduced to what the estimator needs: the second moments ``S = sum x x^T``,
    held as the base's block (shared between sensors) and the sensor's own three rows."""

    number: int
    start_s: float
    end_s: float
    valid: bool  # no gap in either stream
    base: BaseMoments
    rows_gyro: np.ndarray  # (3, 11): w_I^T x_g
    rows_accel: np.ndarray  # (3, 29): f_I^T x_a
    samples: int
    info: WindowInfo | None = None  # observability, filled in (in bulk) when first needed


_UPPER = {dim: np.triu_indices(dim - 3) for dim in (GYRO_DIM, ACCEL_DIM)}


def base_moments(G_gyro: np.ndarray, G_accel: np.ndarray) -> BaseMoments:
    """The base block from the Gram matrices ``X^T X`` of the base part of the data vectors,
    (8, 8) for the gyro and (26, 26) for the accelerometer."""
    return BaseMoments(G_gyro[_UPPER[GYRO_DIM]], G_accel[_UPPER[ACCEL_DIM]])


def assemble_moments(windows: Sequence[WindowMoments], which: str) -> np.ndarray:
    """The full moments ``S`` of several windows, (K, dim, dim), ``which`` is "gyro" or "accel"."""
    if which == "gyro":
        dim, rows, packed = GYRO_DIM, [w.rows_gyro for w in windows], [w.base.packed_gyro for w in windows]
    else:
        dim, rows, packed = ACCEL_DIM, [w.rows_accel for w in windows], [w.base.packed_accel for w in windows]
    rows, packed = np.stack(rows), np.stack(packed)
    upper = _UPPER[dim]
    full = np.empty((len(windows), dim, dim))
    full[:, 3 + upper[0], 3 + upper[1]] = packed
    full[:, 3 + upper[1], 3 + upper[0]] = packed
    full[:, 0:3, :] = rows
    full[:, :, 0:3] = rows.transpose(0, 2, 1)
    return full


#: Windows whose normal equations are formed together (bounds the estimator's scratch memory).
SOLVE_CHUNK = 128
#: The accelerometer's full moments are kept through the iterations up to this size (about 13 h
#: of 10 s windows); beyond it they are stacked again, a chunk at a time, every iteration.
SOLVE_CACHE_BYTES = 32 << 20


# --------------------------------------------------------------------------- the estimator


def _C_gyro(Rt: np.ndarray, dtau: float, bj: np.ndarray, bk: np.ndarray) -> np.ndarray:
    """Coefficients of ``r_g = C x_g`` per window: (K, 3, 11)."""
    K = len(bj)
    C = np.zeros((K, 3, GYRO_DIM))
    C[:, :, 0:3] = np.eye(3)
    C[:, :, 3:6] = -Rt
    C[:, :, 6:9] = dtau * Rt
    C[:, :, 9] = -bj
    C[:, :, 10] = -(bk - bj)
    return C


def _kron_t(t: np.ndarray) -> np.ndarray:
    """``t^T (x) I3``: (3, 9) with ``A t = (t^T (x) I3) vec A``."""
    return np.hstack([t[0] * np.eye(3), t[1] * np.eye(3), t[2] * np.eye(3)])


def _C_accel(Rt: np.ndarray, t: np.ndarray, dtau: float, aj: np.ndarray, ak: np.ndarray) -> np.ndarray:
    """Coefficients of ``r_a = C x_a`` per window: (K, 3, 29)."""
    K = len(aj)
    T = _kron_t(t)
    C = np.zeros((K, 3, ACCEL_DIM))
    C[:, :, 0:3] = np.eye(3)
    C[:, :, 3:6] = -Rt
    C[:, :, 6:9] = dtau * Rt
    C[:, :, 9:18] = -Rt @ T
    C[:, :, 18:27] = dtau * Rt @ T
    C[:, :, 27] = -aj
    C[:, :, 28] = -(ak - aj)
    return C


def _derivatives_gyro(C: np.ndarray, Rt: np.ndarray) -> np.ndarray:
    """d C_g / d [rot(3), dtau]: (K, 4, 3, 11); the biases' derivatives, constant, are
    :func:`_normal_equations`' own."""
    K = len(C)
    D = np.zeros((K, 4, 3, GYRO_DIM))
    rotating = C.copy()
    rotating[:, :, 0:3] = 0.0
    rotating[:, :, 9:11] = 0.0
    for m in range(3):  # R^T -> (I - [d]x) R^T
        D[:, m] = -skew(np.eye(3)[m]) @ rotating
    D[:, 3, :, 6:9] = Rt
    return D


def _derivatives_accel(C: np.ndarray, Rt: np.ndarray, t: np.ndarray, dtau: float) -> np.ndarray:
    """d C_a / d [rot(3), t(3), dtau]: (K, 7, 3, 29); the biases' derivatives, constant, are
    :func:`_normal_equations`' own."""
    K = len(C)
    D = np.zeros((K, 7, 3, ACCEL_DIM))
    rotating = C.copy()
    rotating[:, :, 0:3] = 0.0
    rotating[:, :, 27:29] = 0.0
    for m in range(3):
        D[:, m] = -skew(np.eye(3)[m]) @ rotating
        E = _kron_t(np.eye(3)[m])
        D[:, 3 + m, :, 9:18] = -Rt @ E
        D[:, 3 + m, :, 18:27] = dtau * Rt @ E
    D[:, 6, :, 6:9] = Rt
    D[:, 6, :, 18:27] = Rt @ _kron_t(t)
    return D


def _normal_equations(D: np.ndarray, S: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window: the GN Hessian ``tr(D_p S D_q^T)``, gradient ``tr(D_p S C^T)`` and cost
    ``tr(C S C^T)``, over the parameters whose derivatives ``D`` (K, P, 3, dim) gives, then the
    window's two bias knots (3 + 3): ``(K, P + 6, P + 6)``, ``(K, P + 6)``, ``(K,)``.

    A bias knot's derivative is constant and sparse: the residual's row ``m`` takes ``-b_j`` on
    the constant column ``a`` of ``x`` and ``-(b_k - b_j)`` on the time column ``b`` (the last
    two), so its products with ``S`` are entries of ``D S``, ``C S`` and ``S`` itself: only the
    other parameters' ``D S`` is multiplied out."""
    K, P, rows, dim = D.shape
    a, b = dim - 2, dim - 1
    DS = (D.reshape(K, P * rows, dim) @ S).reshape(K, P, rows, dim)
    CS = C @ S
    H = np.zeros((K, P + 6, P + 6))
    H[:, :P, :P] = DS.reshape(K, P, rows * dim) @ D.reshape(K, P, rows * dim).transpose(0, 2, 1)
    H[:, :P, P : P + 3] = DS[:, :, :, b] - DS[:, :, :, a]  # b_j: -e_a + e_b on row m
    H[:, :P, P + 3 :] = -DS[:, :, :, b]  # b_k: -e_b on row m
    H[:, P:, :P] = H[:, :P, P:].transpose(0, 2, 1)
    S_aa, S_ab, S_bb = S[:, a, a], S[:, a, b], S[:, b, b]
    for m in range(3):
        H[:, P + m, P + m] = S_aa - 2.0 * S_ab + S_bb
        H[:, P + m, P + 3 + m] = H[:, P + 3 + m, P + m] = S_ab - S_bb
        H[:, P + 3 + m, P + 3 + m] = S_bb
    g = np.empty((K, P + 6))
    g[:, :P] = (DS.reshape(K, P, rows * dim) @ C.reshape(K, rows * dim, 1))[:, :, 0]
    g[:, P : P + 3] = CS[:, :, b] - CS[:, :, a]
    g[:, P + 3 :] = -CS[:, :, b]
    cost = np.sum(CS * C, axis=(1, 2))
    return H, g, cost


def _bounded_step(L: np.ndarray, s: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The step minimising ``|L^T x - L^-1 s|^2`` (``x^T S x / 2 - s^T x`` with ``S = L L^T``)
    inside the box ``[lower, upper]``. The cost is strictly convex, so where the unconstrained
    minimiser ``S^-1 s`` lies in the box it is the answer; otherwise the box is taken by
    ``scipy.optimize.lsq_linear`` (bounded-variable least squares; imported only then)."""
    target = np.linalg.solve(L, s)
    free = np.linalg.solve(L.T, target)
    if np.all(free >= lower) and np.all(free <= upper):
        return free
    from scipy.optimize import lsq_linear

    return lsq_linear(L.T, target, bounds=(lower, upper), method="bvls", tol=1e-12).x


def kabsch_rotation(S_gyro: np.ndarray, samples: np.ndarray) -> Rotation:
    """``R_base_imu`` minimising ``sum |R^T w_B - w_I|^2`` over windows, each centred (eq. 10).

    From the gyro moments ``S = sum x x^T``, ``x = [w_I, w_B, dw_B, 1, u]`` (K, 11, 11): centring
    per window removes a constant relative gyro bias. Kabsch/Horn: with the centred cross
    covariance ``sum w_I w_B^T = U diag(s) V^T``, ``R_imu_base = U diag(1, 1, det) V^T``.
    """
    n = samples[:, None, None]
    mean_I, mean_B = S_gyro[:, 0:3, 9][:, :, None] / n, S_gyro[:, 3:6, 9][:, :, None] / n
    cross = np.sum(S_gyro[:, 0:3, 3:6] - n * mean_I @ mean_B.transpose(0, 2, 1), axis=0)
    U, _, Vt = np.linalg.svd(cross)
    d = np.sign(np.linalg.det(U @ Vt))
    R_imu_base = U @ np.diag([1.0, 1.0, d]) @ Vt
    return Rotation.from_matrix(R_imu_base.T)


def solve(
    windows: list[WindowMoments],
    prior: Transform,
    options: CalibrationOptions,
    tau0: float,
    sigma: tuple[float, float],
    lowpass: Lowpass,
) -> SensorEstimate:
    """Joint Gauss-Newton estimate from the selected windows' moments (see module docstring)."""
    used = [w for w in windows if w.info is not None and w.info.selected]
    numbers = np.array([w.number for w in used])
    n_knots = int(max(w.number for w in windows)) + 2
    S_g = assemble_moments(used, "gyro")  # (K, 11, 11): small
    # the accelerometer's moments are stacked a chunk at a time (memory bounded by the chunk)
    starts = range(0, len(used), SOLVE_CHUNK)

    def S_a_chunk(a: int) -> np.ndarray:
        return assemble_moments(used[a : a + SOLVE_CHUNK], "accel")

    trace_f = float(sum(np.trace(w.rows_accel[:, 0:3]) for w in used))
    samples = sum(w.samples for w in used)
    gain = lowpass.white_noise_gain()

    R = kabsch_rotation(S_g, np.array([w.samples for w in used], dtype=float))
    t = prior.translation.copy()
    t_prior, bound = prior.translation, options.translation_bound_m
    dtau = 0.0
    knots = np.zeros((n_knots, _KNOT))  # [gyro bias, accel bias] per knot
    prior_band = _bias_prior(
        n_knots, options.window_s, (options.gyro_bias_walk, ACCEL_BIAS_WALK), (options.gyro_bias_prior_std, ACCEL_BIAS_PRIOR_STD)
    )
    n_bias = _KNOT * n_knots
    # Where each window's normal equations go (the same every iteration). Unknowns: globals
    # [rot 0-2, t 3-5, dtau 6], then the biases, per knot [gyro 0-2, accel 3-5]. A window's gyro
    # equations hold [rot, dtau, its two knots' gyro biases], its accelerometer's [rot, t, dtau,
    # their accel biases]: the globals' rows and columns, and the biases' (bias index).
    K = len(used)
    globals_g, globals_a = np.array([0, 1, 2, 6]), np.arange(7)
    biases_g = _KNOT * numbers[:, None] + np.array([0, 1, 2, 6, 7, 8])
    biases_a = _KNOT * numbers[:, None] + np.array([3, 4, 5, 9, 10, 11])
    upper6 = np.triu_indices(6)  # a window's bias indices increase: these are its upper entries

    def band_at(biases: np.ndarray) -> np.ndarray:  # flat index into the (_BAND + 1, n_bias) band
        i, j = biases[:, upper6[0]], biases[:, upper6[1]]
        return ((_BAND + i - j) * n_bias + j).ravel()

    band_g, band_a = band_at(biases_g), band_at(biases_a)
    cross_g = (globals_g[None, :, None] * n_bias + biases_g[:, None, :]).ravel()  # into (7, n_bias)
    cross_a = (globals_a[None, :, None] * n_bias + biases_a[:, None, :]).ravel()
    # the accelerometer's moments, stacked once where they are small, else a chunk at a time
    cached = [S_a_chunk(a) for a in starts] if K * ACCEL_DIM**2 * 8 <= SOLVE_CACHE_BYTES else None

    scale_g, scale_a = sigma[0] * np.sqrt(gain), sigma[1] * np.sqrt(gain)
    # A cost from moments is a difference of large sums: below RESOLUTION times the signal's RMS
    # the residual is round-off, not noise (noise-free data).
    floor_g = (RESOLUTION**2) * np.trace(S_g[:, 0:3, 0:3].sum(axis=0)) / (3 * samples)
    floor_a = (RESOLUTION**2) * trace_f / (3 * samples)
    free_global = np.ones(7, dtype=bool)
    if options.max_time_offset_s <= 0:
        free_global[6] = False
    observable = np.ones(3, dtype=bool)
    converged_once = False
    S_inv = np.zeros((0, 0))
    cost_g = cost_a = np.zeros(len(used))
    factor = None
    X = np.zeros((0, 0))
    iterations = 0
    for iterations in range(1, options.max_iterations + 1):  # noqa: B007
        Rt = R.inv().as_matrix()
        bj, bk = knots[numbers], knots[numbers + 1]
        Cg = _C_gyro(Rt, dtau, bj[:, 0:3], bk[:, 0:3])
        Ca = _C_accel(Rt, t, dtau, bj[:, 3:6], bk[:, 3:6])
        Hg, gg, cost_g = _normal_equations(_derivatives_gyro(Cg, Rt), S_g, Cg)
        parts = []
        for n, a in enumerate(starts):
            chunk = slice(a, a + SOLVE_CHUNK)  # the accelerometer's (K, 7, 3, 29) in slices
            S_a = cached[n] if cached is not None else S_a_chunk(a)
            parts.append(_normal_equations(_derivatives_accel(Ca[chunk], Rt, t, dtau), S_a, Ca[chunk]))
        Ha, ga, cost_a = (np.concatenate([p[i] for p in parts]) for i in range(3))
        if iterations > 1:  # residual variance from the fit, above what the moments resolve
            scale_g = float(np.sqrt(max(cost_g.sum() / (3 * samples), floor_g)))
            scale_a = float(np.sqrt(max(cost_a.sum() / (3 * samples), floor_a)))
        wg, wa = gain / scale_g**2, gain / scale_a**2
        # the normal equations: the globals' 7x7 block, their coupling to the biases, the
        # biases' banded block (with the prior) and the gradient
        Hg, Ha, gg, ga = wg * Hg, wa * Ha, wg * gg, wa * ga
        H_gg_all = np.zeros((7, 7))
        H_gg_all[np.ix_(globals_g, globals_g)] += Hg[:, :4, :4].sum(axis=0)
        H_gg_all += Ha[:, :7, :7].sum(axis=0)
        H_gb_all = (np.bincount(cross_g, Hg[:, :4, 4:].ravel(), 7 * n_bias) + np.bincount(cross_a, Ha[:, :7, 7:].ravel(), 7 * n_bias)).reshape(7, n_bias)
        size = (_BAND + 1) * n_bias
        H_bb = (np.bincount(band_g, Hg[:, 4:, 4:][:, upper6[0], upper6[1]].ravel(), size) + np.bincount(band_a, Ha[:, 7:, 7:][:, upper6[0], upper6[1]].ravel(), size)).reshape(_BAND + 1, n_bias)
        H_bb += prior_band
        grad_g = -ga[:, :7].sum(axis=0)
        grad_g[globals_g] -= gg[:, :4].sum(axis=0)
        x_bias = knots.ravel()
        grad_b = -(np.bincount(biases_g.ravel(), gg[:, 4:].ravel(), n_bias) + np.bincount(biases_a.ravel(), ga[:, 7:].ravel(), n_bias))
        grad_b -= _band_times(prior_band, x_bias)
        free = np.flatnonzero(free_global & np.concatenate([[True] * 3, observable, [True]]))
        H_gg = H_gg_all[np.ix_(free, free)]
        H_gb = H_gb_all[free]
        factor = (cholesky_banded(H_bb, lower=False), False)
        X = cho_solve_banded(factor, H_gb.T)
        S = H_gg - H_gb @ X
        s = grad_g[free] - X.T @ grad_b
        lower, upper = np.full(len(free), -np.inf), np.full(len(free), np.inf)
        for k, col in enumerate(free):
            if 3 <= col < 6:
                lower[k] = t_prior[col - 3] - bound - t[col - 3]
                upper[k] = t_prior[col - 3] + bound - t[col - 3]
        L = np.linalg.cholesky(S)
        step_free = _bounded_step(L, s, lower, upper)
        step = np.zeros(7)
        step[free] = step_free
        step_bias = cho_solve_banded(factor, grad_b - H_gb.T @ step_free)
        R = R * Rotation.from_rotvec(step[:3])
        t = t + step[3:6]
        dtau = dtau + step[6]
        knots = knots + step_bias.reshape(n_knots, 6)
        S_inv = np.linalg.inv(S)
        small = np.max(np.abs(step[:3])) < 1e-10 and np.max(np.abs(step[3:])) < 1e-8
        if small and iterations > 2:
            t_std = np.full(3, np.inf)
            for k, col in enumerate(free):
                if 3 <= col < 6:
                    t_std[col - 3] = np.sqrt(S_inv[k, k])
            weak = observable & (t_std >= OBSERVABLE_FRACTION_OF_BOUND * bound)
            if weak.any() and not converged_once:
                observable &= ~weak
                t[~observable] = t_prior[~observable]
                converged_once = True
                continue
            break

    cov = np.zeros((7, 7))
    cov[np.ix_(free, free)] = S_inv
    for axis in range(3):
        if not observable[axis]:
            cov[3 + axis, 3 + axis] = bound**2 / 3.0
    rot = np.eye(6)
    rot[:3, :3] = R.as_matrix()
    cov6 = rot @ cov[:6, :6] @ rot.T

    last = n_knots - 1
    bias_std = None
    if factor is not None:
        cols_last = [_KNOT * last + a for a in range(_KNOT)]
        E = np.zeros((n_bias, _KNOT))
        E[cols_last, np.arange(_KNOT)] = 1.0
        Y = cho_solve_banded(factor, E)
        XtE = X.T @ E
        block = Y[cols_last] + XtE.T @ S_inv @ XtE
        bias_std = np.sqrt(np.clip(np.diag(block), 0.0, None))
    n_total = 3 * samples
    return SensorEstimate(
        status="ok" if observable.all() else "partial",
        T_base_imu=Transform(R, t),
        covariance=cov6,
        translation_observable=observable.copy(),
        time_offset_s=float(tau0 + dtau),
        time_offset_std_s=float(np.sqrt(cov[6, 6])) if free_global[6] else None,
        gyro_bias=knots[last, 0:3].copy(),
        gyro_bias_std=bias_std[0:3] if bias_std is not None else None,
        accel_bias=knots[last, 3:6].copy(),
        accel_bias_std=bias_std[3:6] if bias_std is not None else None,
        bias_knots_s=np.arange(n_knots) * options.window_s,
        gyro_bias_knots=knots[:, 0:3].copy(),
        accel_bias_knots=knots[:, 3:6].copy(),
        windows=[w.info for w in windows if w.info is not None],
        residual_rms_gyro=float(np.sqrt(max(cost_g.sum(), 0.0) / n_total)),
        residual_rms_accel=float(np.sqrt(max(cost_a.sum(), 0.0) / n_total)),
        iterations=iterations,
        noise_std={"gyro_radps": sigma[0], "accel_mps2": sigma[1]},
    )
