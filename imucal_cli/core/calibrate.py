"""Extrinsics of one sensor IMU in the base frame from the two IMUs' signals (paper eqs. 10-17).

The paper solves the rotation by Kabsch/Horn (eq. 10) and then the translation by bounded least
squares (eq. 16). Here the Kabsch/Horn solution over the selected windows only initialises a
joint Gauss-Newton estimate of everything the two signals share:

- gyro (eq. 10): ``w_I(t + tau) = R^T w_B(t) + b_g(t)``
- accelerometer (eq. 11): ``f_I(t + tau) = R^T (f_B + ([dw_B]x + [w_B]x^2) t_BI)(t) + b_a(t)``

with ``R = R_base_imu``, ``t_BI = t_base_imu``, the clock offset ``tau`` (stamp of the sensor
minus stamp of the base) and the sensor's biases relative to the base as piecewise-linear
functions of time with a knot every window (they drift). The accelerometer equation constrains
the rotation too (through gravity and the vehicle's accelerations), so the axis that yaw-only
driving leaves free in eq. 10 is fixed by gravity. Both sides are resampled onto one grid and
pass through the same zero-phase low-pass (:mod:`imucal_cli.core.signals`); the angular
acceleration is the derivative of the base gyro's interpolating spline, filtered alike.

The biases are eliminated by a sparse Schur complement, so the remaining 7x7 problem in
``(rotation, translation, tau)`` takes the translation box of eq. 16 through
``scipy.optimize.lsq_linear``. The covariance is the inverse Fisher information with the
residual variance estimated from the fit, corrected for the low-pass's correlation of
neighbouring residuals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.interpolate import make_interp_spline
from scipy.optimize import lsq_linear
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from imucal_cli.core.segments import OBSERVABLE_FRACTION_OF_BOUND, WindowInfo, analyse_windows
from imucal_cli.core.signals import LOWPASS_HZ, Lowpass, TooLittleData, white_noise_std
from imucal_cli.core.so3 import skew, skew_squared
from imucal_cli.core.timing import estimate_time_offset
from imucal_cli.types import ImuStream, Transform

#: Random walk of the accelerometer bias allowed between knots (m/s^2/sqrt(s)): loose, a few
#: times what MEMS parts drift, so the data decide.
ACCEL_BIAS_WALK = 0.01
#: Prior standard deviation of the accelerometer bias (m/s^2): keeps knots without data defined.
ACCEL_BIAS_PRIOR_STD = 1.0
#: A gap is a step between stamps longer than this many median periods: windows holding one
#: are not used (the spline cannot bridge it).
GAP_PERIODS = 3.0


@dataclass(frozen=True)
class CalibrationOptions:
    resample_hz: float = 100.0
    max_time_offset_s: float = 0.1
    window_s: float = 10.0
    max_rotation_std_deg: float = 1.0
    translation_bound_m: float = 0.3
    gyro_bias_walk: float = np.radians(0.1)  # rad/s/sqrt(s), config gyro_bias.process_noise_dps
    gyro_bias_prior_std: float = np.radians(0.3)  # rad/s, config gyro_bias.initial_std_dps
    lowpass_hz: float = LOWPASS_HZ
    max_iterations: int = 12


@dataclass(frozen=True)
class SensorEstimate:
    """The estimate for one sensor IMU and how well the drive determines it."""

    status: str  # ok | partial | unobservable
    T_base_imu: Transform
    covariance: np.ndarray | None  # 6x6 of [rotation (rad, about base axes), t_base_imu (m)]
    translation_observable: np.ndarray  # (3,) bool
    time_offset_s: float
    time_offset_std_s: float | None
    gyro_bias: np.ndarray  # (3,) final relative gyro bias (rad/s, IMU frame)
    gyro_bias_std: np.ndarray | None
    accel_bias: np.ndarray  # (3,) final relative accelerometer bias (m/s^2, IMU frame)
    accel_bias_std: np.ndarray | None
    bias_knots_s: np.ndarray  # (K,) knot times on the grid clock
    gyro_bias_knots: np.ndarray  # (K, 3)
    accel_bias_knots: np.ndarray  # (K, 3)
    windows: list[WindowInfo]
    residual_rms_gyro: float | None
    residual_rms_accel: float | None
    iterations: int = 0
    noise_std: dict[str, float] = field(default_factory=dict)

    @property
    def rotation_std_deg(self) -> np.ndarray | None:
        if self.covariance is None:
            return None
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def translation_std_m(self) -> np.ndarray | None:
        if self.covariance is None:
            return None
        return np.sqrt(np.diag(self.covariance)[3:])

    def lidar_covariance(self, T_imu_lidar: Transform) -> np.ndarray | None:
        """6x6 covariance of ``T_base_lidar = T_base_imu T_imu_lidar`` (rotation about base axes)."""
        if self.covariance is None:
            return None
        lever = self.T_base_imu.rotation.apply(T_imu_lidar.translation)
        J = np.eye(6)
        J[3:, :3] = -skew(lever)  # d(R t_IL) = [dtheta]x R t_IL = -[R t_IL]x dtheta
        return J @ self.covariance @ J.T


# --------------------------------------------------------------------------- base side


@dataclass(frozen=True)
class BaseSignals:
    """The base IMU on the common grid, low-passed (everything the equations need)."""

    grid_s: np.ndarray  # (N,) seconds from ``t_ref_ns``, base clock
    t_ref_ns: int
    rate_hz: float
    lowpass: Lowpass
    w: np.ndarray  # (N, 3) rad/s
    dw: np.ndarray  # (N, 3) rad/s^2, derivative of the gyro's spline, filtered alike
    f: np.ndarray  # (N, 3) m/s^2
    df: np.ndarray  # (N, 3) m/s^3
    A: np.ndarray  # (N, 3, 3) LP([w]x^2) + [dw]x, eq. 12's design matrix
    valid: np.ndarray  # (N,) bool, no gap
    noise_density_gyro: float  # rad/s/sqrt(Hz)
    noise_density_accel: float


def _stream_seconds(stream: ImuStream, t_ref_ns: int) -> np.ndarray:
    return (stream.t_ns - t_ref_ns).astype(np.float64) * 1e-9


def _median_period(t_s: np.ndarray) -> float:
    steps = np.diff(t_s)
    return float(np.median(steps[steps > 0]))


def _noise_density(stream: ImuStream) -> tuple[float, float, float]:
    """Isotropic white-noise densities (gyro, accel) and the stream's rate."""
    rate = 1.0 / _median_period(stream.t_ns * 1e-9)
    gyro = float(np.sqrt(np.mean(white_noise_std(stream.gyro) ** 2)) / np.sqrt(rate))
    accel = float(np.sqrt(np.mean(white_noise_std(stream.accel) ** 2)) / np.sqrt(rate))
    return gyro, accel, rate


