"""Per-IMU biases without any other sensor (paper section IV-C, eqs. 2-9).

- Gravity alignment from the first rest (Pedley's tilt, paper ref. [19]: roll and pitch from the
  accelerometer).
- Madgwick orientation (eqs. 2-4): gyro propagation corrected by gradient descent towards the
  accelerometer's gravity direction.
- Rest detection (eq. 5): ``|R_WI^T g - f| <= accel_tolerance`` plus ``|w| <= gyro_tolerance``,
  held for at least ``min_duration_s`` (on a 0.1 s moving average, so single noisy samples do not
  break a rest). Bias statistics use each rest without its first and last
  :data:`REST_EDGE_S` seconds, where the vehicle is settling or creeping off.
- Accelerometer bias and noise at each rest (eq. 6). At one rest pose only the gravity-parallel
  component of the bias separates from tilt (the tilt absorbs the rest), so the bias reported
  here is that component; ``calibrate`` gives the full vector relative to the base IMU.
- Gyro bias (eqs. 7-9): initialised at the first rest, tracked by a Kalman filter with random-walk
  process noise ``Q`` and measurements at rest (``y = w``, ``H = I``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.signals import white_noise_std
from imucal_cli.types import GRAVITY_MPS2, ImuStream

#: Seconds dropped at each end of a rest before averaging (settling, creeping off).
REST_EDGE_S = 1.0


@dataclass(frozen=True)
class RestPeriod:
    start_index: int
    end_index: int  # exclusive
    start_s: float  # seconds from the stream's first sample
    end_s: float
    accel_bias: np.ndarray  # (3,) gravity-parallel component, m/s^2
    accel_noise_std: np.ndarray  # (3,) m/s^2
    gyro_mean: np.ndarray  # (3,) rad/s


@dataclass(frozen=True)
class BiasReport:
    """What one IMU alone says about its biases."""

    rest_periods: list[RestPeriod]
    accel_bias: np.ndarray  # (3,) from the last rest (eq. 6 keeps it until the next one)
    accel_noise_std: np.ndarray  # (3,)
    gyro_bias_initial: np.ndarray  # (3,) eq. 7: the mean of the first rest (zero without one)
    gyro_bias_final: np.ndarray  # (3,)
    gyro_bias_track_std: np.ndarray  # (3,) spread of the tracked bias over the log
    gyro_bias_final_std: np.ndarray  # (3,) sqrt(diag P) at the end
    gyro_bias_track: np.ndarray  # (N, 3)
    gyro_bias_track_std_series: np.ndarray  # (N, 3) sqrt(diag P) over time
    rest_mask: np.ndarray  # (N,) bool


def tilt_quaternion(accel: np.ndarray) -> np.ndarray:
    """Pedley's tilt (roll, pitch) from a mean specific force, as a quaternion [w, x, y, z]
    of ``R_W_I`` with zero yaw."""
    ax, ay, az = accel
    roll = math.atan2(ay, az)
    pitch = math.atan2(-ax, math.hypot(ay, az))
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([cr * cp, sr * cp, cr * sp, -sr * sp])


def madgwick_gravity(
    t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, q0: np.ndarray, beta: float = 0.05
) -> np.ndarray:
    """Madgwick IMU filter (eqs. 2-4); returns gravity's direction in the IMU frame per sample
    (unit vectors, the third row of ``R_W_I``), i.e. ``R_W_I^T e_z``."""
    n = len(t_s)
    out = np.empty((n, 3))
    q0w, q1, q2, q3 = (float(v) for v in q0)
    dts = np.diff(t_s, prepend=t_s[0])
    for k in range(n):
        gx, gy, gz = gyro[k]
        ax, ay, az = accel[k]
        dt = dts[k]
        # rate of change from the gyro (eq. 2-3)
        qd0 = 0.5 * (-q1 * gx - q2 * gy - q3 * gz)
        qd1 = 0.5 * (q0w * gx + q2 * gz - q3 * gy)
        qd2 = 0.5 * (q0w * gy - q1 * gz + q3 * gx)
        qd3 = 0.5 * (q0w * gz + q1 * gy - q2 * gx)
        norm_a = math.sqrt(ax * ax + ay * ay + az * az)
        if norm_a > 0:
            ax, ay, az = ax / norm_a, ay / norm_a, az / norm_a
            # gradient of |R^T e_z - a| (eq. 4)
            f1 = 2 * (q1 * q3 - q0w * q2) - ax
            f2 = 2 * (q0w * q1 + q2 * q3) - ay
            f3 = 2 * (0.5 - q1 * q1 - q2 * q2) - az
            s0 = -2 * q2 * f1 + 2 * q1 * f2
            s1 = 2 * q3 * f1 + 2 * q0w * f2 - 4 * q1 * f3
            s2 = -2 * q0w * f1 + 2 * q3 * f2 - 4 * q2 * f3
            s3 = 2 * q1 * f1 + 2 * q2 * f2
            norm_s = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
            if norm_s > 0:
                qd0 -= beta * s0 / norm_s
                qd1 -= beta * s1 / norm_s
                qd2 -= beta * s2 / norm_s
                qd3 -= beta * s3 / norm_s
        q0w += qd0 * dt
        q1 += qd1 * dt
        q2 += qd2 * dt
        q3 += qd3 * dt
        norm_q = math.sqrt(q0w * q0w + q1 * q1 + q2 * q2 + q3 * q3)
        q0w, q1, q2, q3 = q0w / norm_q, q1 / norm_q, q2 / norm_q, q3 / norm_q
        out[k, 0] = 2 * (q1 * q3 - q0w * q2)
        out[k, 1] = 2 * (q0w * q1 + q2 * q3)
        out[k, 2] = 1 - 2 * (q1 * q1 + q2 * q2)
    return out


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return x
    kernel = np.ones(n) / n
    padded = np.pad(x, ((n // 2, n - 1 - n // 2), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(x.shape[1])], axis=1)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def detect_rest(
    t_s: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    accel_tolerance: float,
    gyro_tolerance: float,
    min_duration_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Rest mask (eq. 5 plus the gyro check) and the Madgwick gravity direction per sample."""
    rate = 1.0 / float(np.median(np.diff(t_s)))
    smooth = max(1, int(round(0.1 * rate)))
    accel_s = _moving_average(accel, smooth)
    gyro_s = _moving_average(gyro, smooth)
    # gravity alignment from the quietest second at the start (Pedley tilt)
    head = accel_s[: max(2, int(rate))].mean(axis=0)
    gravity_dir = madgwick_gravity(t_s, gyro, accel, tilt_quaternion(head))
    predicted = gravity_dir * GRAVITY_MPS2
    still = (np.linalg.norm(predicted - accel_s, axis=1) <= accel_tolerance) & (
        np.linalg.norm(gyro_s, axis=1) <= gyro_tolerance
    )
    mask = np.zeros(len(t_s), dtype=bool)
    for a, b in _runs(still):
        if t_s[b - 1] - t_s[a] >= min_duration_s:
            mask[a:b] = True
    return mask, gravity_dir


