"""Old windows merged so that what a sensor keeps is bounded in the log's length."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from imucal_cli.core.calibrate import bias_model, make_problem
from imucal_cli.core.model import (
    ACCEL_DATA,
    GYRO_DATA,
    KNOT,
    SENSOR_ERRORS,
    BiasModel,
    Point,
    accel_coefficients,
    gyro_coefficients,
)
from imucal_cli.core.moments import (
    WindowMoments,
    assemble_moments,
    base_moments,
    constant_moments,
    merged,
)
from imucal_cli.core.segments import WindowInfo
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.types import rotation_type


def _window(rng, number: int, span: int = 1, samples: int = 500) -> WindowMoments:
    """A window of random data vectors (the ``one`` and ``u`` columns as a window's: 1, and
    the time across its ``span`` windows)."""
    moments = []
    for layout in (GYRO_DATA, ACCEL_DATA):
        X = rng.normal(size=(samples, layout.size))
        X[:, layout.index("one")] = 1.0
        X[:, layout.index("u")] = (np.arange(samples) + 0.5) / samples
        moments.append(X.T @ X)
    S_g, S_a = moments
    info = WindowInfo(
        10.0 * number, 10.0 * (number + span), 1.0, 0.1, True, np.ones(3), np.ones(3, bool), True
    )
    return WindowMoments(
        number,
        10.0 * number,
        10.0 * (number + span),
        True,
        base_moments(S_g[6:, 6:], S_a[3:, 3:]),
        S_g[:6].copy(),
        S_a[:3].copy(),
        samples,
        info,
        span=span,
        count=span,
    )


def _short_windows(document):
    document.setdefault("segments", {})["window_s"] = 2.0


def _reduced(drive):
    """The calibrator of a drive fed whole, in 2 s windows none of which is merged."""
    from imucal_cli.pipeline import feed, make_calibrator

    calibrator = make_calibrator(drive.config(_short_windows))
    feed(calibrator, drive.streams())
    calibrator.finish()
    return calibrator


@pytest.mark.parametrize("group", [2, 3])
def test_a_stretch_is_fitted_as_the_windows_it_holds(short_drive, group):
    """Merging is exact for the fit: a sensor's windows, each with a clock shift of its own
    (a followed clock's track beyond the offset it was resampled at), merged into stretches of
    ``group`` (each moved by its shift, the bias knots between their ends eliminated under the
    biases' walk and prior) give the fit of the windows themselves -- the extrinsics, the
    clock, their covariance and the stretches' end knots -- at the residual std the fit starts
    from, to round-off. (With the shifts in the coefficients and not in the derivatives, as the
    solver had them, the rotations differed by 0.0026 deg.)"""
    calibrator = _reduced(short_drive)
    name = next(iter(calibrator.sensors))
    setup, sigma = calibrator.sensors[name], calibrator.sigma[name]
    windows = list(calibrator.moments(name))
    assert len(windows) >= 8 and all(w.count == 1 for w in windows)
    shifts = np.random.default_rng(group).normal(0, 2e-3, len(windows))
    for w, shift in zip(windows, shifts, strict=True):
        w.shift_s = float(shift)
    biases = bias_model(setup.options)
    calibrator.windows[name] = [
        merged(part, np.array([w.shift_s for w in part]), part[0].offset_s, biases, sigma)
        for part in (windows[i : i + group] for i in range(0, len(windows), group))
    ]
    stretches = calibrator.moments(name)  # (their observability)
    args = (setup.prior_T_base_imu, setup.options, sigma, calibrator.lowpass)
    whole, merged_ = (make_problem(w, *args, calibrator.dw_noise_var) for w in (windows, stretches))
    assert merged_.n_knots < whole.n_knots
    start = whole.start()
    free = start.free.copy()
    fits = [
        problem.fit(
            replace(start, knots=np.zeros((problem.n_knots, KNOT.size))), free, estimate_scale=False
        )
        for problem in (whole, merged_)
    ]
    a, b = fits
    assert rotation_angle_deg(a.point.R, b.point.R) < 1e-9
    np.testing.assert_allclose(b.point.t, a.point.t, rtol=0, atol=1e-9)
    assert abs(b.point.dtau - a.point.dtau) < 1e-12
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-7, atol=1e-20)
    ends = np.isin(whole.knot_numbers, merged_.knot_numbers)
    np.testing.assert_allclose(b.knots, a.knots[ends], rtol=0, atol=1e-9)


def test_a_window_moved_by_its_clock_shift_costs_what_it_costs_at_that_shift():
    """A window merged with the clock shift its track gives it costs, at any point and knots,
    what it costs at the point's clock offset plus that shift (the model's ``dtau`` columns are
    the base's terms' derivatives: the shift is a linear map of the data vector), to
    round-off."""
    rng = np.random.default_rng(5)
    window = _window(rng, 3)
    shift = 2.5e-3
    moved = merged(
        [window], np.array([shift]), 0.0, BiasModel(10.0, (1e-3, 1e-2), (1e-2, 1.0)), (0.1, 0.2)
    )
    point = Point(
        rotation_type().from_rotvec(rng.normal(size=3)),
        rng.normal(size=3),
        3e-3,
        rng.normal(size=2) * 1e-3,
        rng.normal(size=SENSOR_ERRORS.stop - SENSOR_ERRORS.start) * 1e-2,
    )
    knots = rng.normal(size=(5, KNOT.size))
    later = replace(point, dtau=point.dtau + shift)
    np.testing.assert_allclose(_cost(moved, point, knots), _cost(window, later, knots), rtol=1e-10)


def _cost(window: WindowMoments, point: Point, knots: np.ndarray) -> float:
    """The window's gyro and accelerometer cost ``tr(C S C^T)`` with its biases at the knots
    of its ends (window numbers)."""
    j, k = knots[window.number], knots[window.number + window.span]
    g, a = KNOT["gyro_bias"], KNOT["accel_bias"]
    Cg = gyro_coefficients(point, j[None, g], k[None, g])
    Ca = accel_coefficients(point, j[None, a], k[None, a])
    S_g, S_a = assemble_moments([window], "gyro"), assemble_moments([window], "accel")
    return float(np.trace(Cg[0] @ S_g[0] @ Cg[0].T) + np.trace(Ca[0] @ S_a[0] @ Ca[0].T))


def test_a_window_not_used_is_counted_and_walks_as_a_gap_does():
    """A window left out (not selected) is counted in the merged stretch and adds no data: the
    stretch is what its neighbours give across a gap of one window (its knots walk, free)."""
    rng = np.random.default_rng(2)
    a, b, c = (_window(rng, n) for n in (0, 1, 2))
    b.info = WindowInfo(10.0, 20.0, 0.0, 9.0, False, np.ones(3), np.ones(3, bool), True)
    biases, sigma = BiasModel(10.0, (1e-3, 1e-2), (1e-2, 1.0)), (0.1, 0.2)
    whole = merged([a, b, c], np.zeros(3), 0.0, biases, sigma)
    across = merged([a, c], np.zeros(2), 0.0, biases, sigma)
    assert whole.count == 3 and whole.samples == a.samples + c.samples
    assert whole.span == across.span == 3  # (the stretch of numbers 0-2 either way)
    for which, layout in (("gyro", GYRO_DATA), ("accel", ACCEL_DATA)):
        np.testing.assert_allclose(
            assemble_moments([whole], which), assemble_moments([across], which), rtol=1e-12
        )
        one = layout.index("one")  # (the constant's own moment, read without assembling)
        S = assemble_moments([a, whole], which)
        np.testing.assert_array_equal(constant_moments([a, whole], which), S[:, one, one])


def test_a_noise_free_drive_kept_in_few_units_is_the_drive_kept_whole(monkeypatch, ideal_drive):
    """An ideal drive (biases constant: one line over any stretch holds them exactly) with
    every window beyond the newest two merged into at most five units gives the extrinsics of
    its windows kept whole, to round-off, and counts every window."""
    from imucal_cli.core import streaming
    from imucal_cli.pipeline import calibrate_streams

    def short_windows(document):
        document.setdefault("segments", {})["window_s"] = 2.0

    config = ideal_drive.config(short_windows)
    whole = calibrate_streams(ideal_drive.streams(), config)
    monkeypatch.setattr(streaming, "FULL_WINDOWS", 2)
    monkeypatch.setattr(streaming, "MAX_UNITS", 5)
    kept = calibrate_streams(ideal_drive.streams(), config)
    for mount in ideal_drive.mounts:
        name = mount.name
        assert len(kept.windows[name]) == 5 < len(whole.windows[name])
        counted = [sum(w.count for w in r.estimates[name].windows) for r in (kept, whole)]
        assert counted[0] == counted[1] == len(whole.windows[name])
        a, b = kept.T_base_lidar(name), whole.T_base_lidar(name)
        assert (a.rotation * b.rotation.inv()).magnitude() < 1e-9
        np.testing.assert_allclose(a.translation, b.translation, rtol=0, atol=1e-8)
        assert kept.estimates[name].status == whole.estimates[name].status == "ok"


def test_segments_keep_every_window_s_row_while_the_estimate_keeps_few(monkeypatch, ideal_drive):
    """Where the rows are asked for (``segments``), every window is listed in time order, one
    row each, although the calibrator keeps at most five units; without, the units are listed,
    each with the windows it stands for."""
    from imucal_cli.core import streaming
    from imucal_cli.pipeline import feed, make_calibrator

    def short_windows(document):
        document.setdefault("segments", {})["window_s"] = 2.0

    monkeypatch.setattr(streaming, "FULL_WINDOWS", 2)
    monkeypatch.setattr(streaming, "MAX_UNITS", 5)
    config = ideal_drive.config(short_windows)
    listed = {}
    for keep_rows in (True, False):
        calibrator = make_calibrator(config, keep_rows=keep_rows)
        feed(calibrator, ideal_drive.streams())
        calibrator.finish()
        listed[keep_rows] = calibrator.window_infos(config.sensors[0].name)
    rows, units = listed[True], listed[False]
    assert len(rows) == sum(info.count for info in units) > len(units) == 5
    assert all(info.count == 1 for info in rows)
    starts = [info.start_s for info in rows]
    np.testing.assert_allclose(np.diff(starts), 2.0, rtol=1e-9)


def test_windows_merged_for_want_of_motion_are_not_called_gaps():
    """Windows left out for want of motion, merged, stay windows without a gap: the sentence of
    a sensor none of whose windows moved enough counts every window, and a gap only where there
    was one."""
    from imucal_cli.core.status import unobservable_reason

    rng = np.random.default_rng(4)
    still = []
    for number in range(4):
        w = _window(rng, number)
        w.info = WindowInfo(
            10.0 * number, 10.0 * number + 10, 0.0, 9.0, False, np.ones(3), np.ones(3, bool), True
        )
        still.append(w)
    gap = _window(rng, 4)
    gap.valid = False
    gap.info = WindowInfo(40.0, 50.0, 0.0, 9.0, False, np.ones(3), np.ones(3, bool), False)
    biases = BiasModel(10.0, (1e-3, 1e-2), (1e-2, 1.0))
    stretch = merged(still, np.zeros(4), 0.0, biases, (0.1, 0.2))
    assert stretch.valid and stretch.info is not None and stretch.info.count == 4
    sentence = unobservable_reason([stretch.info, gap.info])
    assert sentence.startswith("no window carried enough motion (1 of 5 have a gap")
    assert not merged([*still, gap], np.zeros(5), 0.0, biases, (0.1, 0.2)).valid
