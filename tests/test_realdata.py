"""Real IMU signals (BROAD, CC BY 4.0): rest detection and gyro bias at rest.

The dataset's ``movement`` flag marks the motion phases; its "with_breaks" trials rest for 10 s
three times within them (flagged as no movement too). At rest its gyro reads a stable bias of
about (+0.0035, +0.0021, -0.0040) rad/s in every trial (../shared/realdata/broad/SOURCE.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REALDATA

from imucal_cli.core.biases import BiasTracker
from imucal_cli.core.signals import true_runs
from imucal_cli.types import ImuStream

h5py = pytest.importorskip("h5py")
BROAD = REALDATA / "broad"
TRIALS = [
    "05_undisturbed_slow_rotation_with_breaks_B",
    "07_undisturbed_fast_rotation_B",
    "09_undisturbed_fast_rotation_with_breaks_B",
    "14_undisturbed_slow_translation_with_breaks_B",
    "18_undisturbed_fast_translation_with_breaks_B",
]
#: Boundary tolerance: the flag was set by hand around the motion; 0.5 s is 140 samples.
EDGE_S = 0.5


def load(trial: str):
    path = BROAD / f"{trial}.hdf5"
    if not path.exists():
        pytest.skip(
            f"the BROAD recording {trial} (a real IMU with motion capture, kept outside this "
            "repository) is not on this machine"
        )
    with h5py.File(path) as f:
        rate = float(f.attrs["sampling_rate"])
        gyro, accel = np.array(f["imu_gyr"]), np.array(f["imu_acc"])
        movement = np.array(f["movement"]).astype(bool).ravel()
    t_ns = np.round(np.arange(len(gyro)) / rate * 1e9).astype(np.int64)
    return ImuStream(t_ns, gyro, accel, "imu"), movement, rate


def estimate_biases(stream, *args):
    """The stream through a tracker, 10 s at a time (as a log is read)."""
    tracker = BiasTracker(*args)
    step = 10**10
    for start in range(int(stream.t_ns[0]), int(stream.t_ns[-1]) + 1, step):
        part = (stream.t_ns >= start) & (stream.t_ns < start + step)
        tracker.add(stream.t_ns[part], stream.gyro[part], stream.accel[part])
    return tracker.report()


@pytest.mark.parametrize("trial", TRIALS)
def test_rest_periods_match_the_movement_flag(trial):
    stream, movement, rate = load(trial)
    report = estimate_biases(stream, 0.1, 0.02, 2.0, np.radians(0.1), np.radians(0.3))
    flagged = [(a / rate, (b - 1) / rate) for a, b in true_runs(~movement)]
    found = [(r.start_s, r.end_s) for r in report.rest_periods]
    assert len(found) == len(flagged)
    expected_breaks = 3 if "with_breaks" in trial else 0
    assert len(flagged) == 2 + expected_breaks
    for (fa, fb), (ra, rb) in zip(flagged, found, strict=True):
        assert abs(fa - ra) < EDGE_S and abs(fb - rb) < EDGE_S


@pytest.mark.parametrize("trial", TRIALS)
def test_gyro_bias_at_rest_matches_the_stable_bias(trial):
    stream, movement, _ = load(trial)
    report = estimate_biases(stream, 0.1, 0.02, 2.0, np.radians(0.1), np.radians(0.3))
    reference = stream.gyro[~movement].mean(axis=0)  # the dataset's own rest samples
    np.testing.assert_allclose(
        reference, [0.0035, 0.0021, -0.0040], atol=4e-4
    )  # SOURCE.md's figure
    per_sample_std = stream.gyro[~movement].std(axis=0)
    for rest in report.rest_periods:
        n = rest.samples
        # the mean of each rest agrees with the reference to its standard error plus the slow
        # drift the dataset shows between rests (<= 3e-4 rad/s across its trials)
        assert np.all(np.abs(rest.gyro_mean - reference) < 4 * per_sample_std / np.sqrt(n) + 3e-4)
    assert np.all(np.abs(report.gyro_bias_initial - reference) < 3e-4)


COMMA = REALDATA / "comma2k19_example"


def test_real_highway_drive_is_reported_unobservable():
    """comma2k19: 60 s of a car on a highway, phone IMU. Its real motion drives a virtual lidar
    IMU made through the SPEC's equations (a front-left-top mount, MEMS noise and biases); with
    that little excitation no window reaches the rotation threshold, so the answer is
    'unobservable' with the prior, never a confident wrong extrinsic."""
    from scipy.interpolate import make_interp_spline

    from imucal_cli.api import DriveStreams, calibrate_streams
    from imucal_cli.config import parse_config
    from imucal_cli.core.so3 import skew_squared
    from imucal_cli.sim.rig import DEFAULT_MOUNTS, cad_prior

    if not (COMMA / "processed_log_IMU_gyro_t.npy").exists():
        pytest.skip(
            "the comma2k19 example drive (a real car's IMU, kept outside this repository) is not "
            "on this machine"
        )
    t = np.load(COMMA / "processed_log_IMU_gyro_t.npy")
    device_to_base = np.diag([1.0, -1.0, -1.0])  # [forward, right, down] -> [forward, left, up]
    w_B = np.load(COMMA / "processed_log_IMU_gyro_value.npy") @ device_to_base
    f_B = np.load(COMMA / "processed_log_IMU_accelerometer_value.npy") @ device_to_base
    dw_B = make_interp_spline(t - t[0], w_B, k=3)(t - t[0], 1)
    mount = DEFAULT_MOUNTS[0]
    R, lever = mount.T_base_imu.rotation.as_matrix(), mount.T_base_imu.translation
    rng = np.random.default_rng(0)
    rate = 1.0 / np.median(np.diff(t))
    f_at = f_B + np.cross(dw_B, lever) + np.einsum("nij,j->ni", skew_squared(w_B), lever)
    w_I = (
        w_B @ R
        + rng.normal(0, np.radians(0.015) * np.sqrt(rate), w_B.shape)
        + np.radians(0.2) * rng.normal(size=3)
    )
    f_I = (
        f_at @ R
        + rng.normal(0, 230e-6 * 9.80665 * np.sqrt(rate), f_B.shape)
        + 0.05 * rng.normal(size=3)
    )
    t_ns = np.round(t * 1e9).astype(np.int64)
    prior = cad_prior(mount.T_base_imu, rng)
    config = parse_config(
        {
            "base": {"topic": "/imu"},
            "sensors": {
                mount.name: {
                    "imu_topic": "/lidar/imu",
                    "T_imu_lidar": mount.T_imu_lidar.to_dict(),
                    "prior_T_base_imu": prior.to_dict(),
                }
            },
        },
        "comma.yaml",
    )
    streams = DriveStreams(
        ImuStream(t_ns, w_B, f_B), {mount.name: ImuStream(t_ns, w_I, f_I)}, int(t_ns[0])
    )
    estimate = calibrate_streams(streams, config).estimates[mount.name]
    assert estimate.status == "unobservable"
    assert np.array_equal(estimate.T_base_imu.as_matrix(), prior.as_matrix())
    assert estimate.windows and all(w.rotation_std_deg > 1.0 for w in estimate.windows)
