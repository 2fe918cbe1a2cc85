"""The calibration on simulated drives with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.config import parse_config
from imucal_cli.core.calibrate import kabsch_rotation
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.core.timing import estimate_time_offset
from imucal_cli.pipeline import DriveStreams, run_calibrate
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


def test_time_offset_estimator_is_sub_sample():
    rate = 100.0
    grid = np.arange(0, 60, 1 / rate)
    rng = np.random.default_rng(0)
    freqs, phases = rng.uniform(0.1, 2.0, 8), rng.uniform(0, 2 * np.pi, 8)

    def speed(t):
        return 0.3 + np.sum(0.05 * np.sin(2 * np.pi * freqs[:, None] * t[None, :] + phases[:, None]), axis=0)

    for tau in (0.0123, -0.0371, 0.0):
        estimate, peak = estimate_time_offset(grid, speed(grid), speed(grid - tau), 0.1)
        assert abs(estimate - tau) < 1e-3 and peak > 0.99


def test_kabsch_recovers_a_rotation_with_per_window_bias():
    """From per-window gyro moments, each window with its own constant bias."""
    rng = np.random.default_rng(1)
    R = Rotation.from_euler("xyz", [3, -20, 140], degrees=True)  # R_base_imu
    moments = []
    for _ in range(4):
        w_base = rng.normal(size=(500, 3))
        w_imu = R.inv().apply(w_base) + rng.normal(size=3)
        x = np.hstack([w_imu, w_base, np.zeros((500, 3)), np.ones((500, 1)), np.linspace(0, 1, 500)[:, None]])
        moments.append(x.T @ x)
    estimate = kabsch_rotation(np.stack(moments), np.full(4, 500.0))
    assert rotation_angle_deg(estimate, R) < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 90.0, 179.9999, 180.0])
def test_rotation_error_is_safe_near_0_and_180(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    a = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    b = a * Rotation.from_rotvec(np.radians(angle) * axis)
    assert rotation_angle_deg(a, b) == pytest.approx(angle, abs=1e-9)


def test_planar_motion_leaves_height_unobservable():
    """A rigid body turning only about z on a flat, smooth yard: [w]x^2 and [dw]x have no z
    column, so the lever arm's height is not observable: status partial, z kept at the prior."""
    from imucal_cli.sim.scenarios import VehicleDynamics

    flat = VehicleDynamics(
        roll_per_lateral_accel=0.0, pitch_per_longitudinal_accel=0.0, bump_roll_rad=0.0,
        bump_pitch_rad=0.0, bump_heave_m=0.0, max_grade=0.0,
    )
    drive = simulate_drive(DriveOptions(scenario="parking", seed=3, dynamics=flat))
    result = calibrate(drive)
    config = parse_config(drive.config_document(), "sim.config.yaml")
    for sensor in config.sensors:
        estimate = result.estimates[sensor.name]
        assert estimate.status == "partial"
        assert estimate.translation_observable.tolist() == [True, True, False]
        assert estimate.T_base_imu.translation[2] == sensor.prior_T_base_imu.translation[2]
        # the reported z std is the search box's, and the true height is inside it
        mount = next(m for m in drive.mounts if m.name == sensor.name)
        assert estimate.translation_std_m[2] == pytest.approx(sensor.translation_bound_m / np.sqrt(3))
        assert abs(estimate.T_base_imu.translation[2] - mount.T_base_imu.translation[2]) < sensor.translation_bound_m
        # x and y are still found
        assert np.all(np.abs(estimate.T_base_imu.translation[:2] - mount.T_base_imu.translation[:2]) < 4 * estimate.translation_std_m[:2])


def _vec(A):
    """Column-major vec of a stack of 3x3 matrices: (n, 3, 3) -> (n, 9), ``A t = (t^T x I) vec A``."""
    return A.transpose(0, 2, 1).reshape(len(A), 9)


def _plain_window_info(w_base, f_base, A, lever_arm, gyro_noise_std, accel_noise_std):
    """A window's rotation information (its min singular value) and lever-arm std, from sums
    over the samples (the module text of :mod:`imucal_cli.core.segments`), each equation's
    constant bias marginalised: the plain form of ``window_infos_from_moments``."""
    from imucal_cli.core.segments import _std_from_information
    from imucal_cli.core.so3 import skew

    def information(rows, noise_std):  # sum J^T J / s^2 of the centred rows
        centred = rows - rows.mean(axis=0)
        return np.einsum("nji,njk->ik", centred, centred) / noise_std**2

    v = f_base + np.einsum("nij,j->ni", A, lever_arm)  # the specific force predicted at the IMU
    rotation = information(-skew(w_base), gyro_noise_std) + information(-skew(v), accel_noise_std)
    return float(np.linalg.svd(rotation, compute_uv=False)[-1]), _std_from_information(information(A, accel_noise_std))


