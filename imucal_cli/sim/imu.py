"""IMU measurement models: ideal kinematics plus noise, biases and timing errors."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imucal_cli.sim.trajectory import Trajectory
from imucal_cli.types import ImuStream, Transform

DEG = np.pi / 180.0
MICRO_G = 9.80665e-6


@dataclass(frozen=True)
class ImuErrorModel:
    """Error model of one IMU.

    Noise densities are one-sided white-noise densities: the per-sample standard deviation at
    rate ``f`` is ``density * sqrt(f)``. Biases are a turn-on constant drawn once plus a random
    walk (``density * sqrt(dt)`` per step).
    """

    gyro_noise_density: float  # rad/s/sqrt(Hz)
    accel_noise_density: float  # m/s^2/sqrt(Hz)
    gyro_turn_on_bias_std: float  # rad/s
    accel_turn_on_bias_std: float  # m/s^2
    gyro_bias_random_walk: float  # rad/s/sqrt(s)
    accel_bias_random_walk: float  # m/s^2/sqrt(s)
    rate_hz: float = 100.0
    time_offset_s: float = 0.0  # stamp minus true measurement time
    jitter_s: float = 0.0  # white stamp noise (std)
    drop_fraction: float = 0.0  # messages lost at random
    latency_s: float = 0.002  # true time to log (receive) time
    gyro_lsb: float = 0.0  # output resolution (rad/s); 0: none
    accel_lsb: float = 0.0  # output resolution (m/s^2); 0: none
    float32_output: bool = False  # the driver publishes single-precision values

    def scaled(self, noise_scale: float) -> ImuErrorModel:
        """Noise, biases, jitter and drop rate multiplied by ``noise_scale`` (0: an ideal sensor)."""
        return replace(
            self,
            gyro_noise_density=self.gyro_noise_density * noise_scale,
            accel_noise_density=self.accel_noise_density * noise_scale,
            gyro_turn_on_bias_std=self.gyro_turn_on_bias_std * noise_scale,
            accel_turn_on_bias_std=self.accel_turn_on_bias_std * noise_scale,
            gyro_bias_random_walk=self.gyro_bias_random_walk * noise_scale,
            accel_bias_random_walk=self.accel_bias_random_walk * noise_scale,
            jitter_s=self.jitter_s * noise_scale,
            drop_fraction=min(1.0, self.drop_fraction * noise_scale),
            gyro_lsb=self.gyro_lsb if noise_scale > 0 else 0.0,
            accel_lsb=self.accel_lsb if noise_scale > 0 else 0.0,
            float32_output=self.float32_output and noise_scale > 0,
        )

    def gyro_noise_std(self) -> float:
        """Per-sample gyro noise standard deviation (rad/s)."""
        return self.gyro_noise_density * np.sqrt(self.rate_hz)

    def accel_noise_std(self) -> float:
        """Per-sample accelerometer noise standard deviation (m/s^2)."""
        return self.accel_noise_density * np.sqrt(self.rate_hz)


#: A tactical-grade GNSS/INS IMU (fibre-optic gyro class), as the base IMU.
TACTICAL_BASE = ImuErrorModel(
    gyro_noise_density=0.002 * DEG,  # 0.12 deg/sqrt(h)
    accel_noise_density=50.0 * MICRO_G,
    gyro_turn_on_bias_std=1.0 * DEG / 3600.0,  # 1 deg/h
    accel_turn_on_bias_std=0.5e-3 * 9.80665,  # 0.5 mg
    gyro_bias_random_walk=1.0e-6,
    accel_bias_random_walk=2.0e-5,
    rate_hz=100.0,
    float32_output=True,
)

#: A MEMS IMU of the class found inside lidars (e.g. an ICM-20948 class part).
MEMS_LIDAR = ImuErrorModel(
    gyro_noise_density=0.015 * DEG,
    accel_noise_density=230.0 * MICRO_G,
    gyro_turn_on_bias_std=0.2 * DEG,
    accel_turn_on_bias_std=0.05,
    gyro_bias_random_walk=5.0e-5,
    accel_bias_random_walk=2.0e-4,
    rate_hz=100.0,
    jitter_s=50e-6,
    drop_fraction=0.001,
    # 16-bit output near +-500 deg/s and +-4 g full scale, with binary scale factors in SI
    # units (2^-12 rad/s = 0.014 deg/s, 2^-10 m/s^2 = 0.1 mg).
    gyro_lsb=2.0**-12,
    accel_lsb=2.0**-10,
)


def ideal_imu(
    trajectory: Trajectory, T_base_imu: Transform, t_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free gyro and specific force of an IMU rigidly mounted at ``T_base_imu``.

    ``w_I = R_B_I^T w_B`` and ``f_I = R_B_I^T (f_B + dw_B x t_B_I + w_B x (w_B x t_B_I))``.
    Returns two (N, 3) arrays: rad/s and m/s^2, in the IMU frame.
    """
    state = trajectory.state(t_s)
    R_imu_base = T_base_imu.rotation.inv()
    gyro = R_imu_base.apply(state.w_base)
    accel = R_imu_base.apply(state.specific_force_at(T_base_imu.translation))
    return np.atleast_2d(gyro), np.atleast_2d(accel)


