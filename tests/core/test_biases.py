"""Rests and biases of one IMU (core/biases.py), streamed."""

from __future__ import annotations

import numpy as np

from imucal_cli.core.biases import BaseGyroBias, BiasTracker, rest_rate
from imucal_cli.types import GRAVITY_MPS2

RATE = 200.0
NOISE_A, NOISE_W = 0.02, 0.002


def _drive(bias_a: np.ndarray, bias_w: np.ndarray, seed: int = 0):
    """Rest 10 s, drive 10 s (turning, braking), rest 10 s: stamps, gyro, accel."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(30 * RATE)) / RATE
    moving = (t >= 10) & (t < 20)
    w = np.zeros((len(t), 3))
    w[moving, 2] = 0.3 * np.sin(2 * np.pi * 0.2 * (t[moving] - 10))
    f = np.tile([0.0, 0.0, GRAVITY_MPS2], (len(t), 1))
    f[moving, 0] = 2.0 * np.sin(2 * np.pi * 0.3 * (t[moving] - 10))
    gyro = w + bias_w + rng.normal(0, NOISE_W, w.shape)
    accel = f + bias_a + rng.normal(0, NOISE_A, f.shape)
    return (t * 1e9).astype(np.int64) + 10**18, gyro, accel


def _tracker(t, gyro, accel, step: int | None = None):
    tracker = BiasTracker(0.1, 0.02, 2.0, np.radians(0.1), np.radians(0.3))
    step = step or len(t)
    for a in range(0, len(t), step):
        tracker.add(t[a : a + step], gyro[a : a + step], accel[a : a + step])
    return tracker.report()


def test_a_bias_past_the_rest_tolerance_still_finds_the_rests_and_is_estimated():
    bias_a, bias_w = (
        np.array([0.0, 0.0, 0.5]),
        np.array([0.004, -0.002, 0.003]),
    )  # 0.5 m/s^2: five tolerances
    report = _tracker(*_drive(bias_a, bias_w))
    assert [(round(r.start_s), round(r.end_s)) for r in report.rest_periods] == [(0, 10), (20, 30)]
    n = report.rest_periods[-1].samples
    assert abs(report.accel_bias[2] - 0.5) < 4 * NOISE_A / np.sqrt(
        n
    )  # the gravity-parallel component
    assert np.all(np.abs(report.gyro_bias_final - bias_w) < 4 * NOISE_W / np.sqrt(n))
    assert not report.warnings


def test_streamed_in_pieces_equals_at_once():
    data = _drive(np.array([0.1, -0.2, 0.3]), np.zeros(3), seed=1)
    whole, pieces = _tracker(*data), _tracker(*data, step=333)
    assert [(r.start_s, r.end_s) for r in whole.rest_periods] == [
        (r.start_s, r.end_s) for r in pieces.rest_periods
    ]
    np.testing.assert_allclose(pieces.accel_bias, whole.accel_bias, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(pieces.gyro_bias_final, whole.gyro_bias_final, rtol=1e-9, atol=1e-15)


def test_no_rest_says_so():
    t, gyro, accel = _drive(np.zeros(3), np.zeros(3))
    gyro[:, 2] += 0.5  # always turning
    report = _tracker(t, gyro, accel)
    assert not report.rest_periods and report.warnings and np.all(report.gyro_bias_final == 0)


def test_many_small_batches_equal_one_batch_through_the_merges():
    """Hundreds of batches (the tracker merges its blocks every 256): every figure as from one
    batch, the rests' sample counts included (a merge that counted its blocks twice doubled
    them)."""
    data = _drive(np.array([0.1, -0.2, 0.3]), np.array([0.001, 0.0, -0.002]), seed=2)
    whole, pieces = _tracker(*data), _tracker(*data, step=7)
    assert [(r.start_s, r.end_s, r.samples) for r in whole.rest_periods] == [
        (r.start_s, r.end_s, r.samples) for r in pieces.rest_periods
    ]
    for name in (
        "accel_bias",
        "accel_noise_std",
        "gyro_bias_final",
        "gyro_bias_track_std",
        "gyro_bias_final_std",
    ):
        np.testing.assert_allclose(
            getattr(pieces, name), getattr(whole, name), rtol=1e-9, atol=1e-15, err_msg=name
        )


def test_memory_follows_the_samples_not_the_span_of_their_stamps():
    """A clock that jumps a year mid-log: the tracker keeps the blocks that hold samples (it
    used to keep every 0.1 s block of the span: 30 GiB for a year), and the rest before the
    jump is still found."""
    import tracemalloc

    t, gyro, accel = _drive(np.zeros(3), np.zeros(3), seed=3)
    t = t.copy()
    t[len(t) // 2 :] += 365 * 86400 * 10**9
    tracemalloc.start()
    try:
        report = _tracker(t, gyro, accel, step=500)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 << 20
    assert [round(r.start_s) for r in report.rest_periods][:1] == [0]


def _stop_and_go(seed: int, stops: int = 8):
    """Drive 20 s, rest 10 s, repeated: stamps, gyro, accel (200 Hz)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(30 * stops * RATE)) / RATE
    moving = (t % 30) < 20
    w = np.zeros((len(t), 3))
    w[moving, 2] = 0.3 * np.sin(2 * np.pi * 0.2 * t[moving])
    f = np.tile([0.0, 0.0, GRAVITY_MPS2], (len(t), 1))
    f[moving, 0] = 2.0 * np.sin(2 * np.pi * 0.3 * t[moving])
    gyro = w + np.array([0.002, -0.001, 0.003]) + rng.normal(0, NOISE_W, w.shape)
    accel = f + np.array([0.05, 0.0, 0.2]) + rng.normal(0, NOISE_A, f.shape)
    return (t * 1e9).astype(np.int64) + 10**18, gyro, accel


