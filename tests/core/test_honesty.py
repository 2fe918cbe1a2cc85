"""`ok` means right: the checks, the units, the clock offset and the box on drives that do not
match the estimator's model (the error classes of ``imucal simulate --errors``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import lidar_error

from imucal_cli.api import DriveStreams, calibrate_streams
from imucal_cli.config import parse_config
from imucal_cli.core.boot import UnitsError
from imucal_cli.core.signals import (
    Lowpass,
    derivative_noise_variance,
    white_noise_density,
    white_noise_std,
)
from imucal_cli.core.timing import TIME_OFFSET_MAX_STD_S, time_offset_shown
from imucal_cli.errors import ConfigError, ImucalError
from imucal_cli.outputs import calibration_document
from imucal_cli.sim import DriveOptions, simulate_drive, with_errors
from imucal_cli.sim.imu import MEMS_LIDAR
from imucal_cli.types import ImuStream


def calibrate(drive):
    return calibrate_streams(drive.streams(), drive.config())


def normalized_errors(drive, result, name):
    """Error over the reported std per axis (rotation about the base axes, then xyz)."""
    error, std = lidar_error(drive, result, name)
    return error / std


def drive_with(errors, scenario="aggressive", seed=3, **options):
    return simulate_drive(
        with_errors(DriveOptions(scenario=scenario, seed=seed, **options), errors)
    )


@pytest.fixture(scope="module")
def si_twin():
    drive = drive_with("none")
    return drive, calibrate(drive)


@pytest.mark.parametrize(
    ("errors", "words"),
    [("accel-g", "accelerometer publishes g"), ("gyro-dps", "gyro publishes deg/s")],
)
def test_units_are_detected_and_calibrate_as_the_si_twin(si_twin, errors, words):
    """The same drive published in g or deg/s: a warning naming the conversion, the same
    status, and an estimate within a small fraction of its std of the SI twin's (the output
    resolution differs between the units, nothing else)."""
    _, twin = si_twin
    drive = drive_with(errors)
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate, reference = result.estimates[mount.name], twin.estimates[mount.name]
        assert any(words in w for w in estimate.warnings), estimate.warnings
        assert estimate.status == reference.status == "ok"
        std = np.sqrt(np.diag(reference.covariance))
        delta_rot = (estimate.T_base_imu.rotation * reference.T_base_imu.rotation.inv()).as_rotvec()
        delta_t = estimate.T_base_imu.translation - reference.T_base_imu.translation
        assert np.all(np.abs(delta_rot) < 0.5 * std[:3]) and np.all(np.abs(delta_t) < 0.5 * std[3:])


def test_a_base_gyro_in_deg_per_s_is_detected():
    drive = simulate_drive(DriveOptions(scenario="aggressive", seed=3, base_gyro_units="dps"))
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert any(w.startswith("base: gyro publishes deg/s") for w in estimate.warnings)
        assert estimate.status == "ok" and np.all(
            np.abs(normalized_errors(drive, result, mount.name)) < 4
        )


def test_declared_units_are_taken_as_declared():
    """``gyro_units: dps`` in the config converts without guessing (and without a warning)."""
    drive = drive_with("gyro-dps")

    def declare(document):
        for sensor in document["sensors"].values():
            sensor["gyro_units"] = "dps"

    result = calibrate_streams(drive.streams(), drive.config(declare))
    for mount in drive.mounts:
        assert result.estimates[mount.name].status == "ok"
        assert not any("publishes" in w for w in result.estimates[mount.name].warnings)


def test_units_that_cannot_be_told_are_an_error_naming_topic_and_key():
    drive = drive_with("none", sensors=1)
    mount = drive.mounts[0]
    stream = drive.sensors[mount.name].stream
    odd = ImuStream(stream.t_ns, stream.gyro, stream.accel * 3.0, stream.frame_id)  # |f| about 29
    with pytest.raises(UnitsError) as error:
        calibrate_streams(DriveStreams(drive.base.stream, {mount.name: odd}, 0), drive.config())
    assert mount.imu_topic in str(error.value) and f"sensors.{mount.name}.accel_units" in str(
        error.value
    )
    assert isinstance(error.value, ImucalError)


def test_a_tilting_mount_is_inconsistent_and_its_tilt_measured():
    """A mount leaning 0.2 deg per m/s^2: not ok, the tilt within 30% (and within 4 of its
    std) of the simulated one, the rotation given the mount's at rest and covered by its std."""
    drive = drive_with("tilting-mount", scenario="urban", duration_s=150.0)
    truth = np.degrees(drive.options.mount_tilt_rad_per_mps2)
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        rigid = estimate.checks["rigid_mount"]
        assert estimate.status == "inconsistent" and not rigid["pass"]
        tilt, std = np.array(rigid["tilt_deg_per_mps2"]), np.array(rigid["std"])
        assert np.all(np.abs(tilt - truth) <= 0.3 * truth) and np.all(
            np.abs(tilt - truth) < 4 * std
        )
        assert any("not rigid" in w for w in estimate.warnings)
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)