def _valid_mask(t_s: np.ndarray, query_s: np.ndarray) -> np.ndarray:
    """True where the samples around ``query_s`` are no further apart than a short gap."""
    period = _median_period(t_s)
    j = np.clip(np.searchsorted(t_s, query_s), 1, len(t_s) - 1)
    inside = (query_s >= t_s[0]) & (query_s <= t_s[-1])
    return inside & (t_s[j] - t_s[j - 1] <= GAP_PERIODS * period)


class _StreamSpline:
    """Cubic interpolating splines of one IMU's gyro and accelerometer over its own stamps."""

    def __init__(self, stream: ImuStream, t_ref_ns: int, grid_rate_hz: float) -> None:
        self.t_s = _stream_seconds(stream, t_ref_ns)
        gyro, accel = stream.gyro, stream.accel
        rate = 1.0 / _median_period(self.t_s)
        if rate > 1.5 * grid_rate_hz:  # anti-alias before the grid, far above the common low-pass
            anti_alias = Lowpass(0.4 * grid_rate_hz, rate)
            gyro, accel = anti_alias(gyro), anti_alias(accel)
        self.gyro = make_interp_spline(self.t_s, gyro, k=3)
        self.accel = make_interp_spline(self.t_s, accel, k=3)

    def valid(self, query_s: np.ndarray) -> np.ndarray:
        return _valid_mask(self.t_s, query_s)


