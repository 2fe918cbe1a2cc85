"""The measurement model: its layouts, and every derivative the solver uses against finite
differences of the model itself.

The estimator's residuals are ``r = C(p) x`` per window (:mod:`imucal_cli.core.model`:
``gyro_coefficients``, ``accel_coefficients``); the Gauss-Newton normal equations and the
reported covariance are built from hand-derived ``dC/dp`` (``gyro_derivatives``,
``accel_derivatives``) and the biases' sparse blocks written out in
``solver.window_equations`` and ``solver.globals_block``. Each is compared here, at random
points, with central differences of ``C`` under the model's own update (:meth:`Point.moved`:
``R <- R exp([d]x)``, the rest additive). Adding an error term to the model adds its
parameters to these loops.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.core import model
from imucal_cli.core.model import (
    ACCEL_DATA,
    ACCEL_GLOBALS,
    GYRO_DATA,
    GYRO_GLOBALS,
    KNOT,
    N_PARAMETERS,
    PARAMETERS,
    Point,
)
from imucal_cli.core.so3 import skew
from imucal_cli.core.solver import globals_block, window_equations

H = 1e-6  # central differences: truncation ~H^2, round-off ~1e-16/H
EQUATIONS = {
    "gyro": (model.gyro_coefficients, model.gyro_derivatives, GYRO_GLOBALS, KNOT["gyro_bias"]),
    "accel": (model.accel_coefficients, model.accel_derivatives, ACCEL_GLOBALS, KNOT["accel_bias"]),
}


def _point(rng: np.random.Generator, K: int = 4) -> tuple[Point, np.ndarray, np.ndarray]:
    """A random point, errors and tilt included, and two knots' biases per window."""
    errors = rng.normal(size=model.SENSOR_ERRORS.stop - model.SENSOR_ERRORS.start) * 0.01
    point = Point(
        Rotation.from_rotvec(rng.normal(size=3)),
        rng.normal(size=3) * 2.0,
        float(rng.normal() * 0.01),
        rng.normal(size=2) * 0.01,
        errors,
    )
    return point, rng.normal(size=(K, KNOT.size)) * 0.1, rng.normal(size=(K, KNOT.size)) * 0.1


def _C(which: str, point: Point, bj: np.ndarray, bk: np.ndarray) -> np.ndarray:
    coefficients, _, _, biases = EQUATIONS[which]
    return coefficients(point, bj[:, biases], bk[:, biases])


def _difference(
    which: str, point: Point, bj: np.ndarray, bk: np.ndarray, parameter: int
) -> np.ndarray:
    step = np.zeros(N_PARAMETERS)
    step[parameter] = H
    ahead, behind = _C(which, point.moved(step), bj, bk), _C(which, point.moved(-step), bj, bk)
    return (ahead - behind) / (2 * H)


def _bias_difference(
    which: str, point: Point, bj: np.ndarray, bk: np.ndarray, knot: int, axis: int
) -> np.ndarray:
    column = EQUATIONS[which][3].start + axis
    moved = []
    for h in (H, -H):
        knots = [bj.copy(), bk.copy()]
        knots[knot][:, column] += h
        moved.append(_C(which, point, *knots))
    return (moved[0] - moved[1]) / (2 * H)


def test_the_layouts_are_contiguous_and_every_parameter_is_in_an_equation():
    for layout in (PARAMETERS, GYRO_DATA, ACCEL_DATA, KNOT):
        covered = np.concatenate([np.arange(s.start, s.stop) for s in layout.slices.values()])
        assert np.array_equal(covered, np.arange(layout.size))
    held = set(GYRO_GLOBALS.tolist()) | set(ACCEL_GLOBALS.tolist())
    assert held == set(range(N_PARAMETERS))
    assert GYRO_DATA.size == 14 and ACCEL_DATA.size == 33  # the sizes the docstrings state
    # the solver reads a bias's columns as the last two of either data vector
    for layout in (GYRO_DATA, ACCEL_DATA):
        assert (layout.index("one"), layout.index("u")) == (layout.size - 2, layout.size - 1)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_each_global_derivative_is_the_models(seed, which):
    """Every derivative against central differences; at seed 0 with the base gyro's own errors
    zero, as every fit but those that estimate them evaluates them (its own code path)."""
    point, bj, bk = _point(np.random.default_rng(seed))
    if seed == 0:
        for block in (model.BASE_GYRO_SCALE, model.BASE_GYRO_AXES):
            point.own(block)[:] = 0.0
    _, derivatives, globals_, _ = EQUATIONS[which]
    D = derivatives(point)
    assert len(D) == len(globals_)
    for column, parameter in enumerate(globals_):
        numeric = _difference(which, point, bj, bk, int(parameter))  # (K, 3, dim): every window
        tolerance = 1e-8 * max(1.0, np.abs(numeric).max())
        for window in numeric:  # the same in every window, whatever its biases
            np.testing.assert_allclose(
                D[column], window, rtol=0, atol=tolerance, err_msg=f"{which}: {parameter}"
            )


