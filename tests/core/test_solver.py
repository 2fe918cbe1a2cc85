"""The solver's parts: the bounded step (eq. 16), the biases' banded prior, the normal
equations read off the moments, and Kabsch/Horn (eq. 10)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.core.model import KNOT
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.core.solver import (
    BAND,
    BiasModel,
    band_times,
    bias_prior,
    bounded_step,
    globals_block,
    half_solve_banded,
    kabsch_rotation,
    window_equations,
)


def test_thebounded_step_is_the_free_minimiser_inside_the_box_and_the_box_s_own_outside():
    """The translation box (eq. 16): where the unconstrained minimiser of ``x^T S x / 2 - s^T x``
    lies inside the box it is the step (to round-off); where it does not, the step is
    bounded-variable least squares' on the box, and it satisfies the optimality conditions
    (gradient zero on free coordinates, pointing out of the box on those at a bound)."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(11)
    for _ in range(20):
        A = rng.normal(size=(7, 7))
        S = A @ A.T + 0.1 * np.eye(7)
        s = rng.normal(size=7)
        L = np.linalg.cholesky(S)
        free = np.linalg.solve(S, s)
        wide = np.abs(free).max() + 1.0
        np.testing.assert_allclose(
            bounded_step(L, s, np.full(7, -wide), np.full(7, wide))[0], free, rtol=1e-12, atol=1e-12
        )
        lower, upper = np.full(7, -np.inf), np.full(7, np.inf)
        lower[3:6], upper[3:6] = (
            -0.3 * np.abs(free[3:6]) - 0.01,
            0.3 * np.abs(free[3:6]) + 0.01,
        )  # the box cuts it
        step = bounded_step(L, s, lower, upper)[0]
        expected = lsq_linear(
            L.T, np.linalg.solve(L, s), bounds=(lower, upper), method="bvls", tol=1e-12
        ).x
        np.testing.assert_allclose(step, expected, rtol=1e-9, atol=1e-12)
        assert np.all(step >= lower - 1e-12) and np.all(step <= upper + 1e-12)
        gradient = S @ step - s
        at_lower, at_upper = (
            np.isclose(step, lower, atol=1e-10),
            np.isclose(step, upper, atol=1e-10),
        )
        inside = ~(at_lower | at_upper)
        assert (at_lower | at_upper).any()
        np.testing.assert_allclose(gradient[inside], 0.0, atol=1e-8 * np.abs(s).max())
        assert np.all(gradient[at_lower] >= -1e-8) and np.all(gradient[at_upper] <= 1e-8)


