"""The measurement model of one sensor IMU against the base IMU, stated once (paper eqs. 10-12).

With ``R = R_base_imu``, ``t = t_base_imu`` (the lever arm), the clock offset ``tau = tau0 +
dtau`` (stamp of the sensor minus stamp of the base; ``tau0`` from the boot's correlation),
both triads resampled onto the base's grid at ``t + tau0`` and low-passed alike:

- gyro (eq. 10)::

      w_I = (I + E_g) R^T N_B^-1 (w_B - dtau dw_B) + G f_I + b_g(t)

- accelerometer (eqs. 11-12)::

      f_I = (I + E_a) (I - [phi]x) R^T ((I + D_B)^-1 (f_B - dtau df_B)
            + (A - dtau dA) t + f_B x theta) + b_a(t)

  with ``A = [w]x^2 + [dw]x`` (centripetal and Euler terms) and ``dA`` its derivative, both
  of the base's rates ``w = N_B^-1 w_B``: linear maps of the readings' ``vec A`` and
  ``vec dA`` (:func:`vec_gain`). The readings there are the base gyro's less its bias where
  the vehicle's stops show it (:func:`.biases.rest_rate`); in the gyro's equation the
  relative bias ``b_g`` takes the base's.

The sensor's own errors: ``E_a``, ``E_g`` each triad's axis errors (symmetric: scale factors
on the diagonal, non-orthogonality off it, :data:`SYMMETRIC`), ``G`` the gyro's g-sensitivity
(rad/s per m/s^2, acting on the sensor's own specific force), ``phi`` the accelerometer
triad's misalignment to the gyro triad (``R`` is the gyro triad's), ``theta = (k_roll f_y,
k_pitch f_x, 0)`` a mount that tilts with the vehicle's specific force (base axes), ``b_g``,
``b_a`` the relative biases, piecewise linear in time with a knot every window. The base IMU's
own errors that the sensor's relative ones cannot absorb: its gyro's axes ``N_B = (1 + s_B) I
+ E_B``, a common scale error ``s_B`` (a gyro that reads low, beyond any grade) and the axis
errors ``E_B`` its grade declares (in the gyro's equation the sensor gyro's ``E_g`` takes both;
in the lever arm's terms they act unlike the sensor's specific force), and ``D_B`` its
accelerometer's axis errors (they scale ``f_B`` and not the lever arm's term). The estimator
estimates the errors a drive determines and carries the rest, with each IMU grade's prior
(:mod:`imucal_cli.core.grades`), into the reported std.

Every residual is linear in a data vector ``x``, ``r = C(p) x``:

- ``x_g`` (:data:`GYRO_DATA`) = ``[w_I, f_I, w_B, dw_B, 1, u]``
- ``x_a`` (:data:`ACCEL_DATA`) = ``[f_I, f_B, df_B, vec A, vec dA, q, 1, u]``

(``u`` the time within the window, 0..1; ``q`` the products of ``f_B`` a tilting mount adds),
so a window's cost ``tr(C S C^T)`` and its Gauss-Newton derivatives are exact functions of its
moments ``S = sum x x^T``. This module owns the layout of the parameters (:data:`PARAMETERS`)
and of both data vectors by name, the coefficients ``C``, and their derivatives; adding an error
term is a block in :data:`PARAMETERS`, its columns here, and its case in
``tests/core/test_model.py``, which checks every derivative against finite differences.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from imucal_cli.core.so3 import skew
from imucal_cli.types import rotation_type

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation


class Layout:
    """Named consecutive blocks of a vector: ``layout["name"]`` is the block's slice."""

    def __init__(self, *blocks: tuple[str, int]) -> None:
        self.slices: dict[str, slice] = {}
        start = 0
        for name, size in blocks:
            self.slices[name] = slice(start, start + size)
            start += size
        self.size = start

    def __getitem__(self, name: str) -> slice:
        return self.slices[name]

    def index(self, name: str) -> int:
        """The position of a one-entry block."""
        block = self.slices[name]
        assert block.stop - block.start == 1, name
        return block.start

    def indices(self, *names: str) -> np.ndarray:
        """The positions of several blocks, in the order named."""
        return np.concatenate([np.arange(self.slices[n].start, self.slices[n].stop) for n in names])

    def mask(self, *names: str) -> np.ndarray:
        """A boolean mask over the vector, True on the blocks named (as symforce's
        ``optimized_keys``)."""
        out = np.zeros(self.size, dtype=bool)
        for name in names:
            out[self.slices[name]] = True
        return out

    def without(self, *names: str) -> Layout:
        """The layout of the other blocks, in order, packed from 0."""
        return Layout(*((n, s.stop - s.start) for n, s in self.slices.items() if n not in names))

    def shifted(self, name: str, offset: int) -> slice:
        """The block's slice ``offset`` entries further on (the layout inside a larger one)."""
        block = self.slices[name]
        return slice(block.start + offset, block.stop + offset)