@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_the_globals_a_residual_does_not_hold_have_no_derivative(which):
    """The parameters left out of an equation's list (:data:`GYRO_GLOBALS`,
    :data:`ACCEL_GLOBALS`) do not move its coefficients."""
    point, bj, bk = _point(np.random.default_rng(7))
    held = set(EQUATIONS[which][2].tolist())
    for parameter in sorted(set(range(N_PARAMETERS)) - held):
        assert np.abs(_difference(which, point, bj, bk, parameter)).max() == 0.0, (
            f"{which}: {parameter}"
        )


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_the_normal_equations_with_the_biases_sparse_blocks_are_the_full_products(seed, which):
    """``window_equations`` writes the two bias knots' blocks out by hand and
    ``globals_block`` takes the globals' block from the moments alone; with every derivative
    taken numerically (the biases' too) the Hessian, gradient and cost are
    ``tr(D_p S D_q^T)``, ``tr(D_p S C^T)`` and ``tr(C S C^T)``."""
    rng = np.random.default_rng(100 + seed)
    point, bj, bk = _point(rng)
    C = _C(which, point, bj, bk)
    K, _, dim = C.shape
    X = rng.normal(size=(K, 50, dim))
    S = X.transpose(0, 2, 1) @ X  # moments: symmetric, positive definite
    _, derivatives, globals_, _ = EQUATIONS[which]
    columns = [_difference(which, point, bj, bk, int(q)) for q in globals_]
    columns += [
        _bias_difference(which, point, bj, bk, knot, axis) for knot in (0, 1) for axis in range(3)
    ]
    D_full = np.stack(columns, axis=1)  # (K, P + 6, 3, dim)
    D = derivatives(point)
    P = len(D)
    coupling, g, cost, bias = window_equations(D, S, C)
    H = np.zeros((K, P + 6, P + 6))
    for k in range(K):
        H[k, :P, :P] = globals_block(D, S[k])
    H[:, :P, P:], H[:, P:, :P], H[:, P:, P:] = coupling, coupling.transpose(0, 2, 1), bias
    H_full = np.einsum("kpid,kde,kqie->kpq", D_full, S, D_full)
    g_full = np.einsum("kpid,kde,kie->kp", D_full, S, C)
    cost_full = np.einsum("kid,kde,kie->k", C, S, C)
    np.testing.assert_allclose(H, H_full, rtol=0, atol=1e-7 * np.abs(H_full).max())
    np.testing.assert_allclose(g, g_full, rtol=0, atol=1e-7 * np.abs(g_full).max())
    np.testing.assert_allclose(cost, cost_full, rtol=1e-12)
    # summed over windows with weights, the globals' block is the weighted sum of the windows'
    w = rng.uniform(size=K)
    np.testing.assert_allclose(
        globals_block(D, np.einsum("k,kde->de", w, S)),
        np.einsum("k,kpq->pq", w, H[:, :P, :P]),
        rtol=1e-12,
        atol=1e-12 * np.abs(H).max(),
    )


