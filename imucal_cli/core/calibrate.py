"""Extrinsics of one sensor IMU in the base frame from the two IMUs' signals (paper eqs. 10-17).

This module holds the estimator; :mod:`imucal_cli.core.streaming` reduces the signals to the
per-window sufficient statistics it works on.

The paper solves the rotation by Kabsch/Horn (eq. 10) and then the translation by bounded least
squares (eq. 16). Here the Kabsch/Horn solution over the selected windows only initialises a
joint Gauss-Newton estimate of everything the two signals share:

- gyro (eq. 10): ``w_I(t + tau) = R^T w_B(t) + b_g(t)``
- accelerometer (eq. 11): ``f_I(t + tau) = R^T (f_B + ([dw_B]x + [w_B]x^2) t_BI)(t) + b_a(t)``

(each right side multiplied by the sensor triad's axes ``I + E`` where the drive shows their errors)

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
LAPACK's banded Cholesky), so the remaining small problem in ``(rotation, translation, tau)``
takes the translation box of eq. 16 through ``scipy.optimize.lsq_linear`` (where the box
binds).

A number is only as good as the model behind it, so :func:`solve` also tests the model on the
data (the gyro's rotation against the accelerometer's, a mount that tilts with the vehicle's
acceleration, the residual level) and makes the covariance honest: the inverse Fisher
information (residual variance from the fit, corrected for the low-pass's correlation of
neighbouring residuals), inflated per axis to a delete-a-group jackknife over the windows, by
the checks that fail, and by the distance to where the data pull an axis that rests on its box.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.spatial.transform import Rotation

from imucal_cli.core.segments import OBSERVABLE_FRACTION_OF_BOUND, WindowInfo
from imucal_cli.core.signals import LOWPASS_HZ, Lowpass
from imucal_cli.core.so3 import skew
from imucal_cli.core.timing import TIME_OFFSET_MAX_STD_S
from imucal_cli.types import GRAVITY_MPS2, Transform

#: Random walk of the accelerometer bias allowed between knots (m/s^2/sqrt(s)): loose, a few
#: times what MEMS parts drift, so the data decide.
ACCEL_BIAS_WALK = 0.01
#: Prior standard deviation of the accelerometer bias (m/s^2): keeps knots without data defined.
ACCEL_BIAS_PRIOR_STD = 1.0


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
    consistency_alpha: float = 0.001  # false-alarm rate of each model-consistency check
    rotation_floor_deg: float = 0.0  # systematic std the data cannot see, added to the result's
    translation_floor_m: float = 0.0


@dataclass(frozen=True)
class SensorEstimate:
    """The estimate for one sensor IMU and how well the drive determines it."""

    status: str  # ok | partial | inconsistent | unobservable
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
    warnings: list[str] = field(default_factory=list)
    #: The model-consistency checks (SPEC ``checks``): name -> figures and ``pass``.
    checks: dict[str, dict[str, Any]] = field(default_factory=dict)
    time_offset_observable: bool = False
    tilt_rad_per_mps2: np.ndarray | None = None  # the mount's, where the rigid-mount check estimated it
    #: The accelerometer's and the gyro's scale factors and non-orthogonality, and the gyro's
    #: g-sensitivity, where the drive shows them.
    accel_intrinsics: dict[str, Any] = field(default_factory=dict)
    gyro_intrinsics: dict[str, Any] = field(default_factory=dict)
    #: Per window used: start (s, grid clock), gyro and accelerometer residual RMS of the fit.
    window_residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

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
        warnings=[_unobservable_reason(windows)],
    )


def _unobservable_reason(windows: list[WindowInfo]) -> str:
    """Why no window was selected: gaps in the data (dropped or missing samples), or motion."""
    broken = sum(not w.valid for w in windows)
    if windows and broken == len(windows):
        return f"every window ({broken}) has a gap in the data (samples missing or dropped): the prior is returned"
    if broken:
        return f"no window carried enough motion ({broken} of {len(windows)} have a gap in the data): the prior is returned"
    return "no window carried enough motion: the prior is returned"


GYRO_DIM = 14
ACCEL_DIM = 33
#: The sensor's own leading entries of each data vector: x_g's [w_I, f_I], x_a's f_I.
OWN_ENTRIES = {GYRO_DIM: 6, ACCEL_DIM: 3}
#: Relative resolution of a residual computed from second moments (double precision squares).
RESOLUTION = 1e-7


@dataclass(frozen=True)
class BaseMoments:
    """The base IMU's block of a window's moments, shared by every sensor (upper triangles)."""

    packed_gyro: np.ndarray  # of the (8, 8) block of x_g's base part [w_B, dw_B, 1, u]
    packed_accel: np.ndarray  # of the (30, 30) block of x_a's base part


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


_UPPER = {dim: np.triu_indices(dim - own) for dim, own in OWN_ENTRIES.items()}


def base_moments(G_gyro: np.ndarray, G_accel: np.ndarray) -> BaseMoments:
    """The base block from the Gram matrices ``X^T X`` of the base part of the data vectors,
    (8, 8) for the gyro and (30, 30) for the accelerometer."""
    return BaseMoments(G_gyro[_UPPER[GYRO_DIM]], G_accel[_UPPER[ACCEL_DIM]])


def assemble_moments(windows: Sequence[WindowMoments], which: str) -> np.ndarray:
    """The full moments ``S`` of several windows, (K, dim, dim), ``which`` is "gyro" or "accel"."""
    if which == "gyro":
        dim, row_list, packed_list = GYRO_DIM, [w.rows_gyro for w in windows], [w.base.packed_gyro for w in windows]
    else:
        dim, row_list, packed_list = ACCEL_DIM, [w.rows_accel for w in windows], [w.base.packed_accel for w in windows]
    rows, packed = np.stack(row_list), np.stack(packed_list)
    upper, own = _UPPER[dim], OWN_ENTRIES[dim]
    full = np.empty((len(windows), dim, dim))
    full[:, own + upper[0], own + upper[1]] = packed
    full[:, own + upper[1], own + upper[0]] = packed
    full[:, 0:own, :] = rows
    full[:, :, 0:own] = rows.transpose(0, 2, 1)
    return full


#: ``vec([n]x) = VEC_SKEW n`` (column-major vec): how the angular acceleration's noise enters
#: the ``vec A`` columns of x_a.
VEC_SKEW = np.zeros((9, 3))
for _column, _row, _component, _sign in ((0, 1, 2, 1), (0, 2, 1, -1), (1, 0, 2, -1), (1, 2, 0, 1), (2, 0, 1, 1), (2, 1, 0, -1)):
    VEC_SKEW[3 * _column + _row, _component] = _sign


#: Windows whose normal equations are formed together (bounds the estimator's scratch memory).
SOLVE_CHUNK = 128
#: The accelerometer's full moments are kept through the iterations up to this size (about 13 h
#: of 10 s windows); beyond it they are stacked again, a chunk at a time, every iteration.
SOLVE_CACHE_BYTES = 32 << 20


# --------------------------------------------------------------------------- the model

#: The estimate's global unknowns: a rotation step (3, right-multiplied onto ``R_base_imu``:
#: IMU axes), ``t_base_imu`` (3), the clock-offset step (1), the mount's tilt (2: roll per
#: lateral and pitch per longitudinal specific force, rad per m/s^2; estimated by the rigid-mount
#: check only), the accelerometer's axis errors (6, :data:`INTRINSICS`), the gyro's (6,
#: :data:`GYRO_INTRINSICS`) and the gyro's g-sensitivity (9, :data:`G_SENSITIVITY`).
N_GLOBAL = 30
TAU = 6
TILT = slice(7, 9)
#: A triad's axis errors: ``f_measured = (I + E) f`` (``w_measured = (I + E) w``) with ``E``
#: symmetric (scale factors on the diagonal, non-orthogonality off it), as :data:`SYMMETRIC`
#: spans it.
INTRINSICS = slice(9, 15)
GYRO_INTRINSICS = slice(15, 21)
#: The gyro's g-sensitivity: ``w_measured = (I + E) w + G f`` with ``G`` (rad/s per m/s^2,
#: row-major, the IMU's axes) acting on the specific force the sensor's own accelerometer
#: measures.
G_SENSITIVITY = slice(21, 30)
#: The sensor's own errors, as ``_Fit.intrinsics`` holds them: the accelerometer's axis errors,
#: the gyro's, its g-sensitivity.
AXES = slice(9, 30)
SYMMETRIC = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
    SYMMETRIC[_k, _i, _j] = SYMMETRIC[_k, _j, _i] = 1.0
#: The globals the gyro equations hold.
_GYRO_GLOBALS = np.array([0, 1, 2, TAU, *range(GYRO_INTRINSICS.start, G_SENSITIVITY.stop)])
_P_GYRO = len(_GYRO_GLOBALS)
#: The globals the accelerometer's equations hold: all before the gyro's own.
_ACCEL_GLOBALS = np.arange(GYRO_INTRINSICS.start)
_P_ACCEL = len(_ACCEL_GLOBALS)


def _C_gyro(Rt: np.ndarray, dtau: float, G: np.ndarray, bj: np.ndarray, bk: np.ndarray) -> np.ndarray:
    """Coefficients of ``r_g = C x_g`` per window, ``x_g = [w_I, f_I, w_B, dw_B, 1, u]``: (K, 3,
    14); ``Rt`` is the gyro's ``(I + E) R^T``, ``G`` its g-sensitivity (:data:`G_SENSITIVITY`)."""
    K = len(bj)
    C = np.zeros((K, 3, GYRO_DIM))
    C[:, :, 0:3] = np.eye(3)
    C[:, :, 3:6] = -G
    C[:, :, 6:9] = -Rt
    C[:, :, 9:12] = dtau * Rt
    C[:, :, 12] = -bj
    C[:, :, 13] = -(bk - bj)
    return C