#: The estimate's global unknowns. ``rotation``: a step right-multiplied onto ``R_base_imu``
#: (IMU axes); ``tilt``: roll per lateral and pitch per longitudinal specific force (rad per
#: m/s^2); ``accel_axes`` and ``gyro_axes``: each triad's ``E`` by :data:`SYMMETRIC`;
#: ``g_sensitivity``: ``G`` row-major (the IMU's axes); ``accel_rotation``: ``phi``;
#: ``base_gyro_scale``: ``s_B``; ``base_gyro_axes``: ``E_B`` and ``base_accel_axes``: ``D_B``,
#: each by :data:`SYMMETRIC`.
PARAMETERS = Layout(
    ("rotation", 3),
    ("translation", 3),
    ("time_offset", 1),
    ("tilt", 2),
    ("accel_axes", 6),
    ("gyro_axes", 6),
    ("g_sensitivity", 9),
    ("accel_rotation", 3),
    ("base_gyro_scale", 1),
    ("base_gyro_axes", 6),
    ("base_accel_axes", 6),
)
N_PARAMETERS = PARAMETERS.size
ROTATION, TRANSLATION, TILT = PARAMETERS["rotation"], PARAMETERS["translation"], PARAMETERS["tilt"]
TIME_OFFSET = PARAMETERS.index("time_offset")
ACCEL_AXES, GYRO_AXES = PARAMETERS["accel_axes"], PARAMETERS["gyro_axes"]
G_SENSITIVITY = PARAMETERS["g_sensitivity"]
ACCEL_ROTATION, BASE_GYRO_SCALE = PARAMETERS["accel_rotation"], PARAMETERS["base_gyro_scale"]
BASE_GYRO_AXES = PARAMETERS["base_gyro_axes"]
BASE_ACCEL_AXES = PARAMETERS["base_accel_axes"]
#: Both IMUs' own errors, as :attr:`Point.errors` holds them.
SENSOR_ERRORS = slice(ACCEL_AXES.start, BASE_ACCEL_AXES.stop)
#: What the fit starts with free: the extrinsics and the clock.
START_FREE = PARAMETERS.mask("rotation", "translation", "time_offset")
#: The extrinsics and the clock: what the jackknife and the reported covariance cover.
EXTRINSICS = slice(ROTATION.start, TIME_OFFSET + 1)
#: The globals each equation holds, in the order of its derivatives' columns.
GYRO_GLOBALS = PARAMETERS.indices(
    "rotation", "time_offset", "gyro_axes", "g_sensitivity", "base_gyro_scale", "base_gyro_axes"
)
ACCEL_GLOBALS = PARAMETERS.indices(
    "rotation",
    "translation",
    "time_offset",
    "tilt",
    "accel_axes",
    "accel_rotation",
    "base_gyro_scale",
    "base_gyro_axes",
    "base_accel_axes",
)