def estimate_biases(
    stream: ImuStream,
    accel_tolerance: float,
    gyro_tolerance: float,
    min_duration_s: float,
    process_noise: float,
    initial_std: float,
) -> BiasReport:
    """Rest periods, accelerometer bias and noise, and the gyro bias track of one IMU.

    ``process_noise`` is the gyro bias random walk (rad/s/sqrt(s)); ``initial_std`` is ``P0``'s
    standard deviation (rad/s).
    """
    t_s = (stream.t_ns - stream.t_ns[0]).astype(np.float64) * 1e-9
    gyro, accel = stream.gyro, stream.accel
    mask, gravity_dir = detect_rest(t_s, gyro, accel, accel_tolerance, gyro_tolerance, min_duration_s)
    rests: list[RestPeriod] = []
    for a, b in _runs(mask):
        inner = (t_s[a:b] >= t_s[a] + REST_EDGE_S) & (t_s[a:b] <= t_s[b - 1] - REST_EDGE_S)
        if np.count_nonzero(inner) < 10:
            inner[:] = True
        mask[a:b] = inner
        up = gravity_dir[a:b][inner].mean(axis=0)
        up /= np.linalg.norm(up)
        f = accel[a:b][inner]
        parallel = float(np.mean(f @ up)) - GRAVITY_MPS2  # eq. 6, along gravity
        rests.append(
            RestPeriod(
                start_index=a,
                end_index=b,
                start_s=float(t_s[a]),
                end_s=float(t_s[b - 1]),
                accel_bias=parallel * up,
                accel_noise_std=np.std(f, axis=0),
                gyro_mean=np.mean(gyro[a:b][inner], axis=0),
            )
        )

    noise = white_noise_std(gyro)
    measurement_var = np.maximum(noise**2, 1e-12)
    n = len(t_s)
    x = rests[0].gyro_mean.copy() if rests else np.zeros(3)  # eq. 7
    x_initial = x.copy()
    P = np.full(3, initial_std**2)
    track = np.empty((n, 3))
    track_std = np.empty((n, 3))
    dts = np.diff(t_s, prepend=t_s[0])
    q = process_noise**2
    for k in range(n):  # eqs. 8-9, per axis (H = I, diagonal Q and noise)
        P = P + q * dts[k]
        if mask[k]:
            K = P / (P + measurement_var)
            x = x + K * (gyro[k] - x)
            P = (1.0 - K) * P
        track[k] = x
        track_std[k] = np.sqrt(P)
    last = rests[-1] if rests else None
    return BiasReport(
        rest_periods=rests,
        accel_bias=last.accel_bias if last else np.zeros(3),
        accel_noise_std=last.accel_noise_std if last else white_noise_std(accel),
        gyro_bias_initial=x_initial,
        gyro_bias_final=track[-1].copy(),
        gyro_bias_track_std=np.std(track, axis=0),
        gyro_bias_final_std=track_std[-1].copy(),
        gyro_bias_track=track,
        gyro_bias_track_std_series=track_std,
        rest_mask=mask,
    )
