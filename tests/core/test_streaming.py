"""The streaming calibrator: live feeds, the spline and the block's symmetric terms."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.config import parse_config
from imucal_cli.core.estimates import estimates
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.types import DriveStreams


def _vec(A):
    """Column-major vec of a stack of 3x3 matrices: (n, 3, 3) -> (n, 9),
    ``A t = (t^T x I) vec A``."""
    return A.transpose(0, 2, 1).reshape(len(A), 9)


def test_live_feed_gives_an_estimate_after_every_window_and_the_batch_result():
    """Fed message by message with block_windows=1, the calibrator has an estimate as soon as
    a window is reduced, and ends where the batch run (blocks of windows) ends: the two differ
    only in where the clock offset was linearised and in filter edges inside the padding, far
    below the reported uncertainty."""
    from imucal_cli.core.streaming import StreamingCalibrator
    from imucal_cli.pipeline import feed, make_calibrator

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=100.0, seed=8))
    config = parse_config(drive.config_document(), "sim.config.yaml")
    streams = DriveStreams(
        drive.base.stream, {m.name: drive.sensors[m.name].stream for m in drive.mounts}, 0
    )
    batch = make_calibrator(config)
    feed(batch, streams)
    batch.finish()
    expected = estimates(batch)

    live = StreamingCalibrator(list(make_calibrator(config).sensors.values()), block_windows=1)
    all_streams = {"base": streams.base, **streams.sensors}
    events = sorted(
        (int(s.t_ns[i]), name, i) for name, s in all_streams.items() for i in range(len(s.t_ns))
    )
    seen = 0
    for _, name, i in events:
        s = all_streams[name]
        if live.add(name, s.t_ns[i : i + 1], s.gyro[i : i + 1], s.accel[i : i + 1]):
            seen += 1
            if seen == 2:  # an estimate already, after two windows
                early = estimates(live)
                assert all(e.status == "ok" for e in early.values())
    live.finish()
    final = estimates(live)
    assert seen >= 3
    for name, estimate in expected.items():
        std = np.sqrt(np.diag(estimate.covariance))
        angle = np.radians(
            rotation_angle_deg(final[name].T_base_imu.rotation, estimate.T_base_imu.rotation)
        )
        assert angle < 0.05 * std[:3].min()
        assert np.all(
            np.abs(final[name].T_base_imu.translation - estimate.T_base_imu.translation)
            < 0.05 * std[3:]
        )


def test_a_live_feed_may_reuse_its_buffers_after_each_add():
    """What add() was given is copied: a caller that refills the same arrays for the next
    samples (as a driver loop does) gets the estimate of the samples it fed."""
    from imucal_cli.pipeline import make_calibrator

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=3))
    config = parse_config(drive.config_document(), "sim.config.yaml")
    streams = {
        "base": drive.base.stream,
        **{m.name: drive.sensors[m.name].stream for m in drive.mounts},
    }
    fresh, reused = make_calibrator(config), make_calibrator(config)
    buffers = {
        name: (np.empty(50, dtype=np.int64), np.empty((50, 3)), np.empty((50, 3)))
        for name in streams
    }
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
    fresh.finish()
    reused.finish()
    expected, got = estimates(fresh), estimates(reused)
    for name, estimate in expected.items():
        assert (
            got[name].T_base_imu.as_matrix().tobytes() == estimate.T_base_imu.as_matrix().tobytes()
        )


def test_natural_cubic_spline_interpolates_and_matches_the_b_spline_away_from_the_ends():
    """The tridiagonal natural spline passes through every sample, and where the end conditions
    have died out (a few samples in) it is the not-a-knot B-spline, values and derivatives."""
    from scipy.interpolate import make_interp_spline

    from imucal_cli.core.resample import NaturalCubic as _NaturalCubic

    rng = np.random.default_rng(5)
    t = np.arange(2000) / 200.0 + rng.normal(0.0, 2e-5, 2000)  # jittered stamps
    y = np.stack([np.sin(2 * np.pi * f * t + p) for f, p in [(0.3, 0), (1.0, 1), (3.0, 2)]], axis=1)
    spline, reference = _NaturalCubic(t, y), make_interp_spline(t, y, k=3)
    np.testing.assert_allclose(spline(t), y, rtol=0, atol=1e-13)
    query = np.linspace(t[40], t[-40], 5000)
    for nu, tol in [(0, 1e-12), (1, 1e-10), (2, 1e-7)]:
        np.testing.assert_allclose(spline(query, nu), reference(query, nu), rtol=0, atol=tol)


def test_symmetric_terms_filtered_by_their_upper_triangles_are_the_full_matrices():
    """What the block reduction builds: the upper triangles of ``[w]x^2`` and
    ``[dw]x[w]x + [w]x[dw]x`` formed element by element are those of the matrix products, and
    vec of (such a term low-passed by its upper triangle, plus a skew part) is vec of the whole
    matrix low-passed, plus that skew part."""
    from imucal_cli.core.moments import upper_symmetric_products as _upper_symmetric_products
    from imucal_cli.core.moments import vec_of_sum as _vec_of_sum
    from imucal_cli.core.signals import Lowpass
    from imucal_cli.core.so3 import skew, skew_squared

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


def test_windows_that_hold_a_saturated_reading_are_not_used(monkeypatch):
    """A sensor gyro clipped at its full scale (here a tenth of a percent of the readings, at a
    full scale the test lowers to the drive's peaks): every window within the low-pass's
    length of a clipped reading is not valid, the others are as before, the warning names the
    topic and the level, and the estimate lies within its std of the truth."""
    from imucal_cli.core import signals
    from imucal_cli.pipeline import make_calibrator

    monkeypatch.setattr(signals, "MIN_FULL_SCALE", (0.1, 1.0))
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=150.0, seed=4))
    config = parse_config(drive.config_document(), "sim.config.yaml")
    name = drive.mounts[0].name
    clean = drive.sensors[name].stream
    level = float(np.quantile(np.abs(clean.gyro).max(axis=1), 0.999))
    clipped = type(clean)(clean.t_ns, np.clip(clean.gyro, -level, level), clean.accel)
    calibrators = []
    for sensor in (clean, clipped):
        calibrator = make_calibrator(config)
        streams = {
            "base": drive.base.stream,
            **{m.name: drive.sensors[m.name].stream for m in drive.mounts},
        }
        streams[name] = sensor
        for imu, s in streams.items():
            calibrator.add(imu, s.t_ns, s.gyro, s.accel)
        calibrator.finish()
        calibrators.append(calibrator)
    before, after = (c.windows[name] for c in calibrators)
    stamps = calibrators[1]._seconds(clean.t_ns[np.abs(clean.gyro).max(axis=1) >= level])
    reach = 1.0 / calibrators[1].lowpass.cutoff_hz
    tau = calibrators[1].tau0[name]
    hit = [
        bool(np.any((stamps >= w.start_s + tau - reach) & (stamps <= w.end_s + tau + reach)))
        for w in after
    ]
    assert 0 < sum(hit) < len(after)
    assert [w.valid for w in after] == [b.valid and not h for b, h in zip(before, hit, strict=True)]
    estimate = estimates(calibrators[1])[name]
    topic = config.sensors[0].imu_topic
    assert any(
        w.startswith(f"{topic}: the gyro saturates at {level:.4g} rad/s") for w in estimate.warnings
    )
    truth = next(m for m in drive.mounts if m.name == name).T_base_imu
    std = np.sqrt(np.diag(estimate.covariance))
    angle = np.radians(rotation_angle_deg(estimate.T_base_imu.rotation, truth.rotation))
    assert angle < 4 * std[:3].max()
    assert np.all(np.abs(estimate.T_base_imu.translation - truth.translation) < 4 * std[3:])


def test_a_short_log_has_one_threshold_stated_truly_and_never_passes_with_no_window():
    """Exit codes went 2, 0 (unobservable, 0/0 windows), 2, then partial as a log grew from 4
    to 10 s, and the message left out the padding. Now: below the one threshold the message
    states, too little data; at or above it, a result with at least one window."""
    import re

    from imucal_cli.api import calibrate_streams
    from imucal_cli.core.streaming import TooLittleData
    from imucal_cli.sim import DriveOptions, simulate_drive

    thresholds, outcomes = set(), []
    for duration in (4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 9.5, 10.0):
        drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=duration, seed=1))
        try:
            result = calibrate_streams(drive.streams(), drive.config())
        except TooLittleData as exc:
            overlap, need = map(float, re.findall(r"([\d.]+) s", str(exc)))
            assert overlap == pytest.approx(duration, abs=0.05) and overlap < need
            thresholds.add(need)
            outcomes.append(False)
            continue
        for estimate in result.estimates.values():
            assert len(estimate.windows) >= 1
        outcomes.append(True)
    assert len(thresholds) == 1
    assert outcomes == sorted(outcomes) and outcomes[0] is False and outcomes[-1] is True
    (need,) = thresholds
    assert 9.0 < need <= 9.5  # the last failing and first passing durations bracket it


def test_dropped_samples_are_put_back_on_a_cubic_exactly_and_gaps_are_left():
    """A cubic sampled at 200 Hz with single, double and triple drops and one long gap: every
    dropped sample comes back on the cubic to rounding (the fill is Lagrange's cubic through
    two samples each side), at its stamp on the period's grid; the long gap stays a gap."""
    from imucal_cli.core.resample import GAP_PERIODS, filled

    period = 0.005
    k = np.arange(2000)
    drops = {10, 300, 301, 900, 901, 902, 1999 - 2}
    gap = set(range(1500, 1500 + int(GAP_PERIODS) + 5))
    kept = np.array([i for i in k if i not in drops | gap])
    t = 0.37 + kept * period

    def cubic(x):
        return np.stack([x**3 - 2 * x, 0.5 * x**2 + 1, -(x**3)], axis=1)

    both = np.hstack([cubic(t), cubic(t - 1.0)])
    t_out, both_out = filled(t, both, period)
    back = sorted(drops)
    assert len(t_out) == len(t) + len(back)
    assert np.all(np.diff(t_out) > 0)
    expected_t = 0.37 + np.array(sorted(set(kept) | drops)) * period
    np.testing.assert_allclose(t_out, expected_t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(both_out[:, :3], cubic(t_out), rtol=0, atol=1e-9)
    np.testing.assert_allclose(both_out[:, 3:], cubic(t_out - 1.0), rtol=0, atol=1e-9)


def test_a_window_s_moments_are_the_same_however_the_windows_are_blocked():
    """The moments take every second grid row (:func:`~imucal_cli.core.moments.moment_step`)
    on the log's grid, not the block's: with windows of an odd number of grid samples
    (10.05 s at 100 Hz), a window reduced alone (a follower's) and within a block of six (a
    recorded log's) has the same moments but for the filters' edges in the padding (1e-8;
    rows taken from the block's start differ by 2e-3 in every second window)."""
    from imucal_cli.pipeline import feed, make_calibrator

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=100.0, seed=8))
    document = drive.config_document()
    document.setdefault("segments", {})["window_s"] = 10.05
    config = parse_config(document, "sim.config.yaml")
    streams = DriveStreams(
        drive.base.stream, {m.name: drive.sensors[m.name].stream for m in drive.mounts}, 0
    )
    reduced = []
    for blocks in (1, 6):
        calibrator = make_calibrator(config, block_windows=blocks)
        feed(calibrator, streams)
        calibrator.finish()
        reduced.append(calibrator)
    from imucal_cli.core.model import GYRO_DATA
    from imucal_cli.core.moments import assemble_moments

    one = GYRO_DATA.index("one")
    for name in reduced[0].sensors:
        # the rows taken stand for the window's samples: the "one" column sums to their count
        # (the windows' means and scatters take it so; a last window of 579 samples in 290
        # rows of two made a spinning wheel's scatter negative)
        assert any(w.samples % 2 for w in reduced[1].windows[name])  # (1005: odd)
        for window in reduced[1].windows[name]:
            ones = assemble_moments([window], "gyro")[0][one, one]
            assert ones == pytest.approx(window.samples, rel=1e-12)
        pairs = list(zip(reduced[0].windows[name], reduced[1].windows[name], strict=True))
        assert len(pairs) >= 8
        for alone, blocked in pairs:
            assert alone.number == blocked.number
            for which in ("rows_gyro", "rows_accel"):
                a, b = getattr(alone, which), getattr(blocked, which)
                assert np.max(np.abs(a - b)) <= 1e-6 * np.max(np.abs(b)), (alone.number, which)
