"""Each window's observability (paper eqs. 18-19)."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.api import calibrate_streams
from imucal_cli.config import parse_config
from imucal_cli.sim import DriveOptions, simulate_drive


def _vec(A):
    """Column-major vec of a stack of 3x3 matrices: (n, 3, 3) -> (n, 9),
    ``A t = (t^T x I) vec A``."""
    return A.transpose(0, 2, 1).reshape(len(A), 9)


def test_planar_motion_leaves_height_unobservable():
    """A rigid body turning only about z on a flat, smooth yard: [w]x^2 and [dw]x have no z
    column, so the lever arm's height is not observable: status partial, z kept at the prior."""
    from imucal_cli.sim.scenarios import VehicleDynamics

    flat = VehicleDynamics(
        roll_per_lateral_accel=0.0,
        pitch_per_longitudinal_accel=0.0,
        bump_roll_rad=0.0,
        bump_pitch_rad=0.0,
        bump_heave_m=0.0,
        max_grade=0.0,
    )
    drive = simulate_drive(DriveOptions(scenario="parking", seed=3, dynamics=flat))
    result = calibrate_streams(drive.streams(), drive.config())
    config = parse_config(drive.config_document(), "sim.config.yaml")
    for sensor in config.sensors:
        estimate = result.estimates[sensor.name]
        assert estimate.status == "partial"
        assert estimate.translation_observable.tolist() == [True, True, False]
        assert estimate.T_base_imu.translation[2] == sensor.prior_T_base_imu.translation[2]
        # the reported z std is the search box's, and the true height is inside it
        mount = next(m for m in drive.mounts if m.name == sensor.name)
        assert estimate.translation_std_m[2] == pytest.approx(
            sensor.translation_bound_m / np.sqrt(3)
        )
        assert (
            abs(estimate.T_base_imu.translation[2] - mount.T_base_imu.translation[2])
            < sensor.translation_bound_m
        )
        # x and y are still found
        assert np.all(
            np.abs(estimate.T_base_imu.translation[:2] - mount.T_base_imu.translation[:2])
            < 4 * estimate.translation_std_m[:2]
        )


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
    return float(np.linalg.svd(rotation, compute_uv=False)[-1]), _std_from_information(
        information(A, accel_noise_std)
    )


def test_window_information_from_moments_equals_the_sample_sums():
    """Segments reduced to moments report the same Fisher information as the sample sums."""
    from imucal_cli.core.segments import window_infos_from_moments

    rng = np.random.default_rng(0)
    n = 500
    w, f, A = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3, 3))
    lever = np.array([4.0, 1.0, 3.0])
    ones, u = np.ones((n, 1)), np.linspace(0, 1, n)[:, None]
    x_g = np.hstack(
        [rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), w, rng.normal(size=(n, 3)), ones, u]
    )  # [w_I, f_I, w_B, dw_B, 1, u]
    q = rng.normal(size=(n, 4))  # the tilt terms
    x_a = np.hstack(
        [
            rng.normal(size=(n, 3)),
            f,
            rng.normal(size=(n, 3)),
            _vec(A),
            _vec(rng.normal(size=(n, 3, 3))),
            q,
            ones,
            u,
        ]
    )
    sigma_min, t_std = _plain_window_info(w, f, A, lever, 0.01, 0.02)
    (c,) = window_infos_from_moments(
        [(0.0, 10.0, True)],
        np.array([n]),
        (x_g.T @ x_g)[None],
        (x_a.T @ x_a)[None],
        lever,
        0.01,
        0.02,
        1.0,
        0.3,
    )
    assert c.min_singular_value == pytest.approx(sigma_min, rel=1e-9)
    np.testing.assert_allclose(c.translation_std_m, t_std, rtol=1e-9)
    assert c.selected == (np.degrees(1.0 / np.sqrt(sigma_min)) < 1.0)