def test_window_information_from_moments_equals_the_sample_sums():
    """Segments reduced to moments report the same Fisher information as the sample sums."""
    from imucal_cli.core.segments import window_infos_from_moments

    rng = np.random.default_rng(0)
    n = 500
    w, f, A = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3, 3))
    lever = np.array([4.0, 1.0, 3.0])
    ones, u = np.ones((n, 1)), np.linspace(0, 1, n)[:, None]
    x_g = np.hstack([rng.normal(size=(n, 3)), w, rng.normal(size=(n, 3)), ones, u])
    x_a = np.hstack([rng.normal(size=(n, 3)), f, rng.normal(size=(n, 3)), _vec(A), _vec(rng.normal(size=(n, 3, 3))), ones, u])
    sigma_min, t_std = _plain_window_info(w, f, A, lever, 0.01, 0.02)
    (c,) = window_infos_from_moments(
        [(0.0, 10.0, True)], np.array([n]), (x_g.T @ x_g)[None], (x_a.T @ x_a)[None], lever, 0.01, 0.02, 1.0, 0.3
    )
    assert c.min_singular_value == pytest.approx(sigma_min, rel=1e-9)
    np.testing.assert_allclose(c.translation_std_m, t_std, rtol=1e-9)
    assert c.selected == (np.degrees(1.0 / np.sqrt(sigma_min)) < 1.0)


def test_live_feed_gives_an_estimate_after_every_window_and_the_batch_result():
    """Fed message by message with block_windows=1, the calibrator has an estimate as soon as
    a window is reduced, and ends where the batch run (blocks of windows) ends: the two differ
    only in where the clock offset was linearised and in filter edges inside the padding, far
    below the reported uncertainty."""
    from imucal_cli.core.streaming import StreamingCalibrator
    from imucal_cli.pipeline import feed, make_calibrator

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=100.0, seed=8))
    config = parse_config(drive.config_document(), "sim.config.yaml")
    streams = DriveStreams(drive.base.stream, {m.name: drive.sensors[m.name].stream for m in drive.mounts}, 0)
    batch = make_calibrator(config)
    feed(batch, streams)
    expected = batch.finish()

    live = StreamingCalibrator(list(make_calibrator(config).sensors.values()), block_windows=1)
    all_streams = {"base": streams.base, **streams.sensors}
    events = sorted((int(s.t_ns[i]), name, i) for name, s in all_streams.items() for i in range(len(s.t_ns)))
    seen = 0
    for _, name, i in events:
        s = all_streams[name]
        if live.add(name, s.t_ns[i : i + 1], s.gyro[i : i + 1], s.accel[i : i + 1]):
            seen += 1
            if seen == 2:  # an estimate already, after two windows
                early = live.estimates()
                assert all(e.status == "ok" for e in early.values())
    final = live.finish()
    assert seen >= 3
    for name, estimate in expected.items():
        std = np.sqrt(np.diag(estimate.covariance))
        angle = np.radians(rotation_angle_deg(final[name].T_base_imu.rotation, estimate.T_base_imu.rotation))
        assert angle < 0.05 * std[:3].min()
        assert np.all(np.abs(final[name].T_base_imu.translation - estimate.T_base_imu.translation) < 0.05 * std[3:])


def test_a_live_feed_may_reuse_its_buffers_after_each_add():
    """What add() was given is copied: a caller that refills the same arrays for the next
    samples (as a driver loop does) gets the estimate of the samples it fed."""
    from imucal_cli.pipeline import make_calibrator

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=3))
    config = parse_config(drive.config_document(), "sim.config.yaml")
    streams = {"base": drive.base.stream, **{m.name: drive.sensors[m.name].stream for m in drive.mounts}}
    fresh, reused = make_calibrator(config), make_calibrator(config)
    buffers = {name: (np.empty(50, dtype=np.int64), np.empty((50, 3)), np.empty((50, 3))) for name in streams}
    for start in range(0, max(len(s.t_ns) for s in streams.values()), 50):
        for name, s in streams.items():
            part = slice(start, min(start + 50, len(s.t_ns)))
            n = part.stop - part.start
            if n <= 0:
                continue
            fresh.add(name, s.t_ns[part].copy(), s.gyro[part].copy(), s.accel[part].copy())
            t, g, a = buffers[name]
            t[:n], g[:n], a[:n] = s.t_ns[part], s.gyro[part], s.accel[part]
            reused.add(name, t[:n], g[:n], a[:n])
    expected, got = fresh.finish(), reused.finish()
    for name, estimate in expected.items():
        assert got[name].T_base_imu.as_matrix().tobytes() == estimate.T_base_imu.as_matrix().tobytes()


