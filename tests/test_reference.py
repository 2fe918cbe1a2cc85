"""The fast estimator against a slow, plain one written from the paper's equations.

The reference works on the raw samples: every IMU interpolated (a cubic spline) onto one 100 Hz
grid,
the same zero-phase low-pass (``scipy.signal.filtfilt``) on every term of the equations (the
products ``[w]x^2`` too, as the method requires), the angular acceleration the
spline's derivative; the rotation from the gyros by Kabsch (eq. 10, centred
per drive: a constant relative gyro bias drops out), then lever arm and accelerometer bias by
linear least squares of eq. 11 (``R f_I - f_B = ([w]x^2 + [dw]x) t + R b_a``). No windows, no
moments, no bias drift: on a drive with constant biases it must agree with the fast one.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.signal import butter, filtfilt
from scipy.spatial.transform import Rotation

from imucal_cli.api import calibrate_streams
from imucal_cli.core.so3 import skew
from imucal_cli.sim import DriveOptions, simulate_drive

RATE = 100.0


def reference(base, sensor, t0_ns):
    """(R_base_imu, t_base_imu) from the raw streams, as the module's text says."""
    start = max(base.t_ns[0], sensor.t_ns[0]) + 2 * 10**9
    end = min(base.t_ns[-1], sensor.t_ns[-1]) - 2 * 10**9
    grid = np.arange(start, end, int(1e9 / RATE))
    b, a = butter(2, 5.0 / (RATE / 2))

    def on_grid(stream, values):
        return CubicSpline((stream.t_ns - t0_ns) * 1e-9, values)((grid - t0_ns) * 1e-9)

    def low(x):
        return filtfilt(b, a, x.reshape(len(x), -1), axis=0).reshape(x.shape)

    gyro = CubicSpline((base.t_ns - t0_ns) * 1e-9, base.gyro)
    w_raw, dw_raw = gyro((grid - t0_ns) * 1e-9), gyro((grid - t0_ns) * 1e-9, 1)
    A = low(skew(w_raw) @ skew(w_raw) + skew(dw_raw))  # (n, 3, 3)
    w_b, f_b = low(w_raw), low(on_grid(base, base.accel))
    w_i, f_i = low(on_grid(sensor, sensor.gyro)), low(on_grid(sensor, sensor.accel))
    edge = int(2 * RATE)  # the filter's ends
    w_b, f_b, w_i, f_i, A = (x[edge:-edge] for x in (w_b, f_b, w_i, f_i, A))
    R, _ = Rotation.align_vectors(w_b - w_b.mean(axis=0), w_i - w_i.mean(axis=0))  # w_B = R w_I
    lhs = np.concatenate([A, np.broadcast_to(np.eye(3), A.shape)], axis=2).reshape(-1, 6)
    rhs = (R.apply(f_i) - f_b).reshape(-1)
    solution = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return R, solution[:3]


@pytest.mark.parametrize("noise_scale", [0.0, 1.0])
def test_fast_estimator_agrees_with_the_plain_reference(noise_scale):
    options = DriveOptions(
        scenario="aggressive",
        duration_s=81.0,
        seed=4,
        sensors=2,
        noise_scale=noise_scale,
        time_offsets_s=(0.0,),
    )
    drive = simulate_drive(options)
    streams, config = drive.streams(), drive.config()
    config = config.__class__(
        **{
            **config.__dict__,
            "calibration": config.calibration.__class__(resample_hz=100.0, max_time_offset_s=0.0),
        }
    )
    result = calibrate_streams(streams, config)
    for mount in drive.mounts:
        fast = result.estimates[mount.name]
        R, t = reference(streams.base, streams.sensors[mount.name], streams.t0_ns)
        d_rot = np.degrees(np.linalg.norm((fast.T_base_imu.rotation * R.inv()).as_rotvec()))
        d_t = np.abs(fast.T_base_imu.translation - t)
        if noise_scale == 0.0:
            # both exact up to interpolation (measured: 1e-7 m; central differences instead
            # of the spline's derivative put the reference 3-7 mm off on this drive)
            assert d_rot < 1e-4 and d_t.max() < 1e-5, (mount.name, d_rot, d_t)
        else:
            # the same data: within the fast estimator's std (the reference, unweighted and
            # blind to bias drift, is no better than it)
            std_rot = float(np.linalg.norm(fast.rotation_std_deg))
            assert d_rot < 4 * std_rot + 2e-3, (mount.name, d_rot, std_rot)
            assert np.all(d_t < 4 * fast.translation_std_m + 1e-3), (
                mount.name,
                d_t,
                fast.translation_std_m,
            )