def _kron_t(t: np.ndarray) -> np.ndarray:
    """``t^T (x) I3``: (3, 9) with ``A t = (t^T (x) I3) vec A``."""
    return np.hstack([t[0] * np.eye(3), t[1] * np.eye(3), t[2] * np.eye(3)])


def _tilt_columns(Rt: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """Coefficients (3, 4) of the tilt columns ``q = [f_y f_z, f_y^2, f_x f_z, f_x^2]`` of x_a.

    A mount leaning by ``theta = (k_roll f_y, k_pitch f_x, 0)`` (base axes) turns the specific
    force it sees into ``R^T exp(-[theta]x) f ~ R^T (f + f x theta)``, and
    ``f x theta = k_roll (0, q1, -q2) + k_pitch (-q3, 0, q4)``."""
    k_roll, k_pitch = tilt
    return np.stack([-k_roll * Rt[:, 1], k_roll * Rt[:, 2], k_pitch * Rt[:, 0], -k_pitch * Rt[:, 2]], axis=-1)


def _axes(intrinsics: np.ndarray) -> np.ndarray:
    """``I + E``: a triad's axes from its six axis errors (:data:`INTRINSICS`)."""
    return np.eye(3) + np.tensordot(intrinsics, SYMMETRIC, axes=1)


def _C_accel(Rt: np.ndarray, t: np.ndarray, dtau: float, tilt: np.ndarray, aj: np.ndarray, ak: np.ndarray) -> np.ndarray:
    """Coefficients of ``r_a = C x_a`` per window: (K, 3, 33); ``Rt`` is the accelerometer's
    ``(I + E) R^T``."""
    K = len(aj)
    T = _kron_t(t)
    C = np.zeros((K, 3, ACCEL_DIM))
    C[:, :, 0:3] = np.eye(3)
    C[:, :, 3:6] = -Rt
    C[:, :, 6:9] = dtau * Rt
    C[:, :, 9:18] = -Rt @ T
    C[:, :, 18:27] = dtau * Rt @ T
    C[:, :, 27:31] = _tilt_columns(Rt, tilt)
    C[:, :, 31] = -aj
    C[:, :, 32] = -(ak - aj)
    return C


def _derivatives_gyro(C: np.ndarray, Rt: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """d C_g / d [rot(3), dtau, intrinsics(6), g-sensitivity(9)] (:data:`_GYRO_GLOBALS`):
    (K, 19, 3, 14), with ``Rt`` the gyro's ``(I + E) R^T`` and ``axes`` its ``I + E`` (as
    :func:`_derivatives_accel`); the biases' derivatives, constant, are
    :func:`_normal_equations`' own."""
    K = len(C)
    D = np.zeros((K, _P_GYRO, 3, GYRO_DIM))
    rotating = np.zeros_like(C)
    rotating[:, :, 6:12] = C[:, :, 6:12]  # the columns (I + E) R^T K: w_B's and dw_B's
    inverse = np.linalg.inv(axes)
    for m in range(3):  # R^T -> (I - [d]x) R^T
        D[:, m] = -(axes @ skew(np.eye(3)[m]) @ inverse) @ rotating
    D[:, 3, :, 9:12] = Rt
    for b in range(6):
        D[:, 4 + b] = (SYMMETRIC[b] @ inverse) @ rotating
    for i in range(3):
        for j in range(3):  # G_ij: row i of f_I's block takes -1 in column j
            D[:, 10 + 3 * i + j, i, 3 + j] = -1.0
    return D


def _derivatives_accel(C: np.ndarray, Rt: np.ndarray, t: np.ndarray, dtau: float, axes: np.ndarray) -> np.ndarray:
    """d C_a / d [rot(3), t(3), dtau, tilt(2), intrinsics(6)] (:data:`_ACCEL_GLOBALS`): (K, 15,
    3, 33), with ``Rt`` the
    accelerometer's ``(I + E) R^T`` and ``axes`` its ``I + E``; the biases' derivatives,
    constant, are :func:`_normal_equations`' own.

    Every column but ``f_I``'s and the biases' is ``-(I + E) R^T K`` (``K`` data-free), so a
    rotation step (``R^T -> (I - [d]x) R^T``) takes ``-(I + E) [d]x (I + E)^-1`` of them and an
    intrinsic ``E_b`` takes ``S_b (I + E)^-1`` of them."""
    K = len(C)
    D = np.zeros((K, _P_ACCEL, 3, ACCEL_DIM))
    rotating = C.copy()
    rotating[:, :, 0:3] = 0.0
    rotating[:, :, 31:33] = 0.0
    inverse = np.linalg.inv(axes)
    for m in range(3):
        D[:, m] = -(axes @ skew(np.eye(3)[m]) @ inverse) @ rotating
        E = _kron_t(np.eye(3)[m])
        D[:, 3 + m, :, 9:18] = -Rt @ E
        D[:, 3 + m, :, 18:27] = dtau * Rt @ E
    D[:, TAU, :, 6:9] = Rt
    D[:, TAU, :, 18:27] = Rt @ _kron_t(t)
    D[:, 7, :, 27:31] = _tilt_columns(Rt, np.array([1.0, 0.0]))
    D[:, 8, :, 27:31] = _tilt_columns(Rt, np.array([0.0, 1.0]))
    for b in range(6):
        D[:, INTRINSICS.start + b] = (SYMMETRIC[b] @ inverse) @ rotating
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


def _bounded_step(L: np.ndarray, s: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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

    return lsq_linear(L.T, target, bounds=(lower, upper), method="bvls", tol=1e-12).x, free


def kabsch_rotation(S_gyro: np.ndarray, samples: np.ndarray) -> Rotation:
    """``R_base_imu`` minimising ``sum |R^T w_B - w_I|^2`` over windows, each centred (eq. 10).

    From the gyro moments ``S = sum x x^T``, ``x = [w_I, f_I, w_B, dw_B, 1, u]`` (K, 14, 14): centring
    per window removes a constant relative gyro bias. Kabsch/Horn: with the centred cross
    covariance ``sum w_I w_B^T = U diag(s) V^T``, ``R_imu_base = U diag(1, 1, det) V^T``.
    """
    n = samples[:, None, None]
    one = GYRO_DIM - 2  # the constant column
    mean_I, mean_B = S_gyro[:, 0:3, one][:, :, None] / n, S_gyro[:, 6:9, one][:, :, None] / n
    cross = np.sum(S_gyro[:, 0:3, 6:9] - n * mean_I @ mean_B.transpose(0, 2, 1), axis=0)
    U, _, Vt = np.linalg.svd(cross)
    d = np.sign(np.linalg.det(U @ Vt))
    R_imu_base = U @ np.diag([1.0, 1.0, d]) @ Vt
    return Rotation.from_matrix(R_imu_base.T)


# --------------------------------------------------------------------------- one fit


@dataclass
class _Fit:
    """One Gauss-Newton solution of the joint problem and its Fisher information."""

    R: Rotation
    t: np.ndarray
    dtau: float
    tilt: np.ndarray  # (2,)
    knots: np.ndarray  # (n_knots, 6): [gyro bias, accel bias] per knot
    free: np.ndarray  # (N_GLOBAL,) bool: the globals estimated
    scale_g: float  # residual std per grid sample (rad/s, m/s^2), from the fit
    scale_a: float
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((N_GLOBAL, N_GLOBAL)))  # free globals (rotation: IMU axes)
    unconstrained_t: np.ndarray = field(default_factory=lambda: np.zeros(3))  # where the box did not stop t
    cost_g: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per window
    cost_a: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias_std: np.ndarray | None = None  # (6,) of the last knot
    iterations: int = 0
    intrinsics: np.ndarray = field(default_factory=lambda: np.zeros(21))  # the sensor's own errors (AXES)

    def std(self) -> np.ndarray:
        """(N_GLOBAL,) standard deviations; inf where not estimated."""
        return np.where(self.free, np.sqrt(np.clip(np.diag(self.covariance), 0.0, None)), np.inf)

    def rotation_covariance_base(self) -> np.ndarray:
        """3x3 covariance of the rotation about the base axes."""
        Rm = self.R.as_matrix()
        return Rm @ self.covariance[:3, :3] @ Rm.T


class _Problem:
    """The normal equations' parts of one sensor's selected windows that stay fixed over
    iterations (see the module docstring): moments, where each window's entries go, the bias
    prior. :meth:`fit` solves it for any set of free globals, either equation alone, and any
    subset of windows (the jackknife)."""

    def __init__(
        self, windows: list[WindowMoments], prior: Transform, options: CalibrationOptions, sigma: tuple[float, float], lowpass: Lowpass, dw_noise_var: float
    ) -> None:
        used = [w for w in windows if w.info is not None and w.info.selected]
        self.used, self.prior, self.options, self.sigma = used, prior, options, sigma
        self.dw_noise_var = dw_noise_var
        self.numbers = np.array([w.number for w in used])
        self.n_knots = int(max(w.number for w in windows)) + 2
        self.S_g = assemble_moments(used, "gyro")  # (K, 14, 14): small
        self.starts = range(0, len(used), SOLVE_CHUNK)
        K = len(used)
        # the accelerometer's moments, stacked once where they are small, else a chunk at a time
        self.cached = [self._S_a(a) for a in self.starts] if K * ACCEL_DIM**2 * 8 <= SOLVE_CACHE_BYTES else None
        self.samples_per_window = np.array([w.samples for w in used], dtype=float)
        self.samples = float(self.samples_per_window.sum())
        self.gain = lowpass.white_noise_gain()
        # A cost from moments is a difference of large sums: below RESOLUTION times the signal's
        # RMS the residual is round-off, not noise (noise-free data).
        trace_f = float(sum(np.trace(w.rows_accel[:, 0:3]) for w in used))
        self.floor_g = (RESOLUTION**2) * np.trace(self.S_g[:, 0:3, 0:3].sum(axis=0)) / (3 * self.samples)
        self.floor_a = (RESOLUTION**2) * trace_f / (3 * self.samples)
        # the sensor's signal about each window's mean, per axis (RMS)
        def spread(rows: np.ndarray, n: int) -> float:  # sum |x - mean|^2 from x^T [x, ..., 1, u]
            return float(np.trace(rows[:, 0:3]) - rows[:, -2] @ rows[:, -2] / n)

        self.signal_rms = (
            float(np.sqrt(sum(spread(w.rows_gyro[:3], w.samples) for w in used) / (3 * self.samples))),
            float(np.sqrt(sum(spread(w.rows_accel, w.samples) for w in used) / (3 * self.samples))),
        )
        self.prior_band = _bias_prior(
            self.n_knots, options.window_s, (options.gyro_bias_walk, ACCEL_BIAS_WALK), (options.gyro_bias_prior_std, ACCEL_BIAS_PRIOR_STD)
        )
        n_bias = self.n_bias = _KNOT * self.n_knots
        # Where each window's normal equations go (the same every iteration). Unknowns: the
        # globals, then the biases, per knot [gyro 0-2, accel 3-5]. A window's gyro equations
        # hold [rot, dtau, its two knots' gyro biases], its accelerometer's [the globals, their
        # accel biases].
        self.biases_g = _KNOT * self.numbers[:, None] + np.array([0, 1, 2, 6, 7, 8])
        self.biases_a = _KNOT * self.numbers[:, None] + np.array([3, 4, 5, 9, 10, 11])
        upper6 = self.upper6 = np.triu_indices(6)  # a window's bias indices increase: its upper entries

        def band_at(biases: np.ndarray) -> np.ndarray:  # flat index into the (_BAND + 1, n_bias) band
            i, j = biases[:, upper6[0]], biases[:, upper6[1]]
            return ((_BAND + i - j) * n_bias + j).ravel()

        self.band_g, self.band_a = band_at(self.biases_g), band_at(self.biases_a)
        self.cross_g = (_GYRO_GLOBALS[None, :, None] * n_bias + self.biases_g[:, None, :]).ravel()
        self.cross_a = (_ACCEL_GLOBALS[None, :, None] * n_bias + self.biases_a[:, None, :]).ravel()
        self._last: tuple[bytes, tuple[np.ndarray, ...]] | None = None

    def _S_a(self, a: int) -> np.ndarray:
        """The accelerometer's moments of a chunk of windows, less what the angular
        acceleration's noise adds to the ``vec A`` block (errors in variables: uncorrected,
        it counts as lever-arm information and pulls the lever arm towards the origin)."""
        windows = self.used[a : a + SOLVE_CHUNK]
        S = assemble_moments(windows, "accel")
        noise = self.dw_noise_var * VEC_SKEW @ VEC_SKEW.T
        S[:, 9:18, 9:18] -= np.array([w.samples for w in windows], dtype=float)[:, None, None] * noise
        return S

    def _linearised(
        self, R: Rotation, t: np.ndarray, dtau: float, tilt: np.ndarray, intrinsics: np.ndarray, knots: np.ndarray,
    ) -> tuple[np.ndarray, ...]:
        """Every window's unweighted normal equations at a point (:func:`_normal_equations`,
        the gyro's then the accelerometer's). The last point's are kept: the jackknife's
        replicates and the one-equation checks all take their one step from the same fit."""
        key = b"".join(np.asarray(v, dtype=np.float64).tobytes() for v in (R.as_quat(), t, dtau, tilt, intrinsics, knots))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        Rt = R.inv().as_matrix()
        bj, bk = knots[self.numbers], knots[self.numbers + 1]
        axes, axes_g, G = _axes(intrinsics[:6]), _axes(intrinsics[6:12]), intrinsics[12:].reshape(3, 3)
        Rt_g, Rt_a = axes_g @ Rt, axes @ Rt  # each triad's (I + E) R^T
        Cg = _C_gyro(Rt_g, dtau, G, bj[:, 0:3], bk[:, 0:3])
        Ca = _C_accel(Rt_a, t, dtau, tilt, bj[:, 3:6], bk[:, 3:6])
        parts_g, parts_a = [], []
        for n, a in enumerate(self.starts):
            chunk = slice(a, a + SOLVE_CHUNK)  # the derivatives, (K, 19, 3, 14) and (K, 15, 3, 33), in slices
            parts_g.append(_normal_equations(_derivatives_gyro(Cg[chunk], Rt_g, axes_g), self.S_g[chunk], Cg[chunk]))
            S_a = self.cached[n] if self.cached is not None else self._S_a(a)
            parts_a.append(_normal_equations(_derivatives_accel(Ca[chunk], Rt_a, t, dtau, axes), S_a, Ca[chunk]))
        gyro, accel = (tuple(np.concatenate([p[i] for p in parts]) for i in range(3)) for parts in (parts_g, parts_a))
        self._last = (key, (*gyro, *accel))
        return self._last[1]

    def translation_information_diagonal(self) -> np.ndarray:
        """Per axis, the lever arm's information ``sum (A - mean A)^T (A - mean A)`` over the
        windows (each centred), less the angular acceleration's noise (unit residual)."""
        total = np.zeros(3)
        for k, a in enumerate(self.starts):
            S = self.cached[k] if self.cached is not None else self._S_a(a)
            n = S[:, ACCEL_DIM - 2, ACCEL_DIM - 2]
            mean = S[:, 9:18, ACCEL_DIM - 2] / n[:, None]
            centred = S[:, 9:18, 9:18] - n[:, None, None] * mean[:, :, None] * mean[:, None, :]
            blocks = centred.sum(axis=0).reshape(3, 3, 3, 3)  # (j, a, l, b) of vec A = A[a, j]
            total += np.einsum("jaja->j", blocks)
        return total

    def eiv_variance(self, t: np.ndarray) -> float:
        """Per-axis variance the angular acceleration's noise adds to the accelerometer's
        residual at lever arm ``t``: ``E |n x t|^2 / 3``."""
        return 2.0 / 3.0 * self.dw_noise_var * float(t @ t)

    def start(self) -> _Fit:
        """The starting point: Kabsch/Horn over the windows (eq. 10), the prior's translation."""
        R = kabsch_rotation(self.S_g, self.samples_per_window)
        scale_g, scale_a = (s * np.sqrt(self.gain) for s in self.sigma)
        free = np.ones(N_GLOBAL, dtype=bool)
        free[TILT] = False
        free[AXES] = False
        return _Fit(R, self.prior.translation.copy(), 0.0, np.zeros(2), np.zeros((self.n_knots, _KNOT)), free, scale_g, scale_a)

    def fit(
        self,
        start: _Fit,
        free: np.ndarray,
        use: tuple[bool, bool] = (True, True),
        window_weights: np.ndarray | None = None,
        estimate_scale: bool = False,
        max_iterations: int | None = None,
        rotation_prior_std: float | None = None,
    ) -> _Fit:
        """Gauss-Newton from ``start`` over the ``free`` globals (and every bias knot), with the
        gyro and accelerometer equations as ``use`` says, each window weighted by
        ``window_weights`` (0 leaves it out). The residual scales are re-estimated from the
        fit where ``estimate_scale``, else kept from ``start``. ``rotation_prior_std`` (rad)
        keeps a rotation that one equation alone leaves free defined."""
        options, t_prior, bound = self.options, self.prior.translation, self.options.translation_bound_m
        R, t, dtau, tilt, knots = start.R, start.t.copy(), start.dtau, start.tilt.copy(), start.knots.copy()
        intrinsics = start.intrinsics.copy()
        scale_g, scale_a = start.scale_g, start.scale_a
        n_bias = self.n_bias
        weights = np.ones(len(self.used)) if window_weights is None else window_weights
        samples = float(np.sum(weights * self.samples_per_window))
        free_idx = np.flatnonzero(free)
        cost_g = cost_a = np.zeros(len(self.used))
        S_inv = np.zeros((len(free_idx), len(free_idx)))
        unconstrained = t.copy()
        factor = X = None
        iterations = 0
        for iterations in range(1, (max_iterations or options.max_iterations) + 1):
            Hg, gg, cost_g, Ha, ga, cost_a = self._linearised(R, t, dtau, tilt, intrinsics, knots)
            if estimate_scale and iterations > 1:  # residual variance from the fit, above what the moments resolve
                scale_g = float(np.sqrt(max(np.dot(weights, cost_g) / (3 * samples), self.floor_g)))
                scale_a = float(np.sqrt(max(np.dot(weights, cost_a) / (3 * samples) + self.eiv_variance(t), self.floor_a)))
            wg = self.gain / scale_g**2 * use[0] * weights
            wa = self.gain / scale_a**2 * use[1] * weights
            # the normal equations: the globals' block, their coupling to the biases, the
            # biases' banded block (with the prior) and the gradient
            Hg, gg = wg[:, None, None] * Hg, wg[:, None] * gg
            Ha, ga = wa[:, None, None] * Ha, wa[:, None] * ga
            H_gg_all = np.zeros((N_GLOBAL, N_GLOBAL))
            H_gg_all[np.ix_(_GYRO_GLOBALS, _GYRO_GLOBALS)] += Hg[:, :_P_GYRO, :_P_GYRO].sum(axis=0)
            H_gg_all[np.ix_(_ACCEL_GLOBALS, _ACCEL_GLOBALS)] += Ha[:, :_P_ACCEL, :_P_ACCEL].sum(axis=0)
            H_gb_all = (
                np.bincount(self.cross_g, Hg[:, :_P_GYRO, _P_GYRO:].ravel(), N_GLOBAL * n_bias)
                + np.bincount(self.cross_a, Ha[:, :_P_ACCEL, _P_ACCEL:].ravel(), N_GLOBAL * n_bias)
            ).reshape(N_GLOBAL, n_bias)
            size = (_BAND + 1) * n_bias
            u6 = self.upper6
            H_bb = (
                np.bincount(self.band_g, Hg[:, _P_GYRO:, _P_GYRO:][:, u6[0], u6[1]].ravel(), size)
                + np.bincount(self.band_a, Ha[:, _P_ACCEL:, _P_ACCEL:][:, u6[0], u6[1]].ravel(), size)
            ).reshape(_BAND + 1, n_bias)
            H_bb += self.prior_band
            grad_g = np.zeros(N_GLOBAL)
            grad_g[_ACCEL_GLOBALS] -= ga[:, :_P_ACCEL].sum(axis=0)
            grad_g[_GYRO_GLOBALS] -= gg[:, :_P_GYRO].sum(axis=0)
            grad_b = -(np.bincount(self.biases_g.ravel(), gg[:, _P_GYRO:].ravel(), n_bias) + np.bincount(self.biases_a.ravel(), ga[:, _P_ACCEL:].ravel(), n_bias))
            grad_b -= _band_times(self.prior_band, knots.ravel())
            H_gg = H_gg_all[np.ix_(free_idx, free_idx)]
            H_gb = H_gb_all[free_idx]
            factor = (cholesky_banded(H_bb, lower=False), False)
            X = cho_solve_banded(factor, H_gb.T)
            S = H_gg - H_gb @ X
            s = grad_g[free_idx] - X.T @ grad_b
            if rotation_prior_std is not None:
                rotation = free_idx < 3
                S[rotation, rotation] += 1.0 / rotation_prior_std**2
            lower, upper = np.full(len(free_idx), -np.inf), np.full(len(free_idx), np.inf)
            for k, col in enumerate(free_idx):
                if 3 <= col < 6:
                    lower[k] = t_prior[col - 3] - bound - t[col - 3]
                    upper[k] = t_prior[col - 3] + bound - t[col - 3]
            L = np.linalg.cholesky(S)
            step_free, unbounded = _bounded_step(L, s, lower, upper)
            step = np.zeros(N_GLOBAL)
            step[free_idx] = step_free
            unconstrained = t.copy()
            for k, col in enumerate(free_idx):
                if 3 <= col < 6:
                    unconstrained[col - 3] += unbounded[k]
            step_bias = cho_solve_banded(factor, grad_b - H_gb.T @ step_free)
            R = R * Rotation.from_rotvec(step[:3])
            t = t + step[3:6]
            dtau = dtau + step[TAU]
            tilt = tilt + step[TILT]
            intrinsics = intrinsics + step[AXES]
            knots = knots + step_bias.reshape(self.n_knots, _KNOT)
            S_inv = np.linalg.inv(S)
            small = np.max(np.abs(step[:3])) < 1e-10 and np.max(np.abs(step[3:])) < 1e-8
            if small and (iterations > 2 or not estimate_scale):
                break

        covariance = np.zeros((N_GLOBAL, N_GLOBAL))
        covariance[np.ix_(free_idx, free_idx)] = S_inv
        bias_std = None
        if factor is not None and X is not None:
            last = self.n_knots - 1
            cols_last = [_KNOT * last + a for a in range(_KNOT)]
            E = np.zeros((n_bias, _KNOT))
            E[cols_last, np.arange(_KNOT)] = 1.0
            Y = cho_solve_banded(factor, E)
            XtE = X.T @ E
            block = Y[cols_last] + XtE.T @ S_inv @ XtE
            bias_std = np.sqrt(np.clip(np.diag(block), 0.0, None))
        return _Fit(R, t, dtau, tilt, knots, free.copy(), scale_g, scale_a, covariance, unconstrained, cost_g, cost_a, bias_std, iterations, intrinsics)


# --------------------------------------------------------------------------- checks and covariance

#: Delete-a-group jackknife: at most this many groups of consecutive windows.
JACKKNIFE_GROUPS = 10
#: Gauss-Newton steps of a replicate, from the full fit (the one-step jackknife): a tenth of
#: the windows left out moves the optimum little, and one step from the full fit lands within
#: second order of it. Replicates converged to 1e-10 rad took 10 steps each and three
#: quarters of the solve's time.
JACKKNIFE_ITERATIONS = 1
#: Residual std over the noise the data imply, above which the model does not explain the data.
RESIDUAL_LEVEL_MAX = 2.0
#: What the grid's interpolation and filtering leave of a signal, relative to its RMS about each
#: window's mean: a residual level counts only above it. (Noise-free drives leave 1e-4 of the
#: gyro's and 3e-4 of the accelerometer's.)
PIPELINE_FLOOR = 1e-3
#: A triad's axis errors are estimated where the drive determines them this well (1% of scale,
#: 0.6 deg of non-orthogonality).
INTRINSICS_MAX_STD = 0.01
#: The gyro's g-sensitivity likewise (rad/s per m/s^2): 0.1 deg/s per g, a MEMS part's.
G_SENSITIVITY_MAX_STD = np.radians(0.1) / GRAVITY_MPS2
#: What the checks take as numerically zero (rad, and rad per m/s^2): on noise-free data the
#: Fisher std is round-off, and so is any difference the checks see.
NUMERICAL_ZERO = 1e-6


def _chi2_limit(dof: int, alpha: float) -> float:
    """The chi-square quantile a false alarm rate ``alpha`` allows (``chi2.ppf(1 - alpha)``,
    from ``scipy.special``: ``scipy.stats`` takes 0.8 s to import)."""
    from scipy.special import chdtri

    return float(chdtri(dof, alpha))


def _rotation_difference(a: Rotation, b: Rotation) -> np.ndarray:
    """Rotation vector of ``a b^-1`` (about the base axes)."""
    return (a * b.inv()).as_rotvec()


def _jackknife(problem: _Problem, fit: _Fit) -> np.ndarray | None:
    """Delete-a-group jackknife covariance (7x7: rotation about the base axes, t, tau) of the
    fit's free globals over groups of consecutive windows, or None with fewer than 3 windows.
    It sees what the Fisher information cannot: residuals correlated over seconds, and errors
    that differ from window to window."""
    K = len(problem.used)
    if K < 3:
        return None
    groups = np.array_split(np.arange(K), min(K, JACKKNIFE_GROUPS))
    replicates = []
    for group in groups:
        weights = np.ones(K)
        weights[group] = 0.0
        rep = problem.fit(fit, fit.free, window_weights=weights, max_iterations=JACKKNIFE_ITERATIONS)
        replicates.append(np.concatenate([_rotation_difference(rep.R, fit.R), rep.t - fit.t, [rep.dtau - fit.dtau]]))
    reps = np.array(replicates)
    G = len(reps)
    centred = reps - reps.mean(axis=0)
    return (G - 1) / G * centred.T @ centred


#: The sensor's own errors, in groups each tested apart: (name, globals, std to be estimated).
OWN_ERRORS = (("accelerometer", INTRINSICS, INTRINSICS_MAX_STD), ("gyro", GYRO_INTRINSICS, INTRINSICS_MAX_STD), ("g-sensitivity", G_SENSITIVITY, G_SENSITIVITY_MAX_STD))


def _own_errors(problem: _Problem, fit: _Fit, alpha: float) -> tuple[_Fit, dict[str, dict[str, Any]]]:
    """The sensor's own errors (:data:`OWN_ERRORS`) from one joint fit: the components the
    drive determines to their group's std, a group kept where a chi-square test at ``alpha``
    finds it. Returns the fit (with the groups kept) and per group ``estimated`` and, where any
    component was determined, ``chi2``, ``dof``, ``value`` and ``std`` (NaN: not determined)."""
    free = fit.free.copy()
    free[AXES] = True
    joint = problem.fit(fit, free)
    std = joint.std()
    shown = np.zeros(N_GLOBAL, dtype=bool)
    for _, which, max_std in OWN_ERRORS:
        shown[which] = std[which] <= max_std
    if not shown.any():
        return fit, {name: {"estimated": False} for name, _, _ in OWN_ERRORS}
    free[AXES] = shown[AXES]
    joint = problem.fit(replace(joint, intrinsics=np.where(shown[AXES], joint.intrinsics, 0.0)), free)
    found: dict[str, dict[str, Any]] = {}
    kept = fit.free.copy()
    for name, which, _ in OWN_ERRORS:
        group = shown[which]
        if not group.any():
            found[name] = {"estimated": False}
            continue
        own = slice(which.start - AXES.start, which.stop - AXES.start)  # in _Fit.intrinsics
        E, cov = joint.intrinsics[own][group], joint.covariance[which, which][np.ix_(group, group)]
        chi2 = float(E @ np.linalg.solve(cov + NUMERICAL_ZERO**2 * np.eye(len(E)), E))
        present = chi2 > _chi2_limit(len(E), alpha)
        found[name] = {"estimated": bool(present), "chi2": chi2, "dof": len(E), "value": joint.intrinsics[own].copy(), "std": np.where(group, joint.std()[which], np.nan)}
        kept[which] = group & present
    if not kept[AXES].any():
        return fit, found
    if np.array_equal(kept, free):
        return joint, found
    return problem.fit(replace(joint, intrinsics=np.where(kept[AXES], joint.intrinsics, 0.0)), kept), found


def _axes_document(found: dict[str, Any]) -> dict[str, Any]:
    """A triad's axis errors as the calibrate document gives them."""
    if "value" not in found:
        return found
    value, std = found["value"], found["std"]
    return {
        "estimated": found["estimated"], "chi2": found["chi2"], "dof": found["dof"],
        "scale": value[:3].tolist(), "nonorthogonality_deg": np.degrees(value[3:]).tolist(),
        "scale_std": std[:3].tolist(), "nonorthogonality_std_deg": np.degrees(std[3:]).tolist(),
    }


def _g_sensitivity_document(found: dict[str, Any]) -> dict[str, Any]:
    """The gyro's g-sensitivity ``G`` (:data:`G_SENSITIVITY`, the IMU's axes) in deg/s per g."""
    if "value" not in found:
        return found
    per_g = np.degrees(1.0) * GRAVITY_MPS2
    return {
        "estimated": found["estimated"], "chi2": found["chi2"], "dof": found["dof"],
        "dps_per_g": (per_g * found["value"]).reshape(3, 3).tolist(), "std_dps_per_g": (per_g * found["std"]).reshape(3, 3).tolist(),
    }


@dataclass(frozen=True)
class Check:
    """One model-consistency test of the estimate (SPEC ``checks``)."""

    name: str
    passed: bool
    figures: dict[str, Any]
    #: Variance inflation the failed check calls for (1 where it passed).
    inflation: float = 1.0


def solve(
    windows: list[WindowMoments],
    prior: Transform,
    options: CalibrationOptions,
    tau0: float,
    sigma: tuple[float, float],
    lowpass: Lowpass,
    time_offset_shown: bool = True,
    time_offset_reason: str = "",
    dw_noise_var: float = 0.0,
) -> SensorEstimate:
    """The estimate from the selected windows' moments, with its checks and honest covariance.

    1. The joint Gauss-Newton fit (module docstring); translation axes the drive does not
       determine are kept at the prior; a clock offset whose std exceeds
       :data:`TIME_OFFSET_MAX_STD_S` (or that ``time_offset_shown`` says the correlation could
       not place) is not estimated. Each triad's axis errors (scale factors, non-orthogonality)
       and the gyro's g-sensitivity join the model where the drive determines them and a
       chi-square test finds them (:func:`_own_errors`).
    2. Checks (each a test at ``options.consistency_alpha``): the rotation from the gyro alone
       against the rotation from the accelerometer alone (chi-square, 3 dof); the mount's tilt
       with the vehicle's specific force (chi-square, 2 dof; failing, the tilt is estimated
       with everything else and the rotation is the mount's at rest); the residual levels
       against the noise the data imply.
    3. The covariance: the Fisher information's, each axis inflated to the delete-a-group
       jackknife's spread where that is larger, then by the failed checks, then the box's
       and the config's systematic floors added.
    """
    problem = _Problem(windows, prior, options, sigma, lowpass, dw_noise_var)
    bound = options.translation_bound_m
    warnings: list[str] = []
    start = problem.start()
    start.free[TAU] = options.max_time_offset_s > 0 and time_offset_shown
    start.free[3:6] = problem.translation_information_diagonal() > 0  # above the noise floor
    try:
        fit = problem.fit(start, start.free, estimate_scale=True)
    except np.linalg.LinAlgError:  # the lever arm's information, noise taken off, is not positive
        start.free[3:6] = False
        fit = problem.fit(start, start.free, estimate_scale=True)
    weak = fit.free[3:6] & (fit.std()[3:6] >= OBSERVABLE_FRACTION_OF_BOUND * bound)
    if weak.any():  # kept at the prior: the drive does not determine them
        free = fit.free.copy()
        free[3:6] &= ~weak
        fit = problem.fit(replace(fit, t=np.where(weak, prior.translation, fit.t)), free)
    checks: list[Check] = []
    alpha = options.consistency_alpha
    # the sensor's own errors, where the drive determines them and they are there (estimated
    # always, they would cost clean drives a good part of their lever-arm std): each triad's
    # axis errors, the gyro's g-sensitivity
    fit, own = _own_errors(problem, fit, options.consistency_alpha)
    for name, found in own.items():
        if found["estimated"]:
            value = found["value"]
            if name == "g-sensitivity":
                detail = f"largest {np.degrees(np.max(np.abs(value))) * GRAVITY_MPS2:.3f} deg/s per g"
            else:
                detail = ("scale " + ", ".join(f"{100 * v:+.2f}%" for v in value[:3])
                          + "; non-orthogonality " + ", ".join(f"{v:+.3f}" for v in np.degrees(value[3:])) + " deg")
            what = "gyro g-sensitivity" if name == "g-sensitivity" else f"{name} axis errors"
            warnings.append(f"{what} estimated with the extrinsics: {detail} (chi2 {found['chi2']:.0f}, {found['dof']} dof)")
    # the mount's tilt with the vehicle's specific force, the axis errors found in the model (an
    # accelerometer's scale factors look like a tilt where they are not)
    with_tilt = fit.free.copy()
    with_tilt[TILT] = True
    tilted = problem.fit(fit, with_tilt)
    k, cov_k = tilted.tilt, tilted.covariance[TILT, TILT]
    chi2_tilt = float(k @ np.linalg.solve(cov_k + NUMERICAL_ZERO**2 * np.eye(2), k))
    rigid = chi2_tilt <= _chi2_limit(2, alpha)
    # (failing, the tilt joins the model: the estimate is then the tilting mount's, and the
    # std needs no inflation for it; the gyro's share of the tilt stays unmodelled, which the
    # rotation check below sees)
    checks.append(Check("rigid_mount", rigid, {
        "tilt_deg_per_mps2": np.degrees(k).tolist(), "std": np.degrees(np.sqrt(np.diag(cov_k))).tolist(),
        "chi2": chi2_tilt, "dof": 2,
    }))
    if not rigid:
        warnings.append(
            f"the mount is not rigid: it tilts {np.degrees(k[0]):.3f} deg (roll) and {np.degrees(k[1]):.3f} deg (pitch) "
            f"per m/s^2 of the vehicle's lateral and longitudinal specific force (chi2 {chi2_tilt:.1f}, 2 dof); "
            "the rotation given is the mount's at rest"
        )
        fit = tilted
    time_offset_observable = options.max_time_offset_s <= 0 or time_offset_shown
    if not time_offset_shown and options.max_time_offset_s > 0:
        warnings.append(f"clock offset not observable ({time_offset_reason or 'the drive does not show it'}): not estimated, kept at 0")
    elif fit.free[TAU] and fit.std()[TAU] > TIME_OFFSET_MAX_STD_S:
        warnings.append(
            f"clock offset not observable: std {fit.std()[TAU] * 1e3:.1f} ms > {TIME_OFFSET_MAX_STD_S * 1e3:g} ms; "
            f"kept at the correlation's {tau0 * 1e3:.1f} ms"
        )
        time_offset_observable = False
        free = fit.free.copy()
        free[TAU] = False
        fit = problem.fit(replace(fit, dtau=0.0), free)

    # the rotation from the gyro alone against the one from the accelerometer alone
    rotation_only = np.zeros(N_GLOBAL, dtype=bool)
    rotation_only[:3] = True
    # (one linear step each from the joint solution: a direction one equation alone leaves
    # free stays put, with its large covariance, instead of wandering off)
    by_gyro = problem.fit(fit, rotation_only, use=(True, False), max_iterations=1, rotation_prior_std=1.0)
    accel_only = np.zeros(N_GLOBAL, dtype=bool)  # the free globals the accelerometer holds, but tau
    accel_only[_ACCEL_GLOBALS] = fit.free[_ACCEL_GLOBALS]
    accel_only[TAU] = False
    by_accel = problem.fit(fit, accel_only, use=(False, True), max_iterations=1, rotation_prior_std=1.0)
    delta = _rotation_difference(by_accel.R, by_gyro.R)
    cov_delta = by_gyro.rotation_covariance_base() + by_accel.rotation_covariance_base() + NUMERICAL_ZERO**2 * np.eye(3)
    chi2_rot = float(delta @ np.linalg.solve(cov_delta, delta))
    agree = chi2_rot <= _chi2_limit(3, alpha)
    checks.append(Check("gyro_vs_accel_rotation", agree, {"chi2": chi2_rot, "dof": 3, "difference_deg": float(np.degrees(np.linalg.norm(delta)))}, max(1.0, chi2_rot / 3)))
    if not agree:
        warnings.append(
            f"the gyro and the accelerometer disagree on the rotation by {np.degrees(np.linalg.norm(delta)):.3f} deg "
            f"(chi2 {chi2_rot:.1f}, 3 dof): their axes are misaligned differently, or the mount moves"
        )
    # the residual levels against the noise the data imply
    expected = np.hypot(np.array(sigma) * np.sqrt(problem.gain), PIPELINE_FLOOR * np.array(problem.signal_rms))
    levels = np.array([fit.scale_g, np.sqrt(max(fit.scale_a**2 - problem.eiv_variance(fit.t), 0.0))]) / expected
    level_ok = bool(np.all(levels <= RESIDUAL_LEVEL_MAX))
    checks.append(Check("residual_level", level_ok, {"gyro": float(levels[0]), "accel": float(levels[1])}, float(max(1.0, np.max(levels) ** 2))))
    if not level_ok:
        warnings.append(
            f"residuals {levels[0]:.1f}x (gyro) and {levels[1]:.1f}x (accelerometer) the noise the data imply: "
            "the model does not explain the data (units, a moving mount, a time-varying offset?)"
        )

    # the covariance: Fisher, inflated per axis to the jackknife's spread, then by failed checks
    Rm = fit.R.as_matrix()
    to_base = np.eye(7)
    to_base[:3, :3] = Rm
    free7 = fit.free[:7]
    fisher = to_base @ fit.covariance[:7, :7] @ to_base.T
    fisher_std = np.sqrt(np.clip(np.diag(fisher), 0.0, None))
    jackknife = _jackknife(problem, fit)
    inflation = np.ones(7)
    if jackknife is None:
        warnings.append(f"only {len(problem.used)} window(s) with enough motion: too few to check the std against the data's spread")
    else:
        jk_std = np.sqrt(np.clip(np.diag(jackknife), 0.0, None))
        inflation[free7] = np.maximum(1.0, jk_std[free7] / np.where(fisher_std[free7] > 0, fisher_std[free7], np.inf))
    cov7 = inflation[:, None] * fisher * inflation[None, :]
    failed = [c for c in checks if not c.passed]
    if failed:
        cov7 *= max(c.inflation for c in failed)
    # translation axes on the box: the std covers the distance to where the data pull them
    on_box = fit.free[3:6] & (np.abs(fit.t - prior.translation) >= bound * (1.0 - 1e-6))
    for axis in np.flatnonzero(on_box).tolist():
        pull = fit.unconstrained_t[axis] - fit.t[axis]
        cov7[3 + axis, 3 + axis] += pull**2
        warnings.append(
            f"translation {'xyz'[axis]} rests on its box (prior {prior.translation[axis]:+.3f} +- {bound:g} m): "
            f"the data pull it {abs(pull):.3f} m further; the prior may be wrong"
        )
    for axis in range(3):
        if not fit.free[3 + axis]:
            cov7[3 + axis, 3 + axis] = bound**2 / 3.0
    cov6 = cov7[:6, :6].copy()
    cov6[:3, :3] += np.radians(options.rotation_floor_deg) ** 2 * np.eye(3)
    cov6[3:, 3:] += options.translation_floor_m**2 * np.eye(3)
    observable = fit.free[3:6].copy()
    if not observable.all():
        warnings.append("translation " + ", ".join("xyz"[a] for a in np.flatnonzero(~observable)) + " not determined by the drive: kept at the prior")

    if failed:
        status = "inconsistent"
    elif not observable.all() or on_box.any() or not time_offset_observable or jackknife is None:
        status = "partial"
    else:
        status = "ok"
    last = problem.n_knots - 1
    n_total = 3 * problem.samples
    bias_std = fit.bias_std
    return SensorEstimate(
        status=status,
        T_base_imu=Transform(fit.R, fit.t),
        covariance=cov6,
        translation_observable=observable,
        time_offset_s=float(tau0 + fit.dtau) if time_offset_shown else 0.0,
        time_offset_std_s=float(np.sqrt(cov7[6, 6])) if fit.free[TAU] else None,
        gyro_bias=fit.knots[last, 0:3].copy(),
        gyro_bias_std=bias_std[0:3] if bias_std is not None else None,
        accel_bias=fit.knots[last, 3:6].copy(),
        accel_bias_std=bias_std[3:6] if bias_std is not None else None,
        bias_knots_s=np.arange(problem.n_knots) * options.window_s,
        gyro_bias_knots=fit.knots[:, 0:3].copy(),
        accel_bias_knots=fit.knots[:, 3:6].copy(),
        windows=[w.info for w in windows if w.info is not None],
        residual_rms_gyro=float(np.sqrt(max(fit.cost_g.sum(), 0.0) / n_total)),
        residual_rms_accel=float(np.sqrt(max(fit.cost_a.sum(), 0.0) / n_total)),
        iterations=fit.iterations,
        noise_std={"gyro_radps": sigma[0], "accel_mps2": sigma[1]},
        warnings=warnings,
        checks={c.name: {**c.figures, "pass": c.passed} for c in checks},
        time_offset_observable=time_offset_observable,
        tilt_rad_per_mps2=fit.tilt.copy(),
        accel_intrinsics=_axes_document(own["accelerometer"]),
        gyro_intrinsics={**_axes_document(own["gyro"]), "g_sensitivity": _g_sensitivity_document(own["g-sensitivity"])},
        window_residuals=np.column_stack([
            [w.start_s for w in problem.used],
            np.sqrt(np.maximum(fit.cost_g, 0.0) / (3 * problem.samples_per_window)),
            np.sqrt(np.maximum(fit.cost_a, 0.0) / (3 * problem.samples_per_window)),
        ]),
    )