GYRO_DATA = Layout(("w_I", 3), ("f_I", 3), ("w_B", 3), ("dw_B", 3), ("one", 1), ("u", 1))
ACCEL_DATA = Layout(
    ("f_I", 3),
    ("f_B", 3),
    ("df_B", 3),
    ("vec_A", 9),
    ("vec_dA", 9),
    ("tilt_terms", 4),
    ("one", 1),
    ("u", 1),
)
#: The base's part of each data vector, shared by every sensor.
GYRO_BASE, ACCEL_BASE = GYRO_DATA.without("w_I", "f_I"), ACCEL_DATA.without("f_I")
#: The sensor's own leading entries of each data vector.
GYRO_OWN = GYRO_DATA.size - GYRO_BASE.size
ACCEL_OWN = ACCEL_DATA.size - ACCEL_BASE.size

#: Bias unknowns per knot.
KNOT = Layout(("gyro_bias", 3), ("accel_bias", 3))

#: Random walk of the accelerometer bias allowed between knots (m/s^2/sqrt(s)): loose, a few
#: times what MEMS parts drift, so the data decide.
ACCEL_BIAS_WALK = 0.01
#: Prior standard deviation of the accelerometer bias (m/s^2): keeps knots without data defined.
ACCEL_BIAS_PRIOR_STD = 1.0


@dataclass(frozen=True)
class BiasModel:
    """How the relative biases (sensor minus base) may drift between knots (a random walk per
    component) and how large they may be where the walk starts (an absolute prior at the first
    knot: the Kalman filter's ``P0``, eqs. 7-9). One prior for the walk, not one a knot: a prior
    at every knot would hold the biases' mean over the log ever tighter as knots add up, and
    an error that reads as a constant bias (the gyro's g-sensitivity along gravity) would take
    up the mean instead."""

    spacing_s: float  # seconds between neighbouring knots: a window
    walks: tuple[float, float]  # gyro (rad/s/sqrt(s)), accelerometer (m/s^2/sqrt(s))
    prior_stds: tuple[float, float]  # gyro (rad/s), accelerometer (m/s^2)

    def walk_information(self, kind: int, gaps_s: np.ndarray | float) -> np.ndarray:
        """The information of the walk of a bias component (``kind`` 0: gyro, 1: accelerometer)
        between knots ``gaps_s`` apart: the inverse of its variance there."""
        return 1.0 / (self.walks[kind] ** 2 * np.asarray(gaps_s, dtype=float))

    def prior_information(self, kind: int) -> float:
        """The information of a bias component's absolute prior at the walk's first knot."""
        return 1.0 / self.prior_stds[kind] ** 2


#: A triad's six axis errors (a block of :data:`PARAMETERS`), in :data:`SYMMETRIC`'s order.
AXIS_ERRORS = Layout(("scale", 3), ("nonorthogonality", 3))
SYMMETRIC = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
    SYMMETRIC[_k, _i, _j] = SYMMETRIC[_k, _j, _i] = 1.0

#: ``vec([n]x) = VEC_SKEW n`` (column-major vec): how the angular acceleration's noise enters
#: the ``vec A`` columns of x_a.
VEC_SKEW = np.zeros((9, 3))
for _column, _row, _component, _sign in (
    (0, 1, 2, 1),
    (0, 2, 1, -1),
    (1, 0, 2, -1),
    (1, 2, 0, 1),
    (2, 0, 1, 1),
    (2, 1, 0, -1),
):
    VEC_SKEW[3 * _column + _row, _component] = _sign