def test_gyro_and_accelerometer_misaligned_apart_fail_the_rotation_check():
    drive = drive_with("misaligned", scenario="urban", duration_s=150.0)
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert (
            estimate.status == "inconsistent"
            and not estimate.checks["gyro_vs_accel_rotation"]["pass"]
        )
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)


def test_a_prior_off_by_more_than_the_box_is_never_ok():
    """The truth 0.5 m from the prior, the box +-0.3 m: x rests on the box, the warning says
    how far the data pull it (about the 0.2 m left), and the std covers the error."""
    drive = drive_with("prior-off", scenario="urban", duration_s=150.0)
    result = calibrate(drive)
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert estimate.status != "ok"
        box = [w for w in estimate.warnings if "rests on its box" in w]
        assert box and box[0].startswith("translation x")
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)


def test_clean_drives_pass_every_check(si_twin):
    drive, result = si_twin
    document = calibration_document(result, "sim.mcap")
    for mount in drive.mounts:
        sensor = document["sensors"][mount.name]
        assert sensor["status"] == "ok" and sensor["warnings"] == []
        assert all(check["pass"] for check in sensor["checks"].values())
        assert sensor["time_offset_observable"] is True
        assert sensor["accel_intrinsics"]["estimated"] is False
        assert (
            sensor["gyro_intrinsics"]["estimated"] is False
            and sensor["gyro_intrinsics"]["g_sensitivity"]["estimated"] is False
        )
        cov = np.array(sensor["covariance"]["matrix"])
        assert (
            cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        )
        assert np.allclose(
            np.sqrt(np.diag(cov)),
            [*np.radians(sensor["rotation_std_deg"]), *sensor["translation_std_m"]],
        )


def test_floors_of_the_config_are_added_to_the_std(si_twin):
    drive, plain = si_twin

    def floors(document):
        for sensor in document["sensors"].values():
            sensor["rotation_floor_deg"], sensor["translation_floor_m"] = 0.05, 0.01

    floored = calibrate_streams(drive.streams(), drive.config(floors))
    for mount in drive.mounts:
        a, b = plain.estimates[mount.name], floored.estimates[mount.name]
        np.testing.assert_allclose(
            b.rotation_std_deg**2, a.rotation_std_deg**2 + 0.05**2, rtol=1e-9
        )
        np.testing.assert_allclose(
            b.translation_std_m**2, a.translation_std_m**2 + 0.01**2, rtol=1e-9
        )


def test_a_flat_or_edge_correlation_does_not_place_the_clock_offset():
    rate, gain = 100.0, Lowpass(5.0, 100.0).white_noise_gain()
    grid = np.arange(0, 60, 1 / rate)
    rng = np.random.default_rng(1)
    freqs, phases = rng.uniform(0.1, 2.0, 8), rng.uniform(0, 2 * np.pi, 8)

    def speed(t, amplitude):
        return 0.3 + np.sum(
            amplitude * np.sin(2 * np.pi * freqs[:, None] * t[None, :] + phases[:, None]), axis=0
        )

    rich = time_offset_shown(grid, speed(grid, 0.05), speed(grid - 0.02, 0.05), 0.1, 1e-3, gain)
    assert (
        rich.shown
        and abs(rich.tau_s - 0.02) < 3 * rich.std_s
        and rich.std_s < TIME_OFFSET_MAX_STD_S
    )
    flat = time_offset_shown(
        grid,
        speed(grid, 1e-5),
        speed(grid - 0.02, 1e-5) + rng.normal(0, 1e-3, len(grid)),
        0.1,
        1e-3,
        gain,
    )
    assert not flat.shown and flat.std_s > TIME_OFFSET_MAX_STD_S
    edge = time_offset_shown(grid, speed(grid, 0.05), speed(grid - 0.3, 0.05), 0.1, 1e-3, gain)
    assert not edge.shown and "edge" in edge.reason


