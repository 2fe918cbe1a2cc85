"""Clocks that drift: a window's offset measured, the track's line, and drives whose lidar
clocks drift from the base's followed to an ``ok`` estimate."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.core.clock import ClockTrack, window_offsets
from tests.conftest import lidar_error


def test_a_window_measures_the_offset_its_sensor_was_resampled_off_by():
    """``w_I(t) = R^T w_B(t - delta) + b``: the first-order regression recovers ``delta`` to
    its second-order error, ``delta^2`` times the motion's frequency (here under 1%)."""
    rate, delta = 100.0, 1.5e-3
    t = np.arange(0.0, 20.0, 1.0 / rate)
    freqs, phases = np.array([0.7, 1.3, 0.4]), np.array([0.2, 1.1, 2.0])

    def w(times):
        return 0.3 * np.sin(2 * np.pi * freqs * times[:, None] + phases)

    def dw(times):
        return 0.3 * 2 * np.pi * freqs * np.cos(2 * np.pi * freqs * times[:, None] + phases)

    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # R_base_imu
    w_I = w(t - delta) @ R + np.array([0.01, -0.02, 0.005])  # R^T w_B(t - delta) + b, by row
    valid = np.ones(len(t), dtype=bool)
    found = window_offsets(w(t), dw(t), w_I, valid, [(0, 1000), (1000, 1000)], 1.0)
    for measured in found:
        assert measured is not None
        assert measured[0] == pytest.approx(delta, rel=0.01)


def test_the_track_fits_a_drifting_offset_exactly():
    """Noise-free measurements of ``tau + drift t`` give the line back to round-off, and the
    offsets to resample at follow it once it stands off the boot's offset."""
    tau, drift = 3e-3, 80e-6
    track = ClockTrack(tau0=tau, max_drift=200e-6)
    for t in np.arange(5.0, 300.0, 10.0):
        track.add(float(t), tau + drift * t, (1e-4) ** 2)
    fit = track.fit()
    assert fit is not None
    assert fit.drift == pytest.approx(drift, rel=1e-9)
    assert fit.at(np.array([0.0, 100.0])) == pytest.approx(tau + drift * np.array([0, 100]))
    assert fit.shown
    later = np.array([400.0, 460.0])
    assert track.predictor(later)(later) == pytest.approx(tau + drift * later, abs=1e-12)


def test_a_step_of_the_clock_is_found_in_the_window_that_holds_it():
    """Blocks of six windows of a clock drifting at 50 ppm that steps by 10 ms in the fourth
    window of the second block: the step is placed there (the window that holds it, half
    stepped, is neither piece's), its size within 3 std; the windows after it start a piece
    of the line and the drift is the one both share. A step in the last window of a block is
    found with the next block, and the windows resampled before it are not to be used."""
    tau, drift, size, var = 3e-3, 50e-6, 0.010, (1e-4) ** 2

    def block(first: int, step_in: int) -> list[tuple[int, float, float, float, float]]:
        rows = []
        for number in range(first, first + 6):
            t = 10.0 * number + 5.0
            stepped = size if number > step_in else size / 2 if number == step_in else 0.0
            rows.append((number, t - 5.0, t, tau + drift * t + stepped, var))
        return rows

    track = ClockTrack(tau0=tau, max_drift=200e-6)
    assert track.add_block(block(0, 99)) == []
    unused = track.add_block(block(6, 9))
    assert unused == [9, 10]
    (step,) = track.steps
    assert step.at_s == pytest.approx(100.0) and abs(step.size_s - size) <= 3 * step.std_s
    fit = track.fit()
    assert fit is not None and fit.drift == pytest.approx(drift, rel=1e-6)
    assert fit.at(np.array([115.0]))[0] == pytest.approx(tau + drift * 115.0 + size, abs=1e-9)
    assert track.add_block(block(12, 9)) == []  # and the next block is on the new piece

    late = ClockTrack(tau0=tau, max_drift=200e-6)
    late.add_block(block(0, 99))
    assert late.add_block(block(6, 11)) == []  # one window after it: not yet a step
    assert late.add_block(block(12, 11)) == [11, 12]
    assert late.steps[0].at_s == pytest.approx(120.0)