def common_grid(streams: list[ImuStream], rate_hz: float, margin_s: float) -> tuple[int, np.ndarray]:
    """A uniform grid over the span every stream covers, ``margin_s`` inside its ends.

    Returns the reference time (ns) and the grid in seconds from it.
    """
    start = max(int(s.t_ns[0]) for s in streams)
    end = min(int(s.t_ns[-1]) for s in streams)
    span = (end - start) * 1e-9 - 2 * margin_s
    if span <= 0:
        raise TooLittleData(f"the IMU streams overlap for {(end - start) * 1e-9:.2f} s only")
    n = int(np.floor(span * rate_hz)) + 1
    return start, margin_s + np.arange(n) / rate_hz


def prepare_base(base: ImuStream, t_ref_ns: int, grid_s: np.ndarray, rate_hz: float, lowpass_hz: float) -> BaseSignals:
    """Resample and low-pass the base IMU; form eq. 12's design matrix."""
    if len(base) < 10:
        raise TooLittleData(f"the base IMU has {len(base)} samples")
    lp = Lowpass(lowpass_hz, rate_hz)
    spline = _StreamSpline(base, t_ref_ns, rate_hz)
    w_raw, dw_raw = spline.gyro(grid_s), spline.gyro(grid_s, nu=1)
    f_raw, df_raw = spline.accel(grid_s), spline.accel(grid_s, nu=1)
    w, dw, f, df = lp(w_raw), lp(dw_raw), lp(f_raw), lp(df_raw)
    centripetal = lp(skew_squared(w_raw).reshape(-1, 9)).reshape(-1, 3, 3)
    gyro_density, accel_density, _ = _noise_density(base)
    return BaseSignals(
        grid_s=grid_s,
        t_ref_ns=t_ref_ns,
        rate_hz=rate_hz,
        lowpass=lp,
        w=w,
        dw=dw,
        f=f,
        df=df,
        A=centripetal + skew(dw),
        valid=spline.valid(grid_s),
        noise_density_gyro=gyro_density,
        noise_density_accel=accel_density,
    )


# --------------------------------------------------------------------------- the estimator