def test_the_angular_acceleration_noise_variance_is_the_filtered_derivative_s():
    """Monte Carlo: white noise of a given density, differentiated and low-passed as the base
    gyro is, has the variance :func:`derivative_noise_variance` says (within its sampling
    error, about 2% for this many independent stretches)."""
    lowpass, rate, density = Lowpass(5.0, 100.0), 100.0, 1e-3
    rng = np.random.default_rng(2)
    x = rng.normal(0.0, density * np.sqrt(rate), (200_000, 1))
    derivative = lowpass(np.gradient(x[:, 0], 1 / rate))
    expected = derivative_noise_variance(lowpass, density)
    assert np.var(derivative[1000:-1000]) == pytest.approx(expected, rel=0.05)


@pytest.mark.parametrize(
    ("key", "value", "problem"),
    [
        ("accel_units", "mg", "expected one of auto, mps2, g"),
        ("gyro_units", "rpm", "expected one of auto, radps, dps"),
        ("rotation_floor_deg", -1.0, "must be >= 0"),
    ],
)
def test_new_sensor_keys_are_checked(key, value, problem):
    drive = drive_with("none", sensors=1)
    document = drive.config_document()
    name = drive.mounts[0].name
    document["sensors"][name][key] = value
    with pytest.raises(ConfigError, match=problem) as error:
        parse_config(document, "v.yaml")
    assert f"sensors.{name}.{key}" in str(error.value)


def test_consistency_alpha_must_be_a_rate():
    document = drive_with("none", sensors=1).config_document()
    document["calibration"]["consistency_alpha"] = 0.7
    with pytest.raises(ConfigError, match=r"calibration\.consistency_alpha"):
        parse_config(document, "v.yaml")
    document["calibration"]["consistency_alpha"] = 0.01
    assert parse_config(document, "v.yaml").calibration.consistency_alpha == 0.01


def test_accelerometer_scale_errors_are_estimated_where_they_show():
    """0.5% scale factors and 0.2 deg non-orthogonality on the accelerometer (the case that
    put the lever arm 6 std off): estimated within 4 std of the simulated ones, and the
    extrinsics inside 3 std again."""
    model = replace(MEMS_LIDAR, scale_factor_std=0.005, nonorthogonality_std_rad=np.radians(0.2))
    drive = simulate_drive(DriveOptions(scenario="urban", seed=4, sensors=4, lidar_model=model))
    result = calibrate(drive)
    estimated = 0
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)
        axes = estimate.accel_intrinsics
        if not axes["estimated"]:
            continue
        estimated += 1
        true = drive.sensors[mount.name].accel_axes - np.eye(3)
        truth = np.array([true[0, 0], true[1, 1], true[2, 2], true[0, 1], true[0, 2], true[1, 2]])
        value = np.array(axes["scale"] + list(np.radians(axes["nonorthogonality_deg"])))
        std = np.array(axes["scale_std"] + list(np.radians(axes["nonorthogonality_std_deg"])))
        shown = np.isfinite(std)
        assert np.all(np.abs(value - truth)[shown] < 4 * std[shown])
        assert any("accelerometer axis errors estimated" in n for n in estimate.notes)
        assert not any("estimated with the extrinsics" in w for w in estimate.warnings)
    assert estimated >= 3


