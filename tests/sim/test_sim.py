"""The simulator: exact kinematics, the SPEC's sensor equations, noise models, scenarios."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.config import parse_config
from imucal_cli.sim import SCENARIOS, DriveOptions, make_scenario, simulate_drive
from imucal_cli.sim.imu import MEMS_LIDAR, ideal_imu, simulate_imu
from imucal_cli.sim.rig import OUSTER_T_IMU_LIDAR, WHEEL_MOUNTS
from imucal_cli.sim.trajectory import GRAVITY_W
from imucal_cli.types import Transform

# Central differences with step h have truncation error h^2/12 |x''''| (second derivative) and
# h^2/6 |x'''| (first derivative). With h = 1e-3 s and |x''''| below ~300 m/s^4 (heave bumps of
# 1.2 cm at 2 Hz: (4 pi)^4 * 0.012), that is < 3e-5 m/s^2; round-off adds ~eps*|p|/h^2 ~ 1e-7.
H = 1e-3
FD_TOL = 1e-4


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_specific_force_matches_finite_difference_of_world_position(scenario):
    trajectory = make_scenario(scenario, duration_s=30.0, seed=3)
    t = np.linspace(1.0, 29.0, 400)
    lever_B = np.array([4.35, -1.12, 2.95])  # a front-right-top lidar point
    H = 1e-3
    if scenario == "wheel":  # a point on the wheel: the second difference's truncation,
        # h^2/12 w^4 |r| = 2e-5 m/s^2 at 24 rad/s and 0.14 m, wants a shorter step
        lever_B, H = WHEEL_MOUNTS[0].T_base_imu.translation, 1e-4

    def point_world(times):
        s = trajectory.state(times)
        return s.p_world + s.R_world_base.apply(lever_B)

    a_world = (point_world(t + H) - 2.0 * point_world(t) + point_world(t - H)) / H**2
    state = trajectory.state(t)
    f_fd = state.R_world_base.inv().apply(a_world - GRAVITY_W)
    np.testing.assert_allclose(state.specific_force_at(lever_B), f_fd, atol=FD_TOL, rtol=0)


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_angular_velocity_and_acceleration_match_finite_differences(scenario):
    # Central differences with h = 1e-4 s: the truncation error h^2/6 |w''| is below 1e-7 rad/s
    # for bumps at 2 Hz (|w''| ~ (4 pi)^3 x peak bump angle ~ 30 rad/s^3), and h^2/6 |w'''|
    # below 1e-6 rad/s^2.
    H = 1e-4
    trajectory = make_scenario(scenario, duration_s=30.0, seed=4)
    t = np.linspace(1.0, 29.0, 400)
    state = trajectory.state(t)
    R_minus = trajectory.state(t - H).R_world_base
    R_plus = trajectory.state(t + H).R_world_base
    # R(t)^T R(t+h) ~ exp([w] h): central estimate in the body frame at t
    w_fd = (
        (state.R_world_base.inv() * R_plus).as_rotvec()
        - (state.R_world_base.inv() * R_minus).as_rotvec()
    ) / (2 * H)
    np.testing.assert_allclose(state.w_base, w_fd, atol=1e-6, rtol=0)
    dw_fd = (trajectory.state(t + H).w_base - trajectory.state(t - H).w_base) / (2 * H)
    np.testing.assert_allclose(state.dw_base, dw_fd, atol=1e-5, rtol=0)


def test_noise_free_sensor_satisfies_the_spec_equations(ideal_drive):
    """w_I = R_B_I^T w_B and f_I = R_B_I^T (f_B + dw_B x t + w_B x (w_B x t)), to 1e-9."""
    truth = ideal_drive.truth_document()
    base = ideal_drive.base
    base_state = ideal_drive.trajectory.state(base.true_time_s)
    np.testing.assert_allclose(base.stream.gyro, base_state.w_base, atol=1e-12)
    np.testing.assert_allclose(base.stream.accel, base_state.f_base, atol=1e-12)
    for name, imu in ideal_drive.sensors.items():
        T_base_imu = Transform.from_dict(truth["sensors"][name]["T_base_imu"])
        R, t = T_base_imu.rotation.as_matrix(), T_base_imu.translation
        s = ideal_drive.trajectory.state(imu.true_time_s)
        w_expected = s.w_base @ R  # rows: R^T w_B
        f_B = s.R_world_base.inv().apply(s.a_world - GRAVITY_W)
        f_expected = (f_B + np.cross(s.dw_base, t) + np.cross(s.w_base, np.cross(s.w_base, t))) @ R
        np.testing.assert_allclose(imu.stream.gyro, w_expected, atol=1e-9, rtol=0)
        np.testing.assert_allclose(imu.stream.accel, f_expected, atol=1e-9, rtol=0)
        # ideal sensors: zero bias, stamps are the true sample times (to the nanosecond)
        assert not np.any(imu.gyro_bias) and not np.any(imu.accel_bias)
        stamps_s = (imu.stream.t_ns - ideal_drive.options.t0_ns) * 1e-9
        assert np.max(np.abs(stamps_s - imu.true_time_s)) < 1e-9


def test_noise_free_sensor_accel_matches_differentiated_imu_position(ideal_drive):
    """Independent of the lever-arm formula: differentiate the IMU's own world position."""
    truth = ideal_drive.truth_document()
    for name, imu in ideal_drive.sensors.items():
        T_base_imu = Transform.from_dict(truth["sensors"][name]["T_base_imu"])
        t = imu.true_time_s[50:-50:37]

        def imu_world(times, lever=T_base_imu.translation):
            s = ideal_drive.trajectory.state(times)
            return s.p_world + s.R_world_base.apply(lever)

        a_world = (imu_world(t + H) - 2 * imu_world(t) + imu_world(t - H)) / H**2
        R_world_imu = ideal_drive.trajectory.state(t).R_world_base * T_base_imu.rotation
        f_fd = R_world_imu.inv().apply(a_world - GRAVITY_W)
        index = np.searchsorted(imu.true_time_s, t)
        np.testing.assert_allclose(imu.stream.accel[index], f_fd, atol=FD_TOL)