def test_natural_cubic_spline_interpolates_and_matches_the_b_spline_away_from_the_ends():
    """The tridiagonal natural spline passes through every sample, and where the end conditions
    have died out (a few samples in) it is the not-a-knot B-spline, values and derivatives."""
    from scipy.interpolate import make_interp_spline

    from imucal_cli.core.streaming import _NaturalCubic

    rng = np.random.default_rng(5)
    t = np.arange(2000) / 200.0 + rng.normal(0.0, 2e-5, 2000)  # jittered stamps
    y = np.stack([np.sin(2 * np.pi * f * t + p) for f, p in [(0.3, 0), (1.0, 1), (3.0, 2)]], axis=1)
    spline, reference = _NaturalCubic(t, y), make_interp_spline(t, y, k=3)
    np.testing.assert_allclose(spline(t), y, rtol=0, atol=1e-13)
    query = np.linspace(t[40], t[-40], 5000)
    for nu, tol in [(0, 1e-12), (1, 1e-10), (2, 1e-7)]:
        np.testing.assert_allclose(spline(query, nu), reference(query, nu), rtol=0, atol=tol)


def test_lowpass_with_a_second_cutoff_is_the_two_filters_in_turn():
    """Two zero-phase responses multiplied in one pass equal the two filters applied one after
    the other (to round-off, away from the ends), and the pass band is kept."""
    from imucal_cli.core.signals import Lowpass

    rng = np.random.default_rng(6)
    x = np.cumsum(rng.normal(size=(4000, 2)), axis=0)
    both = Lowpass(5.0, 200.0, 4, 40.0)(x)
    in_turn = Lowpass(5.0, 200.0)(Lowpass(40.0, 200.0)(x))
    np.testing.assert_allclose(both[200:-200], in_turn[200:-200], rtol=0, atol=1e-9 * np.abs(x).max())
    t = np.arange(4000) / 200.0
    slow = np.sin(2 * np.pi * 0.2 * t)
    np.testing.assert_allclose(Lowpass(5.0, 200.0, 4, 40.0)(slow)[200:-200], slow[200:-200], atol=1e-6)


def test_symmetric_terms_filtered_by_their_upper_triangles_are_the_full_matrices():
    """What the block reduction builds: the upper triangles of ``[w]x^2`` and
    ``[dw]x[w]x + [w]x[dw]x`` formed element by element are those of the matrix products, and
    vec of (such a term low-passed by its upper triangle, plus a skew part) is vec of the whole
    matrix low-passed, plus that skew part."""
    from imucal_cli.core.signals import Lowpass
    from imucal_cli.core.so3 import skew, skew_squared
    from imucal_cli.core.streaming import _upper_symmetric_products, _vec_of_sum

    rng = np.random.default_rng(7)
    w, dw = rng.normal(size=(300, 3)), rng.normal(size=(300, 3))
    Sw, Sdw = skew(w), skew(dw)
    lp = Lowpass(5.0, 100.0)
    for term, (a, b, half) in ((skew_squared(w), (w, w, 0.5)), (Sdw @ Sw + Sw @ Sdw, (dw, w, 1.0))):
        upper = np.empty((300, 6))
        _upper_symmetric_products(a, b, upper)
        upper *= half
        np.testing.assert_allclose(upper, term[:, *np.triu_indices(3)], rtol=0, atol=1e-13)
        full = lp(term.reshape(-1, 9)).reshape(-1, 3, 3) + skew(dw)
        got = np.empty((300, 9))
        _vec_of_sum(lp(upper), dw, got)
        np.testing.assert_allclose(got, _vec(full), rtol=0, atol=1e-12)


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


@pytest.mark.parametrize("dim", [11, 29])
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