def test_gyro_axis_errors_and_g_sensitivity_are_estimated_where_they_show():
    """0.5% scale factors, 0.2 deg non-orthogonality and 0.1 deg/s per g of g-sensitivity on the
    gyro (what left MEMS lidars 0.1-0.5 deg off, every one `inconsistent`): each estimated
    within 4 of its std of the simulated one, the extrinsics inside 3 std and `ok`, and the
    document carries them."""
    from imucal_cli.types import GRAVITY_MPS2

    model = replace(
        MEMS_LIDAR,
        scale_factor_std=0.005,
        nonorthogonality_std_rad=np.radians(0.2),
        g_sensitivity_std=np.radians(0.1) / GRAVITY_MPS2,
    )
    drive = simulate_drive(DriveOptions(scenario="urban", seed=4, sensors=4, lidar_model=model))
    result = calibrate(drive)
    document = calibration_document(result, "sim.mcap")
    for mount in drive.mounts:
        estimate, simulated = result.estimates[mount.name], drive.sensors[mount.name]
        assert estimate.status == "ok"
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)
        axes = document["sensors"][mount.name]["gyro_intrinsics"]
        assert axes["estimated"] and axes["g_sensitivity"]["estimated"]
        true = simulated.gyro_axes - np.eye(3)
        truth = np.array([true[0, 0], true[1, 1], true[2, 2], true[0, 1], true[0, 2], true[1, 2]])
        value = np.array(axes["scale"] + list(np.radians(axes["nonorthogonality_deg"])))
        std = np.array(axes["scale_std"] + list(np.radians(axes["nonorthogonality_std_deg"])))
        shown = np.isfinite(std)
        assert np.all(np.abs(value - truth)[shown] < 4 * std[shown])
        per_g = np.degrees(1.0) * GRAVITY_MPS2
        g_value, g_std = (
            np.array(axes["g_sensitivity"]["dps_per_g"]),
            np.array(axes["g_sensitivity"]["std_dps_per_g"]),
        )
        shown = np.isfinite(g_std)
        assert shown.sum() >= 6
        assert np.all(np.abs(g_value - per_g * simulated.g_sensitivity)[shown] < 4 * g_std[shown])
        assert any("gyro axis errors estimated" in n for n in estimate.notes)
        assert any("gyro g-sensitivity estimated" in n for n in estimate.notes)
        assert not any("estimated with the extrinsics" in w for w in estimate.warnings)


def test_a_mount_vibration_is_not_counted_as_white_noise():
    """White noise plus a 37 Hz vibration ten times its std: the periodogram's median in
    10-20 Hz finds the noise (within its sampling error), second differences do not."""
    rate, std = 100.0, 0.01
    rng = np.random.default_rng(3)
    t = np.arange(60_000) / rate
    x = rng.normal(0.0, std, (len(t), 3)) + 0.1 * np.sin(2 * np.pi * 37.0 * t)[:, None]
    density = white_noise_density(x, rate, (10.0, 20.0))
    np.testing.assert_allclose(density * np.sqrt(rate), std, rtol=0.05)
    assert np.all(white_noise_std(x) > 3 * std)


def test_a_failed_rotation_check_covers_the_discrepancy_it_measured():
    """Gyro and accelerometer triads 0.2 deg apart: the check fails, and the reported rotation
    std covers the rotation difference it measured (its variance holds ``delta delta^T``), not
    a share of it scaled by the chi-square (issue 30, item 5)."""
    drive = simulate_drive(
        with_errors(DriveOptions(scenario="urban", seed=3, sensors=2), "misaligned")
    )
    result = calibrate_streams(drive.streams(), drive.config())
    failed = 0
    for estimate in result.estimates.values():
        check = estimate.checks["gyro_vs_accel_rotation"]
        if check["pass"]:
            continue
        failed += 1
        assert estimate.status == "inconsistent"
        total = float(np.sqrt(np.sum(estimate.rotation_std_deg**2)))
        assert total >= check["difference_deg"], (total, check["difference_deg"])
    assert failed


@pytest.fixture(scope="module")
def wheel():
    """A car's wheel (B at its hub) rolling straight at up to 1,390 deg/s about its axle, two
    IMUs on it 0.14 and 0.11 m out, 0.1% of the sensor messages dropped: a real recording of
    such a wheel exited 2 ("numerically degenerate (Matrix is not positive definite)")."""
    return simulate_drive(DriveOptions(scenario="wheel", duration_s=60.0, seed=1))


def test_a_base_spinning_about_one_axis_gets_a_result_not_an_error(wheel):
    """The lever arm along the axle and the gyro's scales off it are not determined by a spin
    about one axis: the solve says so (partial, the axle's axis kept at the prior) instead of
    failing its factorisation; every other axis within its std."""
    rates = np.degrees(np.abs(wheel.base.stream.gyro).max())
    assert rates > 1000.0
    result = calibrate_streams(wheel.streams(), wheel.config())
    for mount in wheel.mounts:
        estimate = result.estimates[mount.name]
        assert estimate.status == "partial", (mount.name, estimate.warnings)
        assert estimate.translation_observable.tolist() == [False, True, True]
        error, std = lidar_error(wheel, result, mount.name)
        assert np.all(np.abs(error) < 4 * std), (mount.name, error / std)