def _hat_weights(t_s: np.ndarray, knots_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear B-spline (hat) interpolation: knot index ``j`` and weight of knot ``j + 1``."""
    j = np.clip(np.searchsorted(knots_s, t_s, side="right") - 1, 0, len(knots_s) - 2)
    u = (t_s - knots_s[j]) / (knots_s[j + 1] - knots_s[j])
    return j, u


def _bias_prior(n_knots: int, spacing_s: float, walk: float, prior_std: float) -> sparse.csr_matrix:
    """Information of a random walk between knots plus a weak absolute prior, per axis (3K)."""
    d = sparse.diags([np.ones(n_knots - 1), -np.ones(n_knots - 1)], [0, 1], shape=(n_knots - 1, n_knots))
    walk_info = (d.T @ d) / (walk**2 * spacing_s)
    info = walk_info + sparse.identity(n_knots) / prior_std**2
    return sparse.kron(info, sparse.identity(3)).tocsr()


def kabsch_rotation(w_base: np.ndarray, w_imu: np.ndarray, windows: list[np.ndarray]) -> Rotation:
    """``R_base_imu`` minimising ``sum |R^T w_B - w_I|^2`` over windows, each centred (eq. 10).

    Centring per window removes a constant relative gyro bias. Horn/Kabsch via
    ``Rotation.align_vectors``, which finds ``A`` minimising ``sum |a_i - A b_i|^2``.
    """
    a = np.concatenate([w_imu[i] - w_imu[i].mean(axis=0) for i in windows])
    b = np.concatenate([w_base[i] - w_base[i].mean(axis=0) for i in windows])
    R_imu_base, _ = Rotation.align_vectors(a, b)
    return R_imu_base.inv()


def _unobservable(prior: Transform, windows: list[WindowInfo], tau: float) -> SensorEstimate:
    return SensorEstimate(
        status="unobservable",
        T_base_imu=prior,
        covariance=None,
        translation_observable=np.zeros(3, dtype=bool),
        time_offset_s=tau,
        time_offset_std_s=None,
        gyro_bias=np.zeros(3),
        gyro_bias_std=None,
        accel_bias=np.zeros(3),
        accel_bias_std=None,
        bias_knots_s=np.zeros(0),
        gyro_bias_knots=np.zeros((0, 3)),
        accel_bias_knots=np.zeros((0, 3)),
        windows=windows,
        residual_rms_gyro=None,
        residual_rms_accel=None,
    )


@dataclass(frozen=True)
class SensorWindows:
    """A sensor on the common grid: its clock offset estimate and its windows' observability."""

    spline: _StreamSpline
    time_offset_s: float
    windows: list[WindowInfo]
    sigma_gyro: float  # white-noise std of one grid sample of the gyro residual (rad/s)
    sigma_accel: float  # ... of the accelerometer residual (m/s^2)


def sensor_windows(
    base: BaseSignals, sensor: ImuStream, lever_arm: np.ndarray, options: CalibrationOptions
) -> SensorWindows:
    """Clock offset from ``|w|`` and the observability of every window (eqs. 18-19)."""
    if len(sensor) < 10:
        raise TooLittleData(f"the sensor IMU has {len(sensor)} samples")
    grid = base.grid_s
    spline = _StreamSpline(sensor, base.t_ref_ns, base.rate_hz)
    gyro_density, accel_density, _ = _noise_density(sensor)
    # white-noise std of one grid sample of each residual, before the low-pass
    sigma_gyro = float(np.sqrt((gyro_density**2 + base.noise_density_gyro**2) * base.rate_hz))
    sigma_accel = float(np.sqrt((accel_density**2 + base.noise_density_accel**2) * base.rate_hz))
    tau = 0.0
    if options.max_time_offset_s > 0:
        w_sensor = base.lowpass(spline.gyro(grid))
        tau, _ = estimate_time_offset(
            grid, np.linalg.norm(base.w, axis=1), np.linalg.norm(w_sensor, axis=1), options.max_time_offset_s
        )
    valid = base.valid & spline.valid(grid + tau)
    windows = analyse_windows(
        grid, base.rate_hz, base.w, base.f, base.A, lever_arm, valid, options.window_s, sigma_gyro, sigma_accel,
        options.max_rotation_std_deg, options.translation_bound_m,
    )
    return SensorWindows(spline, tau, windows, sigma_gyro, sigma_accel)


def calibrate_sensor(
    base: BaseSignals,
    sensor: ImuStream,
    prior_T_base_imu: Transform,
    options: CalibrationOptions,
) -> SensorEstimate:
    """Estimate ``T_base_imu``, the clock offset and the relative biases of one sensor IMU."""
    grid = base.grid_s
    lp = base.lowpass
    found = sensor_windows(base, sensor, prior_T_base_imu.translation, options)
    spline, tau, windows = found.spline, found.time_offset_s, found.windows
    sigma_gyro, sigma_accel = found.sigma_gyro, found.sigma_accel

    def sensor_on_grid(tau: float) -> tuple[np.ndarray, np.ndarray]:
        return lp(spline.gyro(grid + tau)), lp(spline.accel(grid + tau))

    selected = [w.index for w in windows if w.selected]
    if not selected:
        return _unobservable(prior_T_base_imu, windows, tau)

    index = np.concatenate(selected)
    n = len(index)
    w_sensor, _ = sensor_on_grid(tau)
    R = kabsch_rotation(base.w, w_sensor, selected)
    t = prior_T_base_imu.translation.copy()
    t_prior = prior_T_base_imu.translation
    bound = options.translation_bound_m

    # Bias knots: one per window boundary over the grid (piecewise linear in time).
    n_knots = int(np.ceil((grid[-1] - grid[0]) / options.window_s)) + 1
    knots = grid[0] + np.arange(n_knots) * options.window_s
    knots[-1] = max(knots[-1], grid[-1] + 1e-9)
    j, u = _hat_weights(grid[index], knots)
    gyro_knots = np.zeros((n_knots, 3))
    accel_knots = np.zeros((n_knots, 3))
    n_bias = 6 * n_knots
    prior_info = sparse.block_diag(
        [
            _bias_prior(n_knots, options.window_s, options.gyro_bias_walk, options.gyro_bias_prior_std),
            _bias_prior(n_knots, options.window_s, ACCEL_BIAS_WALK, ACCEL_BIAS_PRIOR_STD),
        ]
    ).tocsc()

    # Sparse structure of the Jacobian (rows: 3 gyro + 3 accel per sample).
    rows3 = np.arange(n)[:, None] * 6 + np.arange(3)[None, :]  # gyro rows (n, 3)
    rows_a = rows3 + 3
    col_bias_g = 7 + 3 * j[:, None] + np.arange(3)[None, :]  # (n, 3) knot j, per axis
    col_bias_a = col_bias_g + 3 * n_knots
    bias_rows = np.concatenate([rows3.ravel(), rows3.ravel(), rows_a.ravel(), rows_a.ravel()])
    bias_cols = np.concatenate([col_bias_g.ravel(), (col_bias_g + 3).ravel(), col_bias_a.ravel(), (col_bias_a + 3).ravel()])
    bias_vals = -np.concatenate([np.repeat(1 - u, 3), np.repeat(u, 3), np.repeat(1 - u, 3), np.repeat(u, 3)])

    A = base.A[index]
    gain = lp.white_noise_gain()
    scale_gyro = sigma_gyro * np.sqrt(gain)  # std of one low-passed residual, first guess
    scale_accel = sigma_accel * np.sqrt(gain)
    free_global = np.ones(7, dtype=bool)
    if options.max_time_offset_s <= 0:
        free_global[6] = False
    observable = np.ones(3, dtype=bool)
    iterations = 0
    converged_once = False
    S_inv = None
    for iterations in range(1, options.max_iterations + 1):  # noqa: B007
        w_sensor, f_sensor = sensor_on_grid(tau)
        w_I, f_I = w_sensor[index], f_sensor[index]
        R_inv = R.inv()
        gyro_bias = gyro_knots[j] * (1 - u)[:, None] + gyro_knots[j + 1] * u[:, None]
        accel_bias = accel_knots[j] * (1 - u)[:, None] + accel_knots[j + 1] * u[:, None]
        u_g = R_inv.apply(base.w[index])
        v = base.f[index] + np.einsum("nij,j->ni", A, t)
        v_a = R_inv.apply(v)
        r_g = w_I - u_g - gyro_bias
        r_a = f_I - v_a - accel_bias
        if iterations > 1:  # residual variance from the fit (per equation)
            scale_gyro = float(np.sqrt(np.mean(r_g**2)))
            scale_accel = float(np.sqrt(np.mean(r_a**2)))

        # Jacobian columns of the globals: rotation (right perturbation), translation, tau.
        J_rot_g = -skew(u_g)
        J_rot_a = -skew(v_a)
        J_t_a = -np.einsum("ij,njk->nik", R_inv.as_matrix(), A)
        J_tau_g = R_inv.apply(base.dw[index])
        J_tau_a = R_inv.apply(base.df[index])
        g_rows = np.repeat(rows3, 3, axis=1).ravel()
        a_rows = np.repeat(rows_a, 3, axis=1).ravel()
        cols3 = np.tile(np.arange(3), 3 * n)
        rows = np.concatenate([g_rows, a_rows, a_rows, rows3.ravel(), rows_a.ravel(), bias_rows])
        cols = np.concatenate([cols3, cols3, cols3 + 3, np.full(3 * n, 6), np.full(3 * n, 6), bias_cols])
        vals = np.concatenate(
            [J_rot_g.ravel(), J_rot_a.ravel(), J_t_a.ravel(), J_tau_g.ravel(), J_tau_a.ravel(), bias_vals]
        )
        weights = np.tile(np.repeat([gain / scale_gyro**2, gain / scale_accel**2], 3), n)
        J = sparse.csr_matrix((vals, (rows, cols)), shape=(6 * n, 7 + n_bias))
        residual = np.concatenate([r_g, r_a], axis=1).ravel()
        JW = J.T.multiply(weights).tocsr()
        H = (JW @ J).tocsc()
        grad = -(JW @ residual)
        x_bias = np.concatenate([gyro_knots.ravel(), accel_knots.ravel()])
        H_bb = (H[7:, 7:] + prior_info).tocsc()
        grad_b = grad[7:] - prior_info @ x_bias
        free = np.flatnonzero(free_global & np.concatenate([[True] * 3, observable, [True]]))
        H_gg = H[:7, :7].toarray()[np.ix_(free, free)]
        H_gb = H[:7, 7:].toarray()[free]
        lu = splu(H_bb)
        X = lu.solve(H_gb.T)  # H_bb^-1 H_bg
        S = H_gg - H_gb @ X
        s = grad[:7][free] - X.T @ grad_b
        lower = np.full(len(free), -np.inf)
        upper = np.full(len(free), np.inf)
        for k, col in enumerate(free):
            if 3 <= col < 6:
                lower[k] = t_prior[col - 3] - bound - t[col - 3]
                upper[k] = t_prior[col - 3] + bound - t[col - 3]
        L = np.linalg.cholesky(S)
        step_free = lsq_linear(L.T, np.linalg.solve(L, s), bounds=(lower, upper), method="bvls", tol=1e-12).x
        step_global = np.zeros(7)
        step_global[free] = step_free
        step_bias = lu.solve(grad_b - H_gb.T @ step_free)
        R = R * Rotation.from_rotvec(step_global[:3])
        t = t + step_global[3:6]
        tau = tau + step_global[6]
        gyro_knots = gyro_knots + step_bias[: 3 * n_knots].reshape(-1, 3)
        accel_knots = accel_knots + step_bias[3 * n_knots :].reshape(-1, 3)
        S_inv = np.linalg.inv(S)
        small = np.max(np.abs(step_global[:3])) < 1e-10 and np.max(np.abs(step_global[3:])) < 1e-8
        if small and iterations > 2:
            # An axis the data cannot pin down is kept at the prior (status partial).
            t_std = np.full(3, np.inf)
            for k, col in enumerate(free):
                if 3 <= col < 6:
                    t_std[col - 3] = np.sqrt(S_inv[k, k])
            weak = observable & (t_std >= OBSERVABLE_FRACTION_OF_BOUND * bound)
            if weak.any() and not converged_once:
                observable &= ~weak
                t[~observable] = t_prior[~observable]
                converged_once = True
                continue
            break

    # Covariance of the free globals, mapped to [rotation about base axes, t_base_imu].
    cov = np.zeros((7, 7))
    cov[np.ix_(free, free)] = S_inv
    for axis in range(3):
        if not observable[axis]:  # kept at the prior: the truth is somewhere in the box
            cov[3 + axis, 3 + axis] = bound**2 / 3.0
    R_m = R.as_matrix()
    rot = np.zeros((6, 6))
    rot[:3, :3] = R_m
    rot[3:, 3:] = np.eye(3)
    cov6 = rot @ cov[:6, :6] @ rot.T

    last = n_knots - 1
    bias_cov_diag = None
    try:  # marginal std of the last knot's biases
        cols = [3 * last + a for a in range(3)] + [3 * n_knots + 3 * last + a for a in range(3)]
        E = np.zeros((n_bias, len(cols)))
        E[cols, np.arange(len(cols))] = 1.0
        Y = lu.solve(E)
        XtE = X.T @ E  # (free, 6): how the globals' uncertainty feeds the biases
        block = Y[cols] + XtE.T @ S_inv @ XtE
        bias_cov_diag = np.sqrt(np.clip(np.diag(block), 0, None))
    except Exception:  # noqa: BLE001 - a report detail; never fail the estimate on it
        bias_cov_diag = None

    T = Transform(R, t)
    status = "ok" if observable.all() else "partial"
    return SensorEstimate(
        status=status,
        T_base_imu=T,
        covariance=cov6,
        translation_observable=observable.copy(),
        time_offset_s=float(tau),
        time_offset_std_s=float(np.sqrt(cov[6, 6])) if free_global[6] else None,
        gyro_bias=gyro_knots[last].copy(),
        gyro_bias_std=bias_cov_diag[:3] if bias_cov_diag is not None else None,
        accel_bias=accel_knots[last].copy(),
        accel_bias_std=bias_cov_diag[3:] if bias_cov_diag is not None else None,
        bias_knots_s=knots,
        gyro_bias_knots=gyro_knots,
        accel_bias_knots=accel_knots,
        windows=windows,
        residual_rms_gyro=float(np.sqrt(np.mean(r_g**2))),
        residual_rms_accel=float(np.sqrt(np.mean(r_a**2))),
        iterations=iterations,
        noise_std={"gyro_radps": sigma_gyro, "accel_mps2": sigma_accel},
    )
