"""IMU measurement models: ideal kinematics plus noise, biases and timing errors."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from imucal_cli.sim.trajectory import Trajectory
from imucal_cli.types import GRAVITY_MPS2, ImuStream, Transform

DEG = np.pi / 180.0
MICRO_G = GRAVITY_MPS2 * 1e-6


#: The error figures ``ImuErrorModel.scaled`` multiplies.
_SCALED = (
    "gyro_noise_density",
    "accel_noise_density",
    "gyro_turn_on_bias_std",
    "accel_turn_on_bias_std",
    "gyro_bias_random_walk",
    "accel_bias_random_walk",
    "jitter_s",
    "scale_factor_std",
    "nonorthogonality_std_rad",
    "misalignment_std_rad",
    "g_sensitivity_std",
    "vibration_accel_mps2",
    "vibration_gyro_radps",
)


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
    time_offset_s: float = 0.0  # stamp minus true measurement time, at the drive's start
    clock_drift_ppm: float = 0.0  # its rate: the offset grows by 1e-6 of the time since
    clock_steps: tuple[tuple[float, float], ...] = ()  # (at s, by s): the clock re-synchronised
    jitter_s: float = 0.0  # white stamp noise (std)
    drop_fraction: float = 0.0  # messages lost at random
    latency_s: float = 0.002  # true time to log (receive) time
    gyro_lsb: float = 0.0  # output resolution (rad/s); 0: none
    accel_lsb: float = 0.0  # output resolution (m/s^2); 0: none
    float32_output: bool = False  # the driver publishes single-precision values
    # Deterministic sensor errors (drawn once per IMU), none by default:
    scale_factor_std: float = 0.0  # per-axis scale-factor error (fraction), gyro and accel apart
    nonorthogonality_std_rad: float = (
        0.0  # symmetric coupling of the axes (the IMU frame stays defined)
    )
    misalignment_std_rad: float = (
        0.0  # each triad (gyro, accel) rotated apart by this much per axis
    )
    g_sensitivity_std: float = 0.0  # gyro error per unit specific force, rad/s per m/s^2, per entry
    housing_std_rad: float = 0.0  # both triads rotated together against the housing, per axis
    gyro_scale: float = 0.0  # the gyro's common scale error (fraction): -0.1 reads 10% low
    vibration_band_hz: tuple[float, float] = (
        20.0,
        60.0,
    )  # the mount's vibration frequency is drawn here
    vibration_accel_mps2: float = 0.0  # amplitude of the mount's vibration (each axis)
    vibration_gyro_radps: float = 0.0
    accel_units: str = "mps2"  # what the driver publishes: mps2 | g
    gyro_units: str = "radps"  # radps | dps

    def scaled(self, noise_scale: float) -> ImuErrorModel:
        """Noise, biases, jitter and drop rate multiplied by ``noise_scale`` (0: an ideal
        sensor)."""
        ideal = noise_scale <= 0
        return replace(
            self,
            **{name: getattr(self, name) * noise_scale for name in _SCALED},
            drop_fraction=min(1.0, self.drop_fraction * noise_scale),
            gyro_lsb=0.0 if ideal else self.gyro_lsb,
            accel_lsb=0.0 if ideal else self.accel_lsb,
            float32_output=self.float32_output and not ideal,
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
    accel_turn_on_bias_std=0.5e-3 * GRAVITY_MPS2,  # 0.5 mg
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


def mount_tilt(f_base: np.ndarray, tilt_rad_per_mps2: tuple[float, float]) -> np.ndarray:
    """Tilt (rotation vector about the base axes, (N, 3) rad) of a mount that leans with the
    vehicle's specific force like a truck cab on its suspension: roll ``k_roll f_y``, pitch
    ``k_pitch f_x``."""
    k_roll, k_pitch = tilt_rad_per_mps2
    return np.stack([k_roll * f_base[:, 1], k_pitch * f_base[:, 0], np.zeros(len(f_base))], axis=1)


def _has_intrinsic_errors(model: ImuErrorModel) -> bool:
    return any(
        v > 0
        for v in (
            model.scale_factor_std,
            model.nonorthogonality_std_rad,
            model.misalignment_std_rad,
            model.g_sensitivity_std,
            model.housing_std_rad,
            model.gyro_scale,
            model.vibration_accel_mps2,
            model.vibration_gyro_radps,
        )
    )


def ideal_imu(
    trajectory: Trajectory,
    T_base_imu: Transform,
    t_s: np.ndarray,
    tilt_rad_per_mps2: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free gyro and specific force of an IMU mounted at ``T_base_imu``.

    ``w_I = R_B_I^T w_B`` and ``f_I = R_B_I^T (f_B + dw_B x t_B_I + w_B x (w_B x t_B_I))``.
    With a tilting mount, ``R_B_I(t) = exp([theta(t)]x) R_B_I`` (:func:`mount_tilt`, pivoting
    about the IMU) and the gyro also sees ``d theta / dt``.
    Returns two (N, 3) arrays: rad/s and m/s^2, in the IMU frame.
    """
    from scipy.spatial.transform import Rotation

    state = trajectory.state(t_s)
    w_base = state.w_base
    R_imu_base = T_base_imu.rotation.inv()
    if any(tilt_rad_per_mps2):
        h = 1e-4  # the trajectory is a quintic spline: a central difference is exact to ~h^2
        theta = mount_tilt(state.f_base, tilt_rad_per_mps2)
        rate = (
            mount_tilt(trajectory.state(t_s + h).f_base, tilt_rad_per_mps2)
            - mount_tilt(trajectory.state(t_s - h).f_base, tilt_rad_per_mps2)
        ) / (2 * h)
        R_imu_base = T_base_imu.rotation.inv() * Rotation.from_rotvec(-theta)
        w_base = w_base + rate
    gyro = R_imu_base.apply(w_base)
    accel = R_imu_base.apply(state.specific_force_at(T_base_imu.translation))
    return np.atleast_2d(gyro), np.atleast_2d(accel)