def test_a_dropped_sample_does_not_lag_what_follows_it(wheel):
    """The sensor's samples are low-passed as a uniform series: each dropped message shifted
    what followed by a period, and a gravity turning at 3 Hz in the wheel's IMU left residuals
    of 2.7-3x the noise (inconsistent, the model "not explaining" a rigid wheel). The dropped
    samples are put back first: the residuals are at the noise."""
    assert any(np.diff(wheel.sensors[m.name].stream.t_ns).max() > 15e6 for m in wheel.mounts)
    result = calibrate_streams(wheel.streams(), wheel.config())
    for estimate in result.estimates.values():
        level = estimate.checks["residual_level"]
        assert level["pass"] and level["accel"] < 1.2 and level["gyro"] < 1.2, level


def test_the_residual_check_tests_the_residuals_of_the_fit_it_reports():
    """The check held the fit before the IMUs' own errors were taken in (5.4x the noise), the
    figure the final fit's windows (all under its 2x line): the check now tests the fit that is
    reported, the quantity the figure draws. Consumer lidar IMUs on an aggressive drive, whose
    own errors the final fit takes in, are ok within their std."""
    drive = simulate_drive(
        with_errors(DriveOptions(scenario="aggressive", seed=1, sensors=2), "consumer")
    )
    result = calibrate_streams(drive.streams(), drive.config())
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        level, r = estimate.checks["residual_level"], estimate.window_residuals
        used = [w for w in estimate.windows if w.selected]  # the figure's windows, in order
        assert [w.start_s for w in used] == pytest.approx(r[:, 0].tolist())
        length = np.array([w.end_s - w.start_s for w in used])  # each window's samples
        for column, key, expected in ((1, "gyro", "radps"), (2, "accel", "mps2")):
            rms = np.sqrt(np.average(r[:, column] ** 2, weights=length))
            # (a window's length weighs it to a grid sample: 1e-3 of its weight at most)
            assert rms / level[f"expected_{key}_{expected}"] == pytest.approx(level[key], rel=1e-4)
        assert estimate.status == "ok", estimate.warnings
        error, std = lidar_error(drive, result, mount.name)
        assert np.all(np.abs(error) < 4 * std)


def test_a_consumer_base_gyros_axis_errors_are_taken_in():
    """A consumer base IMU (its gyro's axes 0.5% and 0.4 deg off, drawn from the grade it
    declares): the lever arms' terms see them through the base's rates, where the sensor's
    relative gyro errors cannot take them. Estimated where the drive determines them, every
    sensor is ok and inside 3 std (left out, 3 of these 4 were inconsistent)."""
    drive = drive_with("mems-base")
    result = calibrate(drive)
    for mount in drive.mounts:
        assert result.estimates[mount.name].status == "ok"
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)
    notes = [n for estimate in result.estimates.values() for n in estimate.notes]
    assert any(n.startswith("base gyro axis errors estimated") for n in notes)


def test_a_base_gyros_yaw_scale_is_not_read_as_a_tilting_mount():
    """A consumer base whose gyro's axes read 0.5% off each (its other errors none): where the
    own errors' test does not take the scales in, the centripetal term they scale still looks
    like a mount leaning with the lateral force. The tilt is tested with them free: every
    sensor ok, rigid, inside 3 std (tested with them held, 2 of these 4 failed it)."""
    options = replace(
        with_errors(DriveOptions(scenario="aggressive", seed=4, sensors=4), "mems-base"),
        base_grade="ideal",  # (the config below declares consumer: the errors drawn are set here)
        base_model=replace(MEMS_LIDAR, scale_factor_std=0.005),
    )
    drive = simulate_drive(options)
    document = drive.config_document()
    document["base"]["grade"] = "consumer"
    result = calibrate_streams(drive.streams(), parse_config(document, "drive.config.yaml"))
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        assert estimate.status == "ok" and estimate.checks["rigid_mount"]["pass"]
        assert np.all(np.abs(normalized_errors(drive, result, mount.name)) < 3)