@dataclass(frozen=True)
class SimulatedImu:
    """A simulated IMU's output and the truth behind it."""

    stream: ImuStream  # what the IMU publishes (stamps include offset and jitter)
    log_time_ns: np.ndarray  # when each message reached the recorder
    true_time_s: np.ndarray  # the instant each sample measured
    gyro_bias: np.ndarray  # (N, 3) true gyro bias at each sample
    accel_bias: np.ndarray  # (N, 3) true accelerometer bias at each sample


def simulate_imu(
    trajectory: Trajectory,
    T_base_imu: Transform,
    model: ImuErrorModel,
    rng: np.random.Generator,
    t0_ns: int,
    frame_id: str,
) -> SimulatedImu:
    """Sample an IMU over the trajectory's span.

    Samples are taken at ``t_k = phase + k / rate`` (true time, seconds from the trajectory
    start) with a random phase; stamps are ``t0_ns + (t_k + time_offset + jitter)``.
    """
    period = 1.0 / model.rate_hz
    phase = rng.uniform(0.0, period)
    t_true = np.arange(trajectory.t_start_s + phase, trajectory.t_end_s, period)
    n = len(t_true)
    gyro, accel = ideal_imu(trajectory, T_base_imu, t_true)

    def bias(turn_on: float, walk: float) -> np.ndarray:
        b = rng.normal(0.0, 1.0, 3) * turn_on
        steps = rng.normal(0.0, 1.0, (n, 3)) * walk * np.sqrt(period)
        steps[0] = 0.0
        return b + np.cumsum(steps, axis=0)

    gyro_bias = bias(model.gyro_turn_on_bias_std, model.gyro_bias_random_walk)
    accel_bias = bias(model.accel_turn_on_bias_std, model.accel_bias_random_walk)
    gyro = gyro + gyro_bias + rng.normal(0.0, 1.0, (n, 3)) * model.gyro_noise_std()
    accel = accel + accel_bias + rng.normal(0.0, 1.0, (n, 3)) * model.accel_noise_std()

    if model.gyro_lsb > 0:
        gyro = np.round(gyro / model.gyro_lsb) * model.gyro_lsb
    if model.accel_lsb > 0:
        accel = np.round(accel / model.accel_lsb) * model.accel_lsb
    if model.float32_output:
        gyro = gyro.astype(np.float32).astype(np.float64)
        accel = accel.astype(np.float32).astype(np.float64)

    stamp_s = t_true + model.time_offset_s
    if model.jitter_s > 0:
        stamp_s = stamp_s + rng.normal(0.0, model.jitter_s, n)
    keep = np.ones(n, dtype=bool)
    if model.drop_fraction > 0:
        keep = rng.uniform(size=n) >= model.drop_fraction
    t_ns = t0_ns + np.round(stamp_s * 1e9).astype(np.int64)
    log_ns = t0_ns + np.round((t_true + model.latency_s) * 1e9).astype(np.int64)
    stream = ImuStream(t_ns[keep], gyro[keep], accel[keep], frame_id)
    return SimulatedImu(stream, log_ns[keep], t_true[keep], gyro_bias[keep], accel_bias[keep])