def test_noise_matches_the_error_model():
    """Per-sample noise std = density * sqrt(rate); checked to 5 standard errors."""
    trajectory = make_scenario("aggressive", duration_s=60.0, seed=9)
    model = MEMS_LIDAR.scaled(1.0)
    from dataclasses import replace

    model = replace(
        model,
        gyro_turn_on_bias_std=0.0,
        accel_turn_on_bias_std=0.0,
        gyro_bias_random_walk=0.0,
        accel_bias_random_walk=0.0,
        drop_fraction=0.0,
        jitter_s=0.0,
        gyro_lsb=0.0,
        accel_lsb=0.0,
    )
    T = Transform(Rotation.from_euler("z", 40, degrees=True), np.array([4.0, 1.0, 3.0]))
    imu = simulate_imu(trajectory, T, model, np.random.default_rng(0), 0, "imu")
    gyro, accel = ideal_imu(trajectory, T, imu.true_time_s)
    n = len(imu.stream)
    for measured, ideal, expected in (
        (imu.stream.gyro, gyro, model.gyro_noise_std()),
        (imu.stream.accel, accel, model.accel_noise_std()),
    ):
        std = np.std(measured - ideal, axis=0)
        assert np.all(np.abs(std / expected - 1.0) < 5.0 / np.sqrt(2 * n))
        assert np.all(np.abs(np.mean(measured - ideal, axis=0)) < 5.0 * expected / np.sqrt(n))


def test_time_offsets_shift_the_stamps():
    drive = simulate_drive(
        DriveOptions(
            scenario="aggressive",
            duration_s=10.0,
            seed=1,
            noise_scale=0.0,
            time_offsets_s=(0.042, -0.017),
        )
    )
    t0 = drive.options.t0_ns
    for (name, imu), offset in zip(drive.sensors.items(), (0.042, -0.017), strict=True):
        assert drive.time_offsets_s[name] == offset
        np.testing.assert_allclose(
            (imu.stream.t_ns - t0) * 1e-9 - imu.true_time_s, offset, atol=1e-9
        )
        assert np.all(imu.log_time_ns > t0 + (imu.true_time_s * 1e9).astype(np.int64))  # latency


def _speed(trajectory, t):
    return np.linalg.norm(trajectory.state(t).v_world, axis=1)