@dataclass
class Point:
    """Where the model is evaluated: the extrinsics, the clock, the tilt, the sensor's errors."""

    R: Rotation  # R_base_imu
    t: np.ndarray  # t_base_imu (3,)
    dtau: float  # the clock offset beyond the boot's
    tilt: np.ndarray = field(default_factory=lambda: np.zeros(2))
    errors: np.ndarray = field(
        default_factory=lambda: np.zeros(SENSOR_ERRORS.stop - SENSOR_ERRORS.start)
    )

    def own(self, block: slice) -> np.ndarray:
        """One block of the sensor's errors (:data:`ACCEL_AXES`, ...)."""
        return self.errors[block.start - SENSOR_ERRORS.start : block.stop - SENSOR_ERRORS.start]

    def moved(self, step: np.ndarray) -> Point:
        """The point after a step of the globals (:data:`PARAMETERS`)."""
        return Point(
            self.R * rotation_type().from_rotvec(step[ROTATION]),
            self.t + step[TRANSLATION],
            self.dtau + step[TIME_OFFSET],
            self.tilt + step[TILT],
            self.errors + step[SENSOR_ERRORS],
        )

    def key(self) -> bytes:
        """Equal for equal points (a cache key)."""
        parts = (self.R.as_quat(), self.t, self.dtau, self.tilt, self.errors)
        return b"".join(np.asarray(v, dtype=np.float64).tobytes() for v in parts)


def triad_axes(errors: np.ndarray) -> np.ndarray:
    """``I + E``: a triad's axes from its six axis errors."""
    return np.eye(3) + np.tensordot(errors, SYMMETRIC, axes=1)


def _accel_axes(point: Point) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's ``(I + E_a)`` and ``(I + E_a)(I - [phi]x)``: what stands left of
    ``R^T`` in its equation."""
    axes = triad_axes(point.own(ACCEL_AXES))
    return axes, axes @ (np.eye(3) - skew(point.own(ACCEL_ROTATION)))


def _base_gyro_axes(point: Point) -> np.ndarray:
    """``N_B = (1 + s_B) I + E_B``: the base gyro's rates to its readings."""
    return triad_axes(point.own(BASE_GYRO_AXES)) + point.own(BASE_GYRO_SCALE)[0] * np.eye(3)


def _base_gyro_inverse(point: Point) -> np.ndarray:
    """``N_B^-1``: the base gyro's readings to rates."""
    return np.linalg.inv(_base_gyro_axes(point))


#: The base gyro's own errors (``s_B``, then ``E_B``'s six) and the steps of ``N_B`` each makes.
BASE_GYRO = PARAMETERS.indices("base_gyro_scale", "base_gyro_axes")
_BASE_GYRO_STEPS = np.concatenate([np.eye(3)[None], SYMMETRIC])


#: The column-major vecs of the nine unit 3x3 matrices, (9, 3, 3): ``_UNITS[k]`` is 1 at
#: ``vec`` entry ``k``; their symmetric and skew parts, and ``w w^T`` of each symmetric part
#: read as ``[w]x^2`` (:func:`_gain_of`).
_UNITS = np.eye(9).reshape(9, 3, 3).transpose(0, 2, 1)
_SYMMETRIC_UNITS = (_UNITS + _UNITS.transpose(0, 2, 1)) / 2
_SKEW_UNITS = _UNITS - _SYMMETRIC_UNITS
_HALF_TRACES = np.trace(_SYMMETRIC_UNITS, axis1=1, axis2=2)[:, None, None] / 2
_OUTER_UNITS = _SYMMETRIC_UNITS - _HALF_TRACES * np.eye(3)


def _gain_of(N: np.ndarray, along: np.ndarray | None = None) -> np.ndarray:
    """The map (9x9 on column-major vecs) from ``X = [w]x^2 + [dw]x`` of the readings to the same
    of the rates ``M w``, ``M = N^-1`` (``N`` symmetric), or its derivatives along ``N``'s steps
    ``along`` (n, 3, 3): (n, 9, 9).

    Symmetric part ``S = [w]x^2 = w w^T - |w|^2 I``: ``w w^T = S - tr(S) / 2 I``, so the rates'
    is ``Q - tr(Q) I`` with ``Q = M (S - tr(S) / 2 I) M``. Skew part ``K = [dw]x``: ``[M dw]x =
    det(M) M^-T K M^-1 = N K N / det(N)``. Both linear in ``X``, and alike for ``dA`` (its
    symmetric part is the derivative of ``[w]x^2``, its skew part ``[ddw]x``)."""
    M, det = np.linalg.inv(N), np.linalg.det(N)
    P, K = _OUTER_UNITS, _SKEW_UNITS
    if along is None:
        Q = M @ P @ M
        skew_part = N @ K @ N / det
    else:
        steps = (-M @ along @ M)[:, None]  # d M, (n, 1, 3, 3) against the units' (9, 3, 3)
        Q = steps @ P @ M + M @ P @ steps
        turned = N @ K @ N / det
        along = along[:, None]
        skew_part = (along @ K @ N + N @ K @ along) / det
        skew_part -= turned * np.trace(M @ along, axis1=-2, axis2=-1)[..., None, None]
    out = Q - np.trace(Q, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) + skew_part
    # column k: the image of unit k, as its column-major vec
    return np.swapaxes(np.swapaxes(out, -1, -2).reshape(*out.shape[:-3], 9, 9), -1, -2)