def _axis_errors(model: ImuErrorModel, rng: np.random.Generator) -> np.ndarray:
    """``M`` with ``measured = M true`` for one triad: scale factors, symmetric
    non-orthogonality, then a small misalignment of the triad."""
    from scipy.spatial.transform import Rotation

    coupling = np.triu(rng.normal(0.0, model.nonorthogonality_std_rad, (3, 3)), 1)
    M = np.eye(3) + np.diag(rng.normal(0.0, model.scale_factor_std, 3)) + coupling + coupling.T
    return Rotation.from_rotvec(rng.normal(0.0, model.misalignment_std_rad, 3)).as_matrix() @ M


@dataclass(frozen=True)
class SimulatedImu:
    """A simulated IMU's output and the truth behind it."""

    stream: ImuStream  # what the IMU publishes (stamps include offset and jitter)
    log_time_ns: np.ndarray  # when each message reached the recorder
    true_time_s: np.ndarray  # the instant each sample measured
    gyro_bias: np.ndarray  # (N, 3) true gyro bias at each sample
    accel_bias: np.ndarray  # (N, 3) true accelerometer bias at each sample
    gyro_axes: np.ndarray = field(default_factory=lambda: np.eye(3))  # measured = axes @ true
    accel_axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    g_sensitivity: np.ndarray = field(
        default_factory=lambda: np.zeros((3, 3))
    )  # the gyro's: + G f (rad/s per m/s^2, IMU axes)


def simulate_imu(
    trajectory: Trajectory,
    T_base_imu: Transform,
    model: ImuErrorModel,
    rng: np.random.Generator,
    t0_ns: int,
    frame_id: str,
    tilt_rad_per_mps2: tuple[float, float] = (0.0, 0.0),
) -> SimulatedImu:
    """Sample an IMU over the trajectory's span (one piece of :class:`ImuSampler`)."""
    sampler = ImuSampler(trajectory, T_base_imu, model, rng, t0_ns, frame_id, tilt_rad_per_mps2)
    return sampler.sample(trajectory.t_start_s, trajectory.t_end_s)