def test_the_residual_of_noise_free_signals_at_the_truth_is_zero():
    """Signals made by the model's equations (every error term present) give a zero residual
    at the true point: the coefficients state the equations the module's text writes."""
    rng = np.random.default_rng(5)
    point, bj, bk = _point(rng, K=1)
    n = 40
    w_B, dw_B, f_B, df_B = (rng.normal(size=(n, 3)) for _ in range(4))
    ddw_B = rng.normal(size=(n, 3))
    u = np.linspace(0.0, 1.0, n)
    Rt = point.R.inv().as_matrix()
    axes_g, axes_a = (
        model.triad_axes(point.own(model.GYRO_AXES)),
        model.triad_axes(point.own(model.ACCEL_AXES)),
    )
    G = point.own(model.G_SENSITIVITY).reshape(3, 3)
    A = np.array([skew(w) @ skew(w) + skew(d) for w, d in zip(w_B, dw_B, strict=True)])
    dA = np.array(
        [
            skew(d) @ skew(w) + skew(w) @ skew(d) + skew(dd)
            for w, d, dd in zip(w_B, dw_B, ddw_B, strict=True)
        ]
    )
    b_g = bj[0, KNOT["gyro_bias"]] + u[:, None] * (
        bk[0, KNOT["gyro_bias"]] - bj[0, KNOT["gyro_bias"]]
    )
    b_a = bj[0, KNOT["accel_bias"]] + u[:, None] * (
        bk[0, KNOT["accel_bias"]] - bj[0, KNOT["accel_bias"]]
    )
    k_roll, k_pitch = point.tilt
    theta = np.column_stack([k_roll * f_B[:, 1], k_pitch * f_B[:, 0], np.zeros(n)])
    # the base's readings corrected for its own errors: the rates are N_B^-1 of the gyro's
    # readings (the lever arm's terms formed of them), the specific force (I + D_B)^-1 of the
    # accelerometer's
    scale = point.own(model.BASE_GYRO_SCALE)[0]
    to_rate = np.linalg.inv(model.triad_axes(point.own(model.BASE_GYRO_AXES)) + scale * np.eye(3))
    w, d, dd = (v @ to_rate.T for v in (w_B, dw_B, ddw_B))
    a_true = np.array([skew(a) @ skew(a) + skew(b) for a, b in zip(w, d, strict=True)])
    da_true = np.array(
        [skew(b) @ skew(a) + skew(a) @ skew(b) + skew(c) for a, b, c in zip(w, d, dd, strict=True)]
    )
    to_force = np.linalg.inv(model.triad_axes(point.own(model.BASE_ACCEL_AXES)))
    specific = (
        (f_B - point.dtau * df_B) @ to_force.T
        + np.einsum("nij,j->ni", a_true - point.dtau * da_true, point.t)
        + np.cross(f_B, theta)
    )
    accel_rotation = np.eye(3) - skew(point.own(model.ACCEL_ROTATION))
    f_I = specific @ (axes_a @ accel_rotation @ Rt).T + b_a
    w_I = (w_B - point.dtau * dw_B) @ (axes_g @ Rt @ to_rate).T + f_I @ G.T + b_g
    vec = lambda M: M.transpose(0, 2, 1).reshape(n, 9)  # noqa: E731 (column-major vec)
    q = np.column_stack(
        [f_B[:, 1] * f_B[:, 2], f_B[:, 1] ** 2, f_B[:, 0] * f_B[:, 2], f_B[:, 0] ** 2]
    )
    x_g = np.column_stack([w_I, f_I, w_B, dw_B, np.ones(n), u])
    x_a = np.column_stack([f_I, f_B, df_B, vec(A), vec(dA), q, np.ones(n), u])
    r_g = x_g @ _C("gyro", point, bj, bk)[0].T
    r_a = x_a @ _C("accel", point, bj, bk)[0].T
    # the tilt enters to first order (the model's small-angle form): exact here by construction
    np.testing.assert_allclose(r_g, 0.0, atol=1e-12)
    np.testing.assert_allclose(r_a, 0.0, atol=1e-12)


def test_a_problem_without_the_base_gyros_axes_linearises_the_rest_alike():
    """The derivatives of the globals a problem may free (the base gyro's axes left out where
    its grade declares none) are the rows of all the globals' derivatives."""
    point, _, _ = _point(np.random.default_rng(11), K=1)
    kept = ~PARAMETERS.mask("base_gyro_axes")
    for _, derivatives, globals_, _ in EQUATIONS.values():
        subset = globals_[kept[globals_]]
        assert len(subset) == len(globals_) - 6
        rows = np.flatnonzero(kept[globals_])
        np.testing.assert_array_equal(derivatives(point, subset), derivatives(point)[rows])