#: :func:`_gain_of` where the base gyro reads its rates exactly (its errors held at zero: every
#: fit but those that estimate them), and its derivatives there along :data:`_BASE_GYRO_STEPS`.
_GAIN_AT_IDENTITY = np.eye(9)
_GAIN_STEPS_AT_IDENTITY = _gain_of(np.eye(3), _BASE_GYRO_STEPS)


def _gains(N: np.ndarray, present: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_gain_of` at ``N`` and along the steps ``present`` (of :data:`_BASE_GYRO_STEPS`)."""
    if np.array_equal(N, np.eye(3)):
        return _GAIN_AT_IDENTITY, _GAIN_STEPS_AT_IDENTITY[present]
    return _gain_of(N), _gain_of(N, _BASE_GYRO_STEPS[present])


def vec_gain(point: Point) -> np.ndarray:
    """``vec A`` of the rates from ``vec A`` of the readings (9x9, :func:`_gain_of`)."""
    return _gains(_base_gyro_axes(point), [])[0]


def _base_accel_inverse(point: Point) -> np.ndarray:
    """``(I + D_B)^-1``: the base accelerometer's readings to specific force."""
    return np.linalg.inv(triad_axes(point.own(BASE_ACCEL_AXES)))


def kron_t(t: np.ndarray) -> np.ndarray:
    """``t^T (x) I3``: (3, 9) with ``A t = (t^T (x) I3) vec A``."""
    return np.hstack([t[0] * np.eye(3), t[1] * np.eye(3), t[2] * np.eye(3)])


def tilt_columns(Rt: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """Coefficients (3, 4) of the tilt terms ``q = [f_y f_z, f_y^2, f_x f_z, f_x^2]`` of x_a.

    A mount leaning by ``theta = (k_roll f_y, k_pitch f_x, 0)`` (base axes) turns the specific
    force it sees into ``R^T exp(-[theta]x) f ~ R^T (f + f x theta)``, and
    ``f x theta = k_roll (0, q1, -q2) + k_pitch (-q3, 0, q4)``."""
    k_roll, k_pitch = tilt
    return np.stack(
        [-k_roll * Rt[:, 1], k_roll * Rt[:, 2], k_pitch * Rt[:, 0], -k_pitch * Rt[:, 2]], axis=-1
    )


def _bias_columns(C: np.ndarray, layout: Layout, bj: np.ndarray, bk: np.ndarray) -> None:
    """The bias, linear between the window's knots ``bj`` and ``bk`` (K, 3): on ``1`` and ``u``."""
    C[:, :, layout.index("one")] = -bj
    C[:, :, layout.index("u")] = -(bk - bj)


def gyro_coefficients(point: Point, bj: np.ndarray, bk: np.ndarray) -> np.ndarray:
    """``C`` of ``r_g = C x_g`` per window, (K, 3, 14), the gyro biases at the window's knots
    (a window's clock beyond the point's is in its moments: :func:`~.moments.shifted`)."""
    D = GYRO_DATA
    Rt = triad_axes(point.own(GYRO_AXES)) @ point.R.inv().as_matrix() @ _base_gyro_inverse(point)
    C = np.zeros((len(bj), 3, D.size))
    C[:, :, D["w_I"]] = np.eye(3)
    C[:, :, D["f_I"]] = -point.own(G_SENSITIVITY).reshape(3, 3)
    C[:, :, D["w_B"]] = -Rt
    C[:, :, D["dw_B"]] = point.dtau * Rt
    _bias_columns(C, D, bj, bk)
    return C


def accel_coefficients(point: Point, aj: np.ndarray, ak: np.ndarray) -> np.ndarray:
    """``C`` of ``r_a = C x_a`` per window, (K, 3, 33), the accelerometer biases at the
    knots."""
    D = ACCEL_DATA
    Rt = _accel_axes(point)[1] @ point.R.inv().as_matrix()
    T = kron_t(point.t) @ vec_gain(point)
    F = Rt @ _base_accel_inverse(point)
    C = np.zeros((len(aj), 3, D.size))
    C[:, :, D["f_I"]] = np.eye(3)
    C[:, :, D["f_B"]] = -F
    C[:, :, D["df_B"]] = point.dtau * F
    C[:, :, D["vec_A"]] = -Rt @ T
    C[:, :, D["vec_dA"]] = point.dtau * (Rt @ T)
    C[:, :, D["tilt_terms"]] = tilt_columns(Rt, point.tilt)
    _bias_columns(C, D, aj, ak)
    return C


def _rotating(C: np.ndarray, layout: Layout, fixed: Sequence[str]) -> np.ndarray:
    """``C`` without the columns that do not turn with ``(I + E) R^T``."""
    out = C.copy()
    for name in fixed:
        out[:, layout[name]] = 0.0
    return out


def _axis_derivatives(
    D: np.ndarray,
    columns: Sequence[int],
    rotating: np.ndarray,
    axes: np.ndarray,
    left: np.ndarray | None = None,
) -> None:
    """Every column ``-L R^T K`` (``K`` data-free; ``L = (I + E) M``, ``left``, ``M = I`` by
    default) under a rotation step (``R^T -> (I - [d]x) R^T``) takes ``-L [d]x L^-1`` of
    itself, and under an axis error ``E_b`` ``S_b (I + E)^-1`` of itself; ``columns``: the
    rotation's three, then the axis errors' six."""
    left = axes if left is None else left
    inverse, left_inverse = np.linalg.inv(axes), np.linalg.inv(left)
    for m in range(3):
        D[columns[m]] = -(left @ skew(np.eye(3)[m]) @ left_inverse) @ rotating
    for b in range(6):
        D[columns[3 + b]] = (SYMMETRIC[b] @ inverse) @ rotating


def _base_gyro_steps(P: list[int]) -> tuple[list[int], list[int]]:
    """Where the base gyro's own errors among the globals ``P`` stand in ``P``, and which of
    :data:`_BASE_GYRO_STEPS` they are."""
    present = [k for k, p in enumerate(BASE_GYRO) if p in P]
    return [P.index(BASE_GYRO[k]) for k in present], present


def gyro_derivatives(point: Point, globals_: np.ndarray = GYRO_GLOBALS) -> np.ndarray:
    """``dC_g / dp`` for the globals ``globals_`` (:data:`GYRO_GLOBALS`, or those of them a
    problem frees, the base gyro's axes left out): (26, 3, 14) for all, the same for every
    window (the biases enter only the ``1`` and ``u`` columns, which no global moves; their
    own derivatives are constant, the solver's)."""
    D, P = GYRO_DATA, list(globals_)
    axes = triad_axes(point.own(GYRO_AXES))
    Rt = axes @ point.R.inv().as_matrix()
    C = gyro_coefficients(point, np.zeros((1, 3)), np.zeros((1, 3)))[0]
    out = np.zeros((len(P), 3, D.size))
    rotating = _rotating(C, D, ("w_I", "f_I", "one", "u"))
    axis_columns = [P.index(p) for p in (*range(3), *range(GYRO_AXES.start, GYRO_AXES.stop))]
    _axis_derivatives(out, axis_columns, rotating, axes)
    inverse_B = _base_gyro_inverse(point)
    out[P.index(TIME_OFFSET), :, D["dw_B"]] = Rt @ inverse_B
    # N_B^-1 right of the base's columns: d N_B^-1 = -N_B^-1 dN_B N_B^-1
    columns, present = _base_gyro_steps(P)
    for column, step in zip(columns, _BASE_GYRO_STEPS[present], strict=True):
        for name in ("w_B", "dw_B"):
            out[column, :, D[name]] = -C[:, D[name]] @ step @ inverse_B
    f_I = D["f_I"].start
    for i in range(3):
        for j in range(3):  # G_ij: row i of f_I's block takes -1 in column j
            out[P.index(G_SENSITIVITY.start + 3 * i + j), i, f_I + j] = -1.0
    return out


def accel_derivatives(point: Point, globals_: np.ndarray = ACCEL_GLOBALS) -> np.ndarray:
    """``dC_a / dp`` for the globals ``globals_`` (:data:`ACCEL_GLOBALS`: (31, 3, 33)), the same
    for every window (as :func:`gyro_derivatives`)."""
    D, P = ACCEL_DATA, list(globals_)
    axes, left = _accel_axes(point)
    Rt = left @ point.R.inv().as_matrix()
    columns, present = _base_gyro_steps(P)
    (gain, gain_steps), inverse_B = (
        _gains(_base_gyro_axes(point), present),
        _base_accel_inverse(point),
    )
    C = accel_coefficients(point, np.zeros((1, 3)), np.zeros((1, 3)))[0]
    out = np.zeros((len(P), 3, D.size))
    rotating = _rotating(C, D, ("f_I", "one", "u"))
    axis_columns = [P.index(p) for p in (*range(3), *range(ACCEL_AXES.start, ACCEL_AXES.stop))]
    _axis_derivatives(out, axis_columns, rotating, axes, left)
    to_rotating = np.linalg.inv(left)  # rotating = -L R^T K; phi_m: (I + E) [e_m]x R^T K
    for m in range(3):
        out[P.index(ACCEL_ROTATION.start + m)] = (
            -(axes @ skew(np.eye(3)[m]) @ to_rotating) @ rotating
        )
        E = kron_t(np.eye(3)[m]) @ gain
        out[P.index(TRANSLATION.start + m), :, D["vec_A"]] = -Rt @ E
        out[P.index(TRANSLATION.start + m), :, D["vec_dA"]] = point.dtau * Rt @ E
    tau = P.index(TIME_OFFSET)
    out[tau, :, D["df_B"]] = Rt @ inverse_B
    out[tau, :, D["vec_dA"]] = Rt @ kron_t(point.t) @ gain
    for k, unit in enumerate(np.eye(2)):
        out[P.index(TILT.start + k), :, D["tilt_terms"]] = tilt_columns(Rt, unit)
    for column, gain_step in zip(columns, Rt @ kron_t(point.t) @ gain_steps, strict=True):
        out[column, :, D["vec_A"]], out[column, :, D["vec_dA"]] = -gain_step, point.dtau * gain_step
    for b in range(6):  # d (I + D_B)^-1 = -(I + D_B)^-1 S_b (I + D_B)^-1
        step_B = Rt @ inverse_B @ SYMMETRIC[b] @ inverse_B
        column = P.index(BASE_ACCEL_AXES.start + b)
        out[column, :, D["f_B"]], out[column, :, D["df_B"]] = step_B, -point.dtau * step_B
    return out


def angular_acceleration_noise(samples: np.ndarray, variance: float) -> np.ndarray:
    """What the angular acceleration's white noise (``variance`` per axis and sample) adds to
    each window's ``vec A`` block of the accelerometer's moments, (K, 9, 9)."""
    return samples[:, None, None] * (variance * VEC_SKEW @ VEC_SKEW.T)