def test_blocks_judged_as_they_settle_give_what_judging_all_at_the_end_gives(monkeypatch):
    """The tracker judges and lets go of the blocks no sample can still change (memory flat in
    the log's length): with passes every few seconds, every rest and figure is what one pass
    over the whole log gives."""
    import imucal_cli.core.biases as biases

    data = _stop_and_go(seed=4)
    whole = _tracker(*data, step=50)  # (4 minutes: under one pass of the default)
    monkeypatch.setattr(biases, "JUDGE_BLOCKS", 150)
    monkeypatch.setattr(biases, "SETTLE_BLOCKS", 20)
    tracker = BiasTracker(0.1, 0.02, 2.0, np.radians(0.1), np.radians(0.3))
    held = []
    for a in range(0, len(data[0]), 50):
        tracker.add(*(x[a : a + 50] for x in data))
        held.append(len(tracker.blocks()[0]))
    passes = tracker.report()
    assert max(held) < 600 < len(data[0]) / RATE / 0.1  # blocks held, against blocks in the log
    assert len(whole.rest_periods) == 8
    assert [(r.start_s, r.end_s, r.samples) for r in passes.rest_periods] == [
        (r.start_s, r.end_s, r.samples) for r in whole.rest_periods
    ]
    for name in (
        "accel_bias",
        "accel_noise_std",
        "gyro_bias_final",
        "gyro_bias_track_std",
        "gyro_bias_final_std",
    ):
        np.testing.assert_allclose(
            getattr(passes, name), getattr(whole, name), rtol=1e-9, atol=1e-15, err_msg=name
        )


def test_the_accelerometer_bias_at_rest_is_said_to_be_its_part_along_gravity():
    """At one rest pose only the bias along gravity separates from the tilt: the report gives
    that number (|g + b| - g), and the biases document and table say so (they printed a
    3-vector whose horizontal parts are not the bias's, issue 32, item 3)."""
    bias_a = np.array([0.3, -0.2, 0.5])
    report = _tracker(*_drive(bias_a, np.zeros(3)))
    rest = report.rest_periods[-1]
    expected = float(np.linalg.norm(np.array([0.0, 0.0, GRAVITY_MPS2]) + bias_a) - GRAVITY_MPS2)
    assert abs(rest.accel_bias_along_gravity - expected) < 4 * NOISE_A / np.sqrt(rest.samples)


def test_biases_table_and_document_label_the_accelerometer_bias(tmp_path, short_drive):
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    write_document(tmp_path / "c.yaml", short_drive.config_document())
    runner = CliRunner()
    table = runner.invoke(
        app, ["biases", str(log), "-c", str(tmp_path / "c.yaml")], env={"COLUMNS": "200"}
    )
    assert "accel bias along g" in table.stdout and "calibrate's accel_bias_mps2" in table.stdout
    document = runner.invoke(app, ["biases", str(log), "-c", str(tmp_path / "c.yaml"), "--json"])
    import json

    for imu in json.loads(document.stdout)["imus"].values():
        assert "accel_bias_along_gravity_mps2" in imu and imu["accel_bias_resolved"].startswith(
            "along gravity only"
        )


def test_fewer_blocks_than_the_rest_test_looks_at_do_not_break_it():
    """Half a second of samples (5 blocks, fewer than the 11 the rest test averages over): no
    rest, no error (the fuzzer's damaged bag left so few at the end of a log: a traceback)."""
    t, gyro, accel = _drive(np.zeros(3), np.zeros(3))
    report = _tracker(t[:100], gyro[:100], accel[:100])
    assert not report.rest_periods and report.warnings


def test_the_base_gyro_bias_comes_from_the_rests_middles_not_their_settling_ends():
    """A noise-free town drive's base gyro reading (0.004, -0.006, 0.01) rad/s too much: the
    middles of its stops, 3 s off each end, give that bias on every axis to 1e-5 rad/s. With
    1 s off each end, the body still pitches on its suspension as it stops and drives off (the
    simulated bus's): its rates there are 1e-4 rad/s and more off the bias about a level axis,
    and its specific force turns with it, which keeps those rests out of the level axes."""
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(
        DriveOptions(scenario="urban", duration_s=120.0, seed=3, noise_scale=0.0, sensors=1)
    )
    base = drive.streams().base
    true_bias = np.array([0.004, -0.006, 0.01])
    gyro = base.gyro + true_bias
    tolerances = (0.1, 0.02, 8.0)
    found = rest_rate(base.t_ns, gyro, base.accel, *tolerances)
    assert found is not None
    assert np.abs(found - true_bias).max() < 1e-5
    short = BiasTracker(*tolerances, 0.0, 1.0, edge_s=1.0)
    short.add(base.t_ns, gyro, base.accel)
    rests = short.rests()
    assert rests
    for rest in rests:
        error = rest.gyro_mean - true_bias
        assert np.linalg.norm(error - (error @ rest.accel_up) * rest.accel_up) > 1e-4
        assert not rest.level