def _runs(mask, t):
    """(start, end) times of the runs where mask is true."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return [(t[a], t[b - 1]) for a, b in zip(edges[::2], edges[1::2], strict=True)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_urban_has_stops_and_right_angle_turns(seed):
    trajectory = make_scenario("urban", seed=seed)
    t = np.arange(0.0, trajectory.t_end_s, 0.01)
    stops = [(a, b) for a, b in _runs(_speed(trajectory, t) < 1e-3, t) if b - a >= 2.0]
    assert stops and stops[0][0] == 0.0  # starts at rest
    assert len(stops) >= 3 and all(b - a >= 4.9 for a, b in stops)
    state = trajectory.state(t)
    yaw = np.unwrap(Rotation.as_euler(state.R_world_base, "xyz")[:, 2])
    lateral = np.abs(np.linalg.norm(state.v_world, axis=1) * state.w_base[:, 2])
    assert lateral.max() < 4.5
    # heading changes by ~90 degrees in at least two places within 15 s
    turns = [abs(yaw[min(i + 1500, len(yaw) - 1)] - yaw[i]) for i in range(0, len(yaw), 100)]
    assert sum(1 for d in turns if 1.3 < d < 1.8) >= 2


def test_aggressive_never_stops_and_excites_all_axes():
    trajectory = make_scenario("aggressive", seed=0)
    t = np.arange(0.0, trajectory.t_end_s, 0.01)
    assert trajectory.t_end_s == 81.0
    assert _speed(trajectory, t).min() > 2.0
    w = trajectory.state(t).w_base
    assert np.all(np.std(w, axis=0) > [0.01, 0.01, 0.1])
    assert np.abs(trajectory.state(t).a_world[:, :2]).max() < 6.0


def test_highway_has_almost_no_yaw_excitation():
    trajectory = make_scenario("highway", seed=0)
    t = np.arange(0.0, trajectory.t_end_s, 0.01)
    assert _speed(trajectory, t).min() > 15.0
    assert np.abs(trajectory.state(t).w_base[:, 2]).max() < 0.02


def test_parking_reverses_at_full_lock_and_stops():
    trajectory = make_scenario("parking", seed=0)
    t = np.arange(0.0, trajectory.t_end_s, 0.01)
    state = trajectory.state(t)
    forward = np.einsum("ij,ij->i", state.v_world, state.R_world_base.apply([1.0, 0.0, 0.0]))
    assert forward.min() < -1.0 and forward.max() > 1.0
    curvature = np.abs(state.w_base[:, 2]) / np.maximum(np.abs(forward), 0.5)
    assert curvature.max() > 0.1  # radius under 10 m
    assert len([r for r in _runs(np.abs(forward) < 1e-3, t) if r[1] - r[0] >= 2.0]) >= 3


def test_truth_and_config_documents(short_drive):
    truth = short_drive.truth_document()
    config = parse_config(short_drive.config_document(), "sim.config.yaml")
    assert [s.name for s in config.sensors] == ["front_left_top", "front_right_top"]
    for sensor in config.sensors:
        t = truth["sensors"][sensor.name]
        T_base_imu = Transform.from_dict(t["T_base_imu"])
        T_base_lidar = Transform.from_dict(t["T_base_lidar"])
        np.testing.assert_allclose(
            (T_base_imu * sensor.T_imu_lidar).as_matrix(), T_base_lidar.as_matrix(), atol=1e-12
        )
        np.testing.assert_allclose(
            sensor.T_imu_lidar.as_matrix(), OUSTER_T_IMU_LIDAR.as_matrix(), atol=1e-12
        )
        # the CAD prior is off by a few degrees and centimetres, inside the search box
        angle = np.degrees(
            (sensor.prior_T_base_imu.rotation.inv() * T_base_imu.rotation).magnitude()
        )
        offset = np.abs(sensor.prior_T_base_imu.translation - T_base_imu.translation)
        assert 0.3 < angle < 12.0 and np.all(offset <= 0.1) and np.any(offset > 0.005)
        assert np.all(offset < sensor.translation_bound_m)
    pair = Transform.from_dict(truth["pairs"]["front_left_top/front_right_top"])
    left = Transform.from_dict(truth["sensors"]["front_left_top"]["T_base_lidar"])
    right = Transform.from_dict(truth["sensors"]["front_right_top"]["T_base_lidar"])
    np.testing.assert_allclose(pair.as_matrix(), (left.inverse() * right).as_matrix(), atol=1e-12)


def test_ouster_imu_to_lidar():
    """IMU at [6.253, -11.775, 7.645] mm in the sensor frame; lidar 180 deg about z, 36.18 mm up."""
    lidar_origin_in_imu = OUSTER_T_IMU_LIDAR.translation
    np.testing.assert_allclose(
        lidar_origin_in_imu, [-6.253e-3, 11.775e-3, 36.18e-3 - 7.645e-3], atol=1e-12
    )
    np.testing.assert_allclose(
        OUSTER_T_IMU_LIDAR.rotation.apply([1.0, 0, 0]), [-1.0, 0, 0], atol=1e-12
    )


def test_same_seed_same_drive():
    a = simulate_drive(DriveOptions(scenario="parking", duration_s=15.0, seed=3))
    b = simulate_drive(DriveOptions(scenario="parking", duration_s=15.0, seed=3))
    c = simulate_drive(DriveOptions(scenario="parking", duration_s=15.0, seed=4))
    assert np.array_equal(
        a.sensors["front_left_top"].stream.gyro, b.sensors["front_left_top"].stream.gyro
    )
    assert not np.array_equal(a.base.stream.accel[:100], c.base.stream.accel[:100])


def test_four_sensors_and_rates():
    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=5.0, sensors=4, lidar_rate_hz=200.0)
    )
    assert len(drive.sensors) == 4
    for imu in drive.sensors.values():
        assert abs(len(imu.stream) - 1000) < 10
    with pytest.raises(ValueError):
        simulate_drive(DriveOptions(sensors=5))


def test_writing_a_log_reports_its_progress_to_the_total(tmp_path, short_drive):
    from imucal_cli.reading import read_imu
    from imucal_cli.sim.writers import write_imu_log

    for fmt, name in (("mcap", "p.mcap"), ("rosbag1", "p.bag")):
        seen: list[tuple[int, int]] = []
        log = write_imu_log(
            tmp_path / name,
            fmt,
            short_drive.topics(),
            lambda count, total, seen=seen: seen.append((count, total)),
        )
        total = sum(len(d.stream) for d in short_drive.topics().values())
        assert seen[-1] == (total, total) and all(t == total for _, t in seen)
        assert (
            sum(len(r.stream) for r in read_imu(log, list(short_drive.topics())).values()) == total
        )


def test_a_drive_longer_than_a_piece_is_written_as_it_is_made_and_is_the_joined_drive(tmp_path):
    """simulate held the whole drive (about 1 GB a simulated hour; 4 h killed at 2.5 GB). A
    drive longer than PIECE_S is made and written piece by piece, the bias walks carried on:
    the log holds exactly the joined drive's samples, without a seam, and the truth file its
    biases."""
    import yaml
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.reading import read_imu
    from imucal_cli.sim.drive import PIECE_S

    duration = 2 * PIECE_S + 100.0
    options = DriveOptions(scenario="urban", duration_s=duration, seed=5, sensors=2)
    drive = simulate_drive(options)
    for imu in (drive.base, *drive.sensors.values()):
        assert np.all(np.diff(imu.stream.t_ns) > 0)
        steps = np.abs(np.diff(imu.gyro_bias, axis=0)).max()
        assert steps < 10 * imu_walk_step(imu)  # (no jump where two pieces meet)
    out = tmp_path / "long.mcap"
    argv = ["simulate", str(out), "--scenario", "urban", "--duration", str(duration)]
    made = CliRunner().invoke(app, [*argv, "--seed", "5", "--sensors", "2"])
    assert made.exit_code == 0, made.output
    read = read_imu(out, list(drive.topics()))
    for topic, data in drive.topics().items():
        np.testing.assert_array_equal(read[topic].stream.t_ns, data.stream.t_ns)
        np.testing.assert_array_equal(read[topic].stream.accel, data.stream.accel)
    truth = yaml.safe_load((tmp_path / "long.truth.yaml").read_text())
    np.testing.assert_allclose(
        truth["base"]["gyro_bias_radps"]["mean"], drive.base.gyro_bias.mean(axis=0), rtol=1e-9
    )
    assert truth["base"]["gyro_bias_radps"]["final"] == drive.base.gyro_bias[-1].tolist()


def imu_walk_step(imu):
    """The largest bias step a sample to the next holds within one piece (the walk's scale)."""
    return max(np.abs(np.diff(imu.gyro_bias[:1000], axis=0)).max(), 1e-15)