def test_segments_table_gives_the_unit_of_the_min_singular_value(tmp_path, short_drive):
    """The rotation Fisher information's smallest singular value is in 1/rad^2: the table says
    so (it had no unit, issue 32, item 9)."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    write_document(tmp_path / "c.yaml", short_drive.config_document())
    result = CliRunner().invoke(
        app, ["segments", str(log), "-c", str(tmp_path / "c.yaml")], env={"COLUMNS": "200"}
    )
    assert result.exit_code == 0, result.output
    assert "min singular value 1/rad^2" in result.stdout


def test_a_short_gap_is_bridged_and_a_long_one_is_said_in_the_table(tmp_path):
    """Three dropped messages in a row (a 20 ms step at 200 Hz) cost a whole 10 s window (over
    3 periods, the calibrator's gap, where inspect reported none); a gap is now what inspect
    calls one (over 5 median periods, :data:`~imucal_cli.types.GAP_PERIODS`), and segments'
    table says why a window was not used (issue 32, item 5)."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import TopicData, write_imu_log
    from imucal_cli.types import ImuStream

    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=40.0, seed=9, lidar_rate_hz=200.0)
    )
    topics = drive.topics()
    sensor = list(topics)[1]
    data = topics[sensor]

    def without(seconds_from: float, count: int) -> dict:
        t = data.stream.t_ns
        at = int(np.searchsorted(t, t[0] + int(seconds_from * 1e9)))
        keep = np.ones(len(t), dtype=bool)
        keep[at : at + count] = False
        s = data.stream
        log_ns = data.log_time_ns[keep] if data.log_time_ns is not None else None
        return {
            **topics,
            sensor: TopicData(
                ImuStream(s.t_ns[keep], s.gyro[keep], s.accel[keep], s.frame_id), log_ns
            ),
        }

    write_document(tmp_path / "c.yaml", drive.config_document())
    runner = CliRunner()
    documents = {}
    for name, changed in (
        ("intact", topics),
        ("short", without(17.0, 3)),
        ("long", without(17.0, 40)),
    ):
        log = write_imu_log(tmp_path / f"{name}.mcap", "mcap", changed)
        result = runner.invoke(
            app, ["segments", str(log), "-c", str(tmp_path / "c.yaml"), "--json"]
        )
        assert result.exit_code == 0, result.output
        import json

        documents[name] = json.loads(result.stdout)["sensors"]
        if name == "long":
            table = runner.invoke(
                app, ["segments", str(log), "-c", str(tmp_path / "c.yaml")], env={"COLUMNS": "220"}
            )
            assert "no: gap in the data" in table.stdout
    gone = next(
        n for n, s in drive.config_document()["sensors"].items() if s["imu_topic"] == sensor
    )
    intact, short, long = (documents[k][gone]["windows"] for k in ("intact", "short", "long"))
    assert [w["selected"] for w in short] == [
        w["selected"] for w in intact
    ]  # three dropped messages bridged
    assert not any(w.get("gap") for w in short)
    assert sum(bool(w.get("gap")) for w in long) == 1  # 40 messages (200 ms): a gap, one window


def test_each_window_says_the_drive_s_excitation_there():
    """A window's excitation (the report's excitation figure) is the base IMU's rate RMS and
    its specific force's std about the window's mean: the same as the raw samples' over the
    window, to the parts in 10^4 by which the resampled, low-passed signals of the moments
    differ from them (the raw gyro's white noise is 2.6e-3 rad/s against 0.25 rad/s)."""
    from conftest import SAMPLE_DATA

    from imucal_cli.api import calibrate
    from imucal_cli.reading import read_imu

    log = SAMPLE_DATA / "aggressive.mcap"
    cal = calibrate(log, SAMPLE_DATA / "aggressive.config.yaml")
    stream = read_imu(log, [cal.config.base.topic])[cal.config.base.topic].stream
    t = (stream.t_ns - cal.t_ref_ns) * 1e-9
    for name, estimate in cal.estimates.items():
        assert estimate.windows, name
        for w in estimate.windows:
            inside = (t >= w.start_s) & (t < w.end_s)
            rms = np.sqrt((stream.gyro[inside] ** 2).sum(axis=1).mean())
            spread = np.sqrt(stream.accel[inside].var(axis=0).sum())
            assert w.rate_rms_radps == pytest.approx(rms, rel=1e-3)
            assert w.accel_std_mps2 == pytest.approx(spread, rel=1e-3)
