"""Every derivative the solver uses, against finite differences of the model itself.

The estimator's residuals are ``r = C(p) x`` per window (``core/calibrate.py``: ``_C_gyro``,
``_C_accel``); the Gauss-Newton normal equations and the reported covariance are built from
hand-derived ``dC/dp`` (``_derivatives_gyro``, ``_derivatives_accel``) and the biases' sparse
blocks written out in ``_normal_equations``. Each is compared here, at random points, with
central differences of ``C`` under the solver's own update rule (``R <- R exp([d]x)``,
everything else additive).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.core import calibrate as cal

H = 1e-6  # central differences: truncation ~H^2, round-off ~1e-16/H


def _point(rng: np.random.Generator, K: int = 4) -> dict:
    return {
        "R": Rotation.from_rotvec(rng.normal(size=3)),
        "t": rng.normal(size=3) * 2.0,
        "dtau": float(rng.normal() * 0.01),
        "tilt": rng.normal(size=2) * 0.01,
        "intrinsics": rng.normal(size=21) * 0.01,
        "bj": rng.normal(size=(K, 6)) * 0.1,
        "bk": rng.normal(size=(K, 6)) * 0.1,
    }


def _C(point: dict, which: str) -> np.ndarray:
    """The residual coefficients at a point, composed as the solver composes them."""
    Rt = point["R"].inv().as_matrix()
    intrinsics = point["intrinsics"]
    if which == "gyro":
        axes = cal._axes(intrinsics[6:12])
        return cal._C_gyro(axes @ Rt, point["dtau"], intrinsics[12:].reshape(3, 3), point["bj"][:, 0:3], point["bk"][:, 0:3])
    axes = cal._axes(intrinsics[:6])
    return cal._C_accel(axes @ Rt, point["t"], point["dtau"], point["tilt"], point["bj"][:, 3:6], point["bk"][:, 3:6])


def _moved(point: dict, parameter: int, step: float) -> dict:
    """The point after a step of one global unknown (the solver's numbering, ``N_GLOBAL``)."""
    moved = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in point.items()}
    if parameter < 3:
        moved["R"] = point["R"] * Rotation.from_rotvec(step * np.eye(3)[parameter])
    elif parameter < 6:
        moved["t"][parameter - 3] += step
    elif parameter == cal.TAU:
        moved["dtau"] += step
    elif cal.TILT.start <= parameter < cal.TILT.stop:
        moved["tilt"][parameter - cal.TILT.start] += step
    else:
        moved["intrinsics"][parameter - cal.AXES.start] += step
    return moved


def _moved_bias(point: dict, which: str, knot: str, axis: int, step: float) -> dict:
    moved = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in point.items()}
    moved[knot][:, (0 if which == "gyro" else 3) + axis] += step
    return moved


def _difference(point: dict, which: str, move) -> np.ndarray:
    return (_C(move(point, H), which) - _C(move(point, -H), which)) / (2 * H)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_each_global_derivative_is_the_models(seed, which):
    rng = np.random.default_rng(seed)
    point = _point(rng)
    C = _C(point, which)
    Rt = point["R"].inv().as_matrix()
    if which == "gyro":
        axes = cal._axes(point["intrinsics"][6:12])
        D, globals_ = cal._derivatives_gyro(C, axes @ Rt, axes), cal._GYRO_GLOBALS
    else:
        axes = cal._axes(point["intrinsics"][:6])
        D, globals_ = cal._derivatives_accel(C, axes @ Rt, point["t"], point["dtau"], axes), cal._ACCEL_GLOBALS
    assert D.shape[1] == len(globals_)
    for column, parameter in enumerate(globals_):
        numeric = _difference(point, which, lambda p, h, parameter=parameter: _moved(p, int(parameter), h))
        np.testing.assert_allclose(D[:, column], numeric, rtol=0, atol=1e-8 * max(1.0, np.abs(numeric).max()), err_msg=f"{which}: global {parameter}")


@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_the_globals_a_residual_does_not_hold_have_no_derivative(which):
    """The parameters left out of an equation's list (:data:`_GYRO_GLOBALS`,
    :data:`_ACCEL_GLOBALS`) do not move its coefficients."""
    point = _point(np.random.default_rng(7))
    held = set((cal._GYRO_GLOBALS if which == "gyro" else cal._ACCEL_GLOBALS).tolist())
    for parameter in sorted(set(range(cal.N_GLOBAL)) - held):
        numeric = _difference(point, which, lambda p, h, parameter=parameter: _moved(p, parameter, h))
        assert np.abs(numeric).max() == 0.0, f"{which}: global {parameter}"


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("which", ["gyro", "accel"])
def test_normal_equations_with_the_biases_sparse_blocks_are_the_full_products(seed, which):
    """``_normal_equations`` writes the two bias knots' blocks out by hand; with every
    derivative taken numerically (the biases' too) the Hessian, gradient and cost are
    ``tr(D_p S D_q^T)``, ``tr(D_p S C^T)`` and ``tr(C S C^T)``."""
    rng = np.random.default_rng(100 + seed)
    point = _point(rng)
    C = _C(point, which)
    K, _, dim = C.shape
    X = rng.normal(size=(K, 50, dim))
    S = X.transpose(0, 2, 1) @ X  # moments: symmetric, positive definite
    globals_ = cal._GYRO_GLOBALS if which == "gyro" else cal._ACCEL_GLOBALS
    columns = [_difference(point, which, lambda p, h, q=int(q): _moved(p, q, h)) for q in globals_]
    columns += [_difference(point, which, lambda p, h, k=knot, a=axis: _moved_bias(p, which, k, a, h)) for knot in ("bj", "bk") for axis in range(3)]
    D_full = np.stack(columns, axis=1)  # (K, P + 6, 3, dim)
    Rt = point["R"].inv().as_matrix()
    if which == "gyro":
        axes = cal._axes(point["intrinsics"][6:12])
        D = cal._derivatives_gyro(C, axes @ Rt, axes)
    else:
        axes = cal._axes(point["intrinsics"][:6])
        D = cal._derivatives_accel(C, axes @ Rt, point["t"], point["dtau"], axes)
    Hs, g, cost = cal._normal_equations(D, S, C)
    H_full = np.einsum("kpid,kde,kqie->kpq", D_full, S, D_full)
    g_full = np.einsum("kpid,kde,kie->kp", D_full, S, C)
    cost_full = np.einsum("kid,kde,kie->k", C, S, C)
    scale = np.abs(H_full).max()
    np.testing.assert_allclose(Hs, H_full, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(g, g_full, rtol=0, atol=1e-7 * np.abs(g_full).max())
    np.testing.assert_allclose(cost, cost_full, rtol=1e-12)