class ImuSampler:
    """An IMU sampled over the trajectory piece by piece (a long drive is written as it is
    made), its bias walks carried from one piece to the next.

    Samples are taken at ``t_k = phase + k / rate`` (true time, seconds from the trajectory
    start) with a random phase; stamps are ``t0_ns + (t_k + time_offset + 1e-6 drift t_k +
    jitter)``. The deterministic errors (axis errors, g-sensitivity, vibration) are drawn from
    a generator of their own, so a model without them leaves every other draw as it was. One
    piece draws what one pass over the whole span drew, in the same order.
    """

    def __init__(
        self,
        trajectory: Trajectory,
        T_base_imu: Transform,
        model: ImuErrorModel,
        rng: np.random.Generator,
        t0_ns: int,
        frame_id: str,
        tilt_rad_per_mps2: tuple[float, float] = (0.0, 0.0),
        moves: tuple[tuple[float, Transform], ...] = (),
    ) -> None:
        self.trajectory, self.T_base_imu, self.model, self.rng = trajectory, T_base_imu, model, rng
        #: Where the mount moved (a knock): from each time (s, true), the pose it has.
        self.moves = moves
        self.t0_ns, self.frame_id, self.tilt = t0_ns, frame_id, tilt_rad_per_mps2
        self.period = 1.0 / model.rate_hz
        self.phase = rng.uniform(0.0, self.period)
        self.gyro_axes = self.accel_axes = np.eye(3)
        self.g_sensitivity = np.zeros((3, 3))
        self.vibration: tuple[float, np.ndarray] | None = None
        intrinsic = rng.spawn(1)[0] if _has_intrinsic_errors(model) else None  # (draws nothing)
        if intrinsic is not None:
            if model.vibration_accel_mps2 > 0 or model.vibration_gyro_radps > 0:
                self.vibration = (
                    intrinsic.uniform(*model.vibration_band_hz),
                    intrinsic.uniform(0.0, 2 * np.pi, 6),
                )
            self.gyro_axes = _axis_errors(model, intrinsic) * (1.0 + model.gyro_scale)
            self.g_sensitivity = intrinsic.normal(0.0, model.g_sensitivity_std, (3, 3))
            self.accel_axes = _axis_errors(model, intrinsic)
            if model.housing_std_rad > 0:  # the triads' frame against the housing's (drawn last)
                from scipy.spatial.transform import Rotation

                housing = Rotation.from_rotvec(intrinsic.normal(0.0, model.housing_std_rad, 3))
                self.gyro_axes, self.accel_axes = (
                    m @ housing.as_matrix() for m in (self.gyro_axes, self.accel_axes)
                )
        self.biases: tuple[np.ndarray, np.ndarray] | None = None  # the last sample's, so far

    def _sensed(self, t_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The motion at ``t_true`` as the IMU senses it, before its biases and noise: its
        mount's vibration and its axes' errors in."""
        model = self.model
        gyro, accel = ideal_imu(self.trajectory, self.T_base_imu, t_true, self.tilt)
        for at_s, pose in self.moves:  # (in order: each from its time on)
            after = t_true >= at_s
            if after.any():
                gyro[after], accel[after] = ideal_imu(
                    self.trajectory, pose, t_true[after], self.tilt
                )
        if self.vibration is not None:
            # a mount resonance, sampled at the output's instants as a real IMU samples it
            # (no anti-alias filter): what lies above Nyquist folds back
            freq, phases = self.vibration
            wave = np.sin(2 * np.pi * freq * t_true[:, None] + phases)
            accel = accel + model.vibration_accel_mps2 * wave[:, :3]
            gyro = gyro + model.vibration_gyro_radps * wave[:, 3:]
        if _has_intrinsic_errors(model):
            gyro = gyro @ self.gyro_axes.T + accel @ self.g_sensitivity.T
            accel = accel @ self.accel_axes.T
        return gyro, accel

    def sample(self, t_from_s: float, t_to_s: float) -> SimulatedImu:
        """The samples whose true time lies in ``[t_from_s, t_to_s)``; pieces follow on."""
        model, rng, period = self.model, self.rng, self.period
        # the instants np.arange(start, t_end, period) gives, those of [t_from_s, t_to_s)
        start, end = self.trajectory.t_start_s + self.phase, self.trajectory.t_end_s
        delta, total = (start + period) - start, int(np.ceil((end - start) / period))
        first = min(max(0, int(np.ceil((t_from_s - start) / delta))), total)
        last = total if t_to_s >= end else min(total, int(np.ceil((t_to_s - start) / delta)))
        t_true = start + np.arange(first, max(first, last)) * delta
        n = len(t_true)
        gyro, accel = self._sensed(t_true)

        def bias(turn_on: float, walk: float, last: np.ndarray | None) -> np.ndarray:
            b = rng.normal(0.0, 1.0, 3) * turn_on if last is None else last
            steps = rng.normal(0.0, 1.0, (n, 3)) * walk * np.sqrt(period)
            if last is None and n:
                steps[0] = 0.0
            return b + np.cumsum(steps, axis=0)

        last_g, last_a = self.biases if self.biases is not None else (None, None)
        gyro_bias = bias(model.gyro_turn_on_bias_std, model.gyro_bias_random_walk, last_g)
        accel_bias = bias(model.accel_turn_on_bias_std, model.accel_bias_random_walk, last_a)
        if n:
            self.biases = (gyro_bias[-1].copy(), accel_bias[-1].copy())
        gyro = gyro + gyro_bias + rng.normal(0.0, 1.0, (n, 3)) * model.gyro_noise_std()
        accel = accel + accel_bias + rng.normal(0.0, 1.0, (n, 3)) * model.accel_noise_std()

        gyro, accel = _published(model, gyro, accel)

        stamp_s = t_true + model.time_offset_s + 1e-6 * model.clock_drift_ppm * t_true
        for at_s, by_s in model.clock_steps:
            stamp_s = stamp_s + np.where(t_true >= at_s, by_s, 0.0)
        if model.jitter_s > 0:
            stamp_s = stamp_s + rng.normal(0.0, model.jitter_s, n)
        keep = np.ones(n, dtype=bool)
        if model.drop_fraction > 0:
            keep = rng.uniform(size=n) >= model.drop_fraction
        t_ns = self.t0_ns + np.round(stamp_s * 1e9).astype(np.int64)
        log_ns = self.t0_ns + np.round((t_true + model.latency_s) * 1e9).astype(np.int64)
        stream = ImuStream(t_ns[keep], gyro[keep], accel[keep], self.frame_id)
        return SimulatedImu(
            stream,
            log_ns[keep],
            t_true[keep],
            gyro_bias[keep],
            accel_bias[keep],
            self.gyro_axes,
            self.accel_axes,
            self.g_sensitivity,
        )


def _published(
    model: ImuErrorModel, gyro: np.ndarray, accel: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """What the driver publishes: its units, its resolution, its float width."""
    if model.gyro_units == "dps":
        gyro = np.degrees(gyro)  # the resolution below is then in deg/s
    if model.accel_units == "g":
        accel = accel / GRAVITY_MPS2
    if model.gyro_lsb > 0:
        gyro = np.round(gyro / model.gyro_lsb) * model.gyro_lsb
    if model.accel_lsb > 0:
        accel = np.round(accel / model.accel_lsb) * model.accel_lsb
    if model.float32_output:
        gyro = gyro.astype(np.float32).astype(np.float64)
        accel = accel.astype(np.float32).astype(np.float64)
    return gyro, accel
