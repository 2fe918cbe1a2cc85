"""The calibration on simulated drives with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.config import parse_config
from imucal_cli.core.calibrate import kabsch_rotation
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.pipeline import run_calibrate
from imucal_cli.sim import DriveOptions, simulate_drive


def calibrate(drive):
    return run_calibrate(drive.streams(), drive.config())


def errors(drive, result, name):
    mount = next(m for m in drive.mounts if m.name == name)
    T = result.T_base_lidar(name)
    rotation_error_B = (mount.T_base_lidar.rotation * T.rotation.inv()).as_rotvec()  # about base axes
    return rotation_error_B, T.translation - mount.T_base_lidar.translation


@pytest.mark.parametrize(("scenario", "duration"), [("aggressive", 81.0), ("parking", 60.0)])
def test_noise_free_drive_comes_back_exactly(scenario, duration):
    """Ideal sensors, no clock offsets: dR < 0.001 deg and |dt| < 1 mm for every lidar."""
    drive = simulate_drive(
        DriveOptions(scenario=scenario, duration_s=duration, seed=2, noise_scale=0.0, time_offsets_s=(0.0,), sensors=4)
    )
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert estimate.status == "ok"
        rot, trans = errors(drive, result, mount.name)
        assert np.degrees(np.linalg.norm(rot)) < 1e-3
        assert np.linalg.norm(trans) < 1e-3
        assert abs(estimate.time_offset_s) < 1e-5


@pytest.fixture(scope="module")
def offset_drives():
    """The same noisy drive with and without clock offsets of +-50 ms."""
    options = DriveOptions(scenario="aggressive", seed=7, time_offsets_s=(0.0, 0.0))
    shifted = DriveOptions(scenario="aggressive", seed=7, time_offsets_s=(0.05, -0.05))
    plain, offset = simulate_drive(options), simulate_drive(shifted)
    return plain, calibrate(plain), offset, calibrate(offset)


def test_clock_offsets_of_50_ms_are_recovered_within_1_ms(offset_drives):
    _, _, drive, result = offset_drives
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        error = estimate.time_offset_s - drive.time_offsets_s[mount.name]
        assert abs(error) < 1e-3
        assert abs(error) < 4 * estimate.time_offset_std_s


def test_clock_offsets_do_not_cost_accuracy(offset_drives):
    """Same noise realisation, with and without offsets: the estimates agree within their std."""
    plain_drive, plain, _offset_drive, offset = offset_drives
    for mount in plain_drive.mounts:
        a, b = plain.estimates[mount.name], offset.estimates[mount.name]
        std = np.sqrt(np.diag(a.covariance))
        angle = np.radians(rotation_angle_deg(a.T_base_imu.rotation, b.T_base_imu.rotation))
        assert angle < np.linalg.norm(std[:3])
        assert np.all(np.abs(a.T_base_imu.translation - b.T_base_imu.translation) < std[3:])


@pytest.mark.parametrize("seed", [3, 4])
def test_errors_lie_within_the_reported_uncertainty(seed):
    """Default noise: every axis within 4 reported std (a Gaussian fails this once in 16000)."""
    drive = simulate_drive(DriveOptions(scenario="aggressive", seed=seed))
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        std = np.sqrt(np.diag(estimate.lidar_covariance(mount.T_imu_lidar)))
        rot, trans = errors(drive, result, mount.name)
        assert np.all(np.abs(rot) < 4 * std[:3]), (rot / std[:3])
        assert np.all(np.abs(trans) < 4 * std[3:]), (trans / std[3:])
        # and the paper's own figures are beaten by far on the aggressive drive
        assert np.degrees(np.linalg.norm(rot)) < 0.05 and np.linalg.norm(trans) < 0.02


def test_motionless_drive_is_unobservable_and_returns_the_prior():
    drive = simulate_drive(DriveOptions(scenario="stationary", duration_s=40.0, seed=1))
    result = calibrate(drive)
    config = parse_config(drive.config_document(), "sim.config.yaml")
    for sensor in config.sensors:
        estimate = result.estimates[sensor.name]
        assert estimate.status == "unobservable"
        assert estimate.covariance is None
        assert np.array_equal(estimate.T_base_imu.as_matrix(), sensor.prior_T_base_imu.as_matrix())
        assert not any(w.selected for w in estimate.windows)
    assert not result.all_ok


def test_highway_is_honest():
    """Straight highway: either not 'ok', or the error inside 3 reported std on every axis."""
    drive = simulate_drive(DriveOptions(scenario="highway", seed=5))
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        if estimate.status != "ok":
            continue
        std = np.sqrt(np.diag(estimate.lidar_covariance(mount.T_imu_lidar)))
        rot, trans = errors(drive, result, mount.name)
        assert np.all(np.abs(rot) < 3 * std[:3]) and np.all(np.abs(trans) < 3 * std[3:])


def test_the_bounded_step_is_the_free_minimiser_inside_the_box_and_the_box_s_own_outside():
    """The translation box (eq. 16): where the unconstrained minimiser of ``x^T S x / 2 - s^T x``
    lies inside the box it is the step (to round-off); where it does not, the step is
    bounded-variable least squares' on the box, and it satisfies the optimality conditions
    (gradient zero on free coordinates, pointing out of the box on those at a bound)."""
    from scipy.optimize import lsq_linear

    from imucal_cli.core.calibrate import _bounded_step

    rng = np.random.default_rng(11)
    for _ in range(20):
        A = rng.normal(size=(7, 7))
        S = A @ A.T + 0.1 * np.eye(7)
        s = rng.normal(size=7)
        L = np.linalg.cholesky(S)
        free = np.linalg.solve(S, s)
        wide = np.abs(free).max() + 1.0
        np.testing.assert_allclose(_bounded_step(L, s, np.full(7, -wide), np.full(7, wide))[0], free, rtol=1e-12, atol=1e-12)
        lower, upper = np.full(7, -np.inf), np.full(7, np.inf)
        lower[3:6], upper[3:6] = -0.3 * np.abs(free[3:6]) - 0.01, 0.3 * np.abs(free[3:6]) + 0.01  # the box cuts it
        step = _bounded_step(L, s, lower, upper)[0]
        expected = lsq_linear(L.T, np.linalg.solve(L, s), bounds=(lower, upper), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(step, expected, rtol=1e-9, atol=1e-12)
        assert np.all(step >= lower - 1e-12) and np.all(step <= upper + 1e-12)
        gradient = S @ step - s
        at_lower, at_upper = np.isclose(step, lower, atol=1e-10), np.isclose(step, upper, atol=1e-10)
        inside = ~(at_lower | at_upper)
        assert (at_lower | at_upper).any()
        np.testing.assert_allclose(gradient[inside], 0.0, atol=1e-8 * np.abs(s).max())
        assert np.all(gradient[at_lower] >= -1e-8) and np.all(gradient[at_upper] <= 1e-8)


def test_the_bias_prior_in_banded_storage_is_the_random_walk_information():
    """The biases' prior, held as LAPACK's upper banded storage, is per component the random
    walk's information ``d^T d / (walk^2 dt)`` plus ``I / prior^2`` (knot order [gyro, accel]),
    and the banded product is the dense one; the banded Cholesky solves it."""
    from scipy.linalg import cho_solve_banded, cholesky_banded

    from imucal_cli.core.calibrate import _BAND, _KNOT, _band_times, _bias_prior

    n_knots, dt, walks, priors = 7, 10.0, (0.002, 0.01), (0.005, 1.0)
    band = _bias_prior(n_knots, dt, walks, priors)
    d = np.diff(np.eye(n_knots), axis=0)  # (K - 1, K) differences between neighbouring knots
    dense = np.zeros((_KNOT * n_knots, _KNOT * n_knots))
    for c in range(_KNOT):
        walk, prior = walks[c // 3], priors[c // 3]
        idx = np.arange(c, _KNOT * n_knots, _KNOT)
        dense[np.ix_(idx, idx)] = d.T @ d / (walk**2 * dt) + np.eye(n_knots) / prior**2
    rebuilt = np.zeros_like(dense)
    for i in range(len(dense)):
        for j in range(i, min(len(dense), i + _BAND + 1)):
            rebuilt[i, j] = rebuilt[j, i] = band[_BAND + i - j, j]
    np.testing.assert_allclose(rebuilt, dense, rtol=1e-14, atol=0)
    x = np.random.default_rng(3).normal(size=len(dense))
    np.testing.assert_allclose(_band_times(band, x), dense @ x, rtol=1e-12)
    np.testing.assert_allclose(cho_solve_banded((cholesky_banded(band), False), x), np.linalg.solve(dense, x), rtol=1e-10)


@pytest.mark.parametrize("dim", [14, 33])
def test_the_normal_equations_read_the_bias_blocks_off_the_moments(dim):
    """Each window's ``tr(D_p S D_q^T)``, ``tr(D_p S C^T)`` and ``tr(C S C^T)``, with the bias
    knots' constant derivatives (row m: -1 on the constant column, +1 on the time column for
    b_j; -1 on the time column for b_k) read off ``D S``, ``C S`` and ``S``, equal the products
    multiplied out with those derivatives written down in full."""
    from imucal_cli.core.calibrate import _normal_equations

    rng = np.random.default_rng(dim)
    K, P = 5, 4
    X = rng.normal(size=(K, 50, dim))
    S = np.einsum("kna,knb->kab", X, X)
    C, D = rng.normal(size=(K, 3, dim)), rng.normal(size=(K, P, 3, dim))
    bias = np.zeros((K, 6, 3, dim))
    for m in range(3):
        bias[:, m, m, dim - 2], bias[:, m, m, dim - 1] = -1.0, 1.0
        bias[:, 3 + m, m, dim - 1] = -1.0
    full = np.concatenate([D, bias], axis=1)
    H, g, cost = _normal_equations(D, S, C)
    np.testing.assert_allclose(H, np.einsum("kpra,kab,kqrb->kpq", full, S, full), rtol=1e-12, atol=1e-9)
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
        x = np.hstack([w_imu, np.zeros((500, 3)), w_base, np.zeros((500, 3)), np.ones((500, 1)), np.linspace(0, 1, 500)[:, None]])  # x_g; f_I, dw_B unused
        moments.append(x.T @ x)
    estimate = kabsch_rotation(np.stack(moments), np.full(4, 500.0))
    assert rotation_angle_deg(estimate, R) < 1e-9