def _standing(bias: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A body that stands 40 s and kneels (pitches 1 deg in 4 s from 15 s) and leans (rolls
    0.5 deg in 3 s from 26 s) about a point 2 m behind and 1 m below its IMU, turns 1 rad
    about the vertical in 10 s (not a rest), and stands 30 s still: 100 Hz, noise-free, the
    gyro reading ``bias`` too much."""
    from scipy.spatial.transform import Rotation

    t = np.arange(0.0, 80.0, 0.01)

    def step(start: float, length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = np.clip((t - start) / length, 0.0, 1.0)
        inside = (u > 0) & (u < 1)
        s = 10 * u**3 - 15 * u**4 + 6 * u**5
        ds = np.where(inside, (30 * u**2 - 60 * u**3 + 30 * u**4) / length, 0.0)
        dds = np.where(inside, (60 * u - 180 * u**2 + 120 * u**3) / length**2, 0.0)
        return s, ds, dds

    size = np.array([np.radians(0.5), np.radians(1.0), 1.0])  # roll, pitch, yaw: rad
    steps = [step(26.0, 3.0), step(15.0, 4.0), step(42.0, 10.0)]
    # one axis turns at a time: rates and their derivatives in the body are those about it
    w = np.column_stack([a * s[1] for a, s in zip(size, steps, strict=True)])
    dw = np.column_stack([a * s[2] for a, s in zip(size, steps, strict=True)])
    euler = np.column_stack([a * s[0] for a, s in zip(size, steps, strict=True)])
    R_world_body = Rotation.from_euler("zyx", euler[:, ::-1])
    lever = np.array([2.0, 0.0, 1.0])  # the IMU from the point the body turns about
    f = R_world_body.inv().apply([0.0, 0.0, GRAVITY_MPS2])
    f += np.cross(dw, lever) + np.cross(w, np.cross(w, lever))
    return (t * 1e9).astype(np.int64), w + bias, f


def test_a_body_that_tilts_while_it_stands_is_not_taken_for_the_base_gyro_bias():
    """A stand in which the body kneels and leans (air suspension, a load), slowly enough to
    stay a rest, then a stand that holds still: the base gyro's bias comes back on every axis,
    about the level axes from the still one alone (the first's specific force shows its
    tilt). Its mean rate would take the tilt, 1.0 deg over 34 s, for 5e-4 rad/s of bias."""
    bias = np.array([3e-4, -2e-4, 1e-4])
    t_ns, gyro, accel = _standing(bias)
    tolerances = (0.1, 0.02, 8.0)
    tracker = BiasTracker(*tolerances, 0.0, 1.0, edge_s=3.0)
    tracker.add(t_ns, gyro, accel)
    tilting, still = tracker.rests()
    assert (tilting.level, still.level) == (False, True)
    assert np.abs(tilting.gyro_mean - bias)[:2].max() > 4e-4
    found = rest_rate(t_ns, gyro, accel, *tolerances)
    assert found is not None
    assert np.abs(found - bias)[:2].max() < 1e-7
    # the first stand's vertical rate holds its turn rate (5e-4 rad/s) times the angle (1 deg)
    # by which its mean vertical stands off the vertical at either end
    assert abs(found[2] - bias[2]) < 5e-4 * np.radians(1.0)


def test_a_block_whose_rests_all_tilt_keeps_the_level_axes_bias_it_had():
    """The base's bias followed block by block: a block whose one stand holds still gives the
    bias on every axis; a later block whose one stand kneels gives it about the vertical and
    keeps the level axes' from before, not zero and not the kneel's rate."""
    bias = np.array([3e-4, -2e-4, 1e-4])
    t_ns, gyro, accel = _standing(bias)
    tilting, still = t_ns < 42e9, t_ns > 52e9
    follow = BaseGyroBias(0.1, 0.02, 8.0)
    follow.update(t_ns[still], gyro[still], accel[still])
    assert follow.value is not None
    assert np.abs(follow.value - bias).max() < 1e-7
    follow.update(t_ns[tilting], gyro[tilting], accel[tilting])
    assert np.abs(follow.value - bias)[:2].max() < 1e-7
    assert abs(follow.value[2] - bias[2]) < 5e-4 * np.radians(1.0)
    alone = BaseGyroBias(0.1, 0.02, 8.0)
    alone.update(t_ns[tilting], gyro[tilting], accel[tilting])
    assert alone.value is not None
    assert np.abs(alone.value[:2]).max() < 1e-5  # (zero about the level axes: no still stand)