def test_a_drift_beyond_the_configured_one_is_held_at_it():
    track = ClockTrack(tau0=0.0, max_drift=50e-6)
    for t in np.arange(5.0, 300.0, 10.0):
        track.add(float(t), 120e-6 * t, (1e-4) ** 2)
    fit = track.fit()
    assert fit is not None and fit.drift == pytest.approx(50e-6)


@pytest.fixture(scope="module")
def drifting():
    """A 300 s urban drive whose two lidar clocks drift at +80 and -120 ppm (12-36 ms)."""
    from imucal_cli.sim import DriveOptions, simulate_drive

    return simulate_drive(
        DriveOptions(scenario="urban", duration_s=300.0, seed=1, clock_drifts_ppm=(80.0, -120.0))
    )


def test_lidars_whose_clocks_drift_are_ok_with_the_drift_within_its_std(drifting):
    """Before the clock was followed both lidars were `inconsistent` (residuals 13-19x the
    noise, lever arms 40-50 mm off); followed, each is `ok`, its extrinsics within 4 std and
    its drift within 3 std, and the offset at t0 within 3 std of the truth's."""
    from imucal_cli.api import calibrate_streams

    cal = calibrate_streams(drifting.streams(), drifting.config())
    truth = drifting.truth_document()["sensors"]
    document = cal.document()["sensors"]
    for name, s in document.items():
        assert s["status"] == "ok", s["warnings"]
        error, std = lidar_error(drifting, cal, name)
        assert np.all(np.abs(error) <= 4 * std)
        assert (
            abs(s["clock_drift_ppm"] - truth[name]["clock_drift_ppm"])
            <= 3 * s["clock_drift_std_ppm"]
        )
        assert abs(s["time_offset_s"] - truth[name]["time_offset_s"]) <= 3 * s["time_offset_std_s"]
        assert any("clock drifts" in note for note in s["notes"])


def test_a_drift_not_estimated_is_null_and_the_offset_one(drifting):
    """``calibration.max_clock_drift_ppm: 0``: one offset for the log, no drift said."""
    from imucal_cli.api import calibrate_streams

    def no_drift(document):
        document["calibration"]["max_clock_drift_ppm"] = 0

    cal = calibrate_streams(drifting.streams(), drifting.config(no_drift))
    for s in cal.document()["sensors"].values():
        assert s["clock_drift_ppm"] is None and s["clock_drift_std_ppm"] is None
        assert not any("clock drifts" in note for note in s["notes"])


def test_a_clock_that_steps_mid_drive_is_said_and_followed():
    """A lidar clock re-synchronised by 15 ms at 150 s of a 300 s drive drifting at 20 ppm:
    before the steps were found it was `inconsistent`, its drift 97 ppm; now the step is said
    (within two windows, its size within 3 std), the sensor `ok` and its drift within 3 std."""
    from imucal_cli.api import calibrate_streams
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(
        DriveOptions(
            scenario="urban",
            duration_s=300.0,
            seed=1,
            sensors=1,
            clock_drifts_ppm=(20.0,),
            clock_steps=(((150.0, 0.015),),),
        )
    )
    cal = calibrate_streams(drive.streams(), drive.config())
    ((name, s),) = cal.document()["sensors"].items()
    assert s["status"] == "ok", s["warnings"]
    assert abs(s["clock_drift_ppm"] - 20.0) <= 3 * s["clock_drift_std_ppm"]
    (said,) = [w for w in s["warnings"] if w.startswith("clock stepped by")]
    size, std = (float(v) for v in said.split("by ")[1].split(" ms")[0].split(" +- "))
    at_s = float(said.split(" at ")[1].split(" s")[0])
    assert abs(size - 15.0) <= 3 * std and abs(at_s - 150.0) <= 20.0
    error, std_axes = lidar_error(drive, cal, name)
    assert np.all(np.abs(error) <= 4 * std_axes)