@pytest.mark.parametrize("gaps", [np.full(6, 10.0), np.array([10.0, 40.0, 10.0, 80.0, 20.0, 10.0])])
def test_the_bias_prior_in_banded_storage_is_the_random_walk_information(gaps):
    """The biases' prior, held as LAPACK's upper banded storage, is per component the random
    walk's information ``sum_i d_i^T d_i / (walk^2 dt_i)`` plus ``1 / prior^2`` at the first
    knot alone, where the walk starts (knot order [gyro, accel]), with knots evenly spaced or
    not (merged windows: one gap over several), and the banded product is the dense one; the
    banded Cholesky solves it."""
    from scipy.linalg import cho_solve_banded, cholesky_banded

    walks, priors = (0.002, 0.01), (0.005, 1.0)
    n_knots = len(gaps) + 1
    band = bias_prior(gaps, BiasModel(10.0, walks, priors))
    d = np.diff(np.eye(n_knots), axis=0)  # (K - 1, K) differences between neighbouring knots
    dense = np.zeros((KNOT.size * n_knots, KNOT.size * n_knots))
    for c in range(KNOT.size):
        walk, prior = walks[c // 3], priors[c // 3]
        idx = np.arange(c, KNOT.size * n_knots, KNOT.size)
        dense[np.ix_(idx, idx)] = d.T @ np.diag(1.0 / (walk**2 * gaps)) @ d
        dense[idx[0], idx[0]] += 1.0 / prior**2
    rebuilt = np.zeros_like(dense)
    for i in range(len(dense)):
        for j in range(i, min(len(dense), i + BAND + 1)):
            rebuilt[i, j] = rebuilt[j, i] = band[BAND + i - j, j]
    np.testing.assert_allclose(rebuilt, dense, rtol=1e-14, atol=0)
    x = np.random.default_rng(3).normal(size=len(dense))
    np.testing.assert_allclose(band_times(band, x), dense @ x, rtol=1e-12)
    np.testing.assert_allclose(
        cho_solve_banded((cholesky_banded(band), False), x), np.linalg.solve(dense, x), rtol=1e-10
    )


def test_the_half_solve_gives_the_schur_complement_of_the_biases():
    """With ``H_bb = U^T U`` banded, ``Z = U^-T H_gb^T`` makes ``Z^T Z`` the dense
    ``H_gb H_bb^-1 H_gb^T`` that eliminating the biases subtracts, and ``Z^T U^-T g`` the
    gradient's ``H_gb H_bb^-1 g``."""
    from scipy.linalg import cholesky_banded

    rng = np.random.default_rng(5)
    n_knots = 9
    band = bias_prior(np.full(n_knots - 1, 10.0), BiasModel(10.0, (0.002, 0.01), (0.005, 1.0)))
    n = KNOT.size * n_knots
    for d in range(1, BAND + 1):  # a window's coupling between knots, on top of the prior
        band[BAND - d, d:] += 0.1 * rng.normal(size=n - d) / (1 + d)
    band[BAND] += 50.0
    dense = np.zeros((n, n))
    for i in range(n):
        for j in range(i, min(n, i + BAND + 1)):
            dense[i, j] = dense[j, i] = band[BAND + i - j, j]
    H_gb, grad = rng.normal(size=(7, n)), rng.normal(size=n)
    factor = (cholesky_banded(band, lower=False), False)
    Z = half_solve_banded(factor, H_gb.T)
    np.testing.assert_allclose(Z.T @ Z, H_gb @ np.linalg.solve(dense, H_gb.T), rtol=1e-10)
    half = half_solve_banded(factor, grad[:, None])[:, 0]
    np.testing.assert_allclose(Z.T @ half, H_gb @ np.linalg.solve(dense, grad), rtol=1e-10)


@pytest.mark.parametrize("dim", [14, 33])
def test_the_normal_equations_read_the_bias_blocks_off_the_moments(dim):
    """Each window's ``tr(D_p S D_q^T)``, ``tr(D_p S C^T)`` and ``tr(C S C^T)``, with the bias
    knots' constant derivatives (row m: -1 on the constant column, +1 on the time column for
    b_j; -1 on the time column for b_k) read off ``D S``, ``C S`` and ``S``, equal the products
    multiplied out with those derivatives written down in full."""
    rng = np.random.default_rng(dim)
    K, P = 5, 4
    X = rng.normal(size=(K, 50, dim))
    S = np.einsum("kna,knb->kab", X, X)
    C, D = rng.normal(size=(K, 3, dim)), rng.normal(size=(P, 3, dim))
    bias = np.zeros((K, 6, 3, dim))
    for m in range(3):
        bias[:, m, m, dim - 2], bias[:, m, m, dim - 1] = -1.0, 1.0
        bias[:, 3 + m, m, dim - 1] = -1.0
    full = np.concatenate([np.broadcast_to(D, (K, P, 3, dim)), bias], axis=1)
    coupling, g, cost, bias_block = window_equations(D, S, C)
    H = np.zeros((K, P + 6, P + 6))
    for k in range(K):
        H[k, :P, :P] = globals_block(D, S[k])
    H[:, :P, P:], H[:, P:, :P] = coupling, coupling.transpose(0, 2, 1)
    H[:, P:, P:] = bias_block
    np.testing.assert_allclose(
        H, np.einsum("kpra,kab,kqrb->kpq", full, S, full), rtol=1e-12, atol=1e-9
    )
    np.testing.assert_allclose(g, np.einsum("kpra,kab,krb->kp", full, S, C), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(cost, np.einsum("kra,kab,krb->k", C, S, C), rtol=1e-12)


def test_kabsch_recovers_a_rotation_with_per_window_bias():
    """From per-window gyro moments, each window with its own constant bias."""
    rng = np.random.default_rng(1)
    R = Rotation.from_euler("xyz", [3, -20, 140], degrees=True)  # R_base_imu
    moments = []
    for _ in range(4):
        w_base = rng.normal(size=(500, 3))
        w_imu = R.inv().apply(w_base) + rng.normal(size=3)
        x = np.hstack(
            [
                w_imu,
                np.zeros((500, 3)),
                w_base,
                np.zeros((500, 3)),
                np.ones((500, 1)),
                np.linspace(0, 1, 500)[:, None],
            ]
        )  # x_g; f_I, dw_B unused
        moments.append(x.T @ x)
    estimate = kabsch_rotation(np.stack(moments))
    assert rotation_angle_deg(estimate, R) < 1e-9


def test_a_fit_stops_where_its_next_step_would_be_below_convergence(short_drive):
    """The fit stops once the step it would take next, from how its last two steps shrank, is
    below :data:`~imucal_cli.core.solver.CONVERGED` (one linearisation less than waiting to
    take that step): from where it stopped, one more Gauss-Newton step moves the rotation by
    less than 1e-10 rad and the other globals by less than 1e-8."""
    from dataclasses import replace

    from imucal_cli.core.calibrate import make_problem
    from imucal_cli.core.solver import CONVERGED
    from imucal_cli.pipeline import feed, make_calibrator

    calibrator = make_calibrator(short_drive.config())
    feed(calibrator, short_drive.streams())
    calibrator.finish()
    name = next(iter(calibrator.sensors))
    setup = calibrator.sensors[name]
    args = (setup.prior_T_base_imu, setup.options, calibrator.sigma[name], calibrator.lowpass)
    problem = make_problem(list(calibrator.moments(name)), *args, calibrator.dw_noise_var)
    start = problem.start()
    fit = problem.fit(start, start.free, estimate_scale=False)
    assert 1 < fit.iterations < problem.settings.max_iterations
    again = problem.fit(replace(fit, knots=fit.knots.copy()), fit.free, max_iterations=1)
    assert rotation_angle_deg(again.point.R, fit.point.R) < np.degrees(CONVERGED[0])
    np.testing.assert_allclose(again.point.t, fit.point.t, rtol=0, atol=CONVERGED[1])
    assert abs(again.point.dtau - fit.point.dtau) < CONVERGED[1]
