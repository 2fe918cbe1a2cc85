"""Extrinsics of one sensor IMU in the base frame from the two IMUs' signals (paper eqs. 10-17).

The paper solves the rotation by Kabsch/Horn (eq. 10) and then the translation by bounded least
squares (eq. 16). Here the Kabsch/Horn solution over the selected windows only initialises a
joint Gauss-Newton estimate of everything the two signals share (:mod:`.model` states the
model; :mod:`.solver` solves it on the windows' moments, which :mod:`.streaming` reduces the
signals to). The accelerometer equation constrains the rotation too (through gravity and the
vehicle's accelerations), so the axis that yaw-only driving leaves free in eq. 10 is fixed by
gravity.

A number is only as good as the model behind it, so :func:`solve` also tests the model on the
data (:mod:`.checks`) and makes the covariance honest (:mod:`.uncertainty`); :mod:`.status`
turns the figures into the status and the sentences.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import pairwise
from typing import Any

import numpy as np

from imucal_cli.core import checks, status
from imucal_cli.core.grades import GRADES, error_prior_std
from imucal_cli.core.model import (
    ACCEL_BIAS_PRIOR_STD,
    ACCEL_BIAS_WALK,
    ACCEL_ROTATION,
    BASE_GYRO_AXES,
    KNOT,
    ROTATION,
    TIME_OFFSET,
    TRANSLATION,
    BiasModel,
)
from imucal_cli.core.moments import WindowMoments
from imucal_cli.core.moves import MIN_SIDE_WINDOWS, find_moves
from imucal_cli.core.segments import OBSERVABLE_FRACTION_OF_BOUND, WindowInfo
from imucal_cli.core.signals import LOWPASS_HZ, Lowpass
from imucal_cli.core.so3 import skew
from imucal_cli.core.solver import Fit, Problem, Settings
from imucal_cli.core.timeline import Epoch
from imucal_cli.core.timing import TIME_OFFSET_MAX_STD_S
from imucal_cli.core.uncertainty import uncertainty
from imucal_cli.types import Transform


@dataclass(frozen=True)
class CalibrationOptions:
    resample_hz: float = 100.0
    max_time_offset_s: float = 0.1
    max_clock_drift_ppm: float = 200.0  # 0: the offset is one for the whole log
    window_s: float = 10.0
    epoch_s: float = 300.0  # the timeline's slice (:mod:`.timeline`)
    max_rotation_std_deg: float = 1.0
    translation_bound_m: float = 0.3
    rotation_bound_deg: float = 20.0  # how far the estimate may turn from the prior (a check)
    gyro_bias_walk: float = np.radians(0.1)  # rad/s/sqrt(s), config gyro_bias.process_noise_dps
    gyro_bias_prior_std: float = np.radians(0.3)  # rad/s, config gyro_bias.initial_std_dps
    lowpass_hz: float = LOWPASS_HZ
    max_iterations: int = 12
    consistency_alpha: float = 0.001  # false-alarm rate of each model-consistency check
    rotation_floor_deg: float = 0.0  # systematic std the data cannot see, added to the result's
    translation_floor_m: float = 0.0
    sensor_grade: str = "ideal"  # SPEC "IMU grades" (core.grades.GRADES): the priors on the
    base_grade: str = "ideal"  # IMUs' own errors carried into the std


def _std(covariance: np.ndarray | None, block: slice, unit: float = 1.0) -> np.ndarray | None:
    """The std of a block of a covariance (None where there is none), times ``unit``."""
    return None if covariance is None else unit * np.sqrt(np.diag(covariance)[block])


@dataclass(frozen=True)
class SensorEstimate:
    """The estimate for one sensor IMU and how well the drive determines it."""

    status: str  # ok | partial | inconsistent | unobservable
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
    warnings: list[str] = field(default_factory=list)
    #: Information that needs no action (SPEC ``notes``): the IMUs' own errors estimated.
    notes: list[str] = field(default_factory=list)
    #: The model-consistency checks (SPEC ``checks``): name -> figures and ``pass``.
    checks: dict[str, dict[str, Any]] = field(default_factory=dict)
    time_offset_observable: bool = False
    #: The mount's tilt (rad per m/s^2), where the rigid-mount check estimated it.
    tilt_rad_per_mps2: np.ndarray | None = None
    #: The accelerometer's and the gyro's scale factors and non-orthogonality, and the gyro's
    #: g-sensitivity, where the drive shows them.
    accel_intrinsics: dict[str, Any] = field(default_factory=dict)
    gyro_intrinsics: dict[str, Any] = field(default_factory=dict)
    #: Per window used: start (s, grid clock), gyro and accelerometer residual RMS of the fit.
    window_residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: The statistical part of ``covariance``: what more driving shrinks (SPEC
    #: ``statistical_std``); the total adds failed checks, the box and the floors.
    statistical_covariance: np.ndarray | None = None
    #: The rate of the clock offset (s/s; ``time_offset_s`` is at the grid's origin) and its
    #: std, where estimated and shown (:mod:`.clock`).
    clock_drift: float | None = None
    clock_drift_std: float | None = None
    #: Where the mount moved during the log, in time order (:func:`mount_moves`); the estimate
    #: is of the windows after the last.
    moves: list[MountMove] = field(default_factory=list)
    #: The sensor estimated alone in each epoch that held motion (:mod:`.timeline`).
    timeline: list[Epoch] = field(default_factory=list)

    @property
    def statistical_rotation_std_deg(self) -> np.ndarray | None:
        return _std(self.statistical_covariance, ROTATION, np.degrees(1.0))

    @property
    def statistical_translation_std_m(self) -> np.ndarray | None:
        return _std(self.statistical_covariance, TRANSLATION)

    @property
    def rotation_std_deg(self) -> np.ndarray | None:
        return _std(self.covariance, ROTATION, np.degrees(1.0))

    @property
    def translation_std_m(self) -> np.ndarray | None:
        return _std(self.covariance, TRANSLATION)

    def lidar_covariance(self, T_imu_lidar: Transform) -> np.ndarray | None:
        """6x6 covariance of ``T_base_lidar = T_base_imu T_imu_lidar`` (rotation about base
        axes)."""
        if self.covariance is None:
            return None
        lever = self.T_base_imu.rotation.apply(T_imu_lidar.translation)
        J = np.eye(6)
        J[TRANSLATION, ROTATION] = -skew(lever)  # d(R t_IL) = [dtheta]x R t_IL = -[R t_IL]x dtheta
        return J @ self.covariance @ J.T


@dataclass(frozen=True)
class MountMove:
    """A move of the mount: when (s, grid clock) with its std, the pose before it
    (``T_base_imu``, from the base IMU, with its statistical std about the base axes) and how
    far it moved to the pose after it."""

    at_s: float
    at_std_s: float
    T_base_imu_before: Transform
    rotation_std_deg: np.ndarray
    translation_std_m: np.ndarray
    T_base_imu_after: Transform
    first_window: int  # the number of the first window after it (the one it lies in: not used)


#: A solve's start: the problem, the joint fit with the IMUs' own errors, and those errors.
Start = tuple[Problem, Fit, dict[str, dict[str, Any]]]


def started(
    windows: list[WindowMoments],
    prior: Transform,
    options: CalibrationOptions,
    clock: ClockEvidence,
    sigma: tuple[float, float],
    lowpass: Lowpass,
    dw_noise_var: float = 0.0,
) -> Start:
    """The joint fit of the extrinsics and the clock (:func:`_first_fit`) with the IMUs' own
    errors the drive shows (:func:`_own_errors`)."""
    problem = make_problem(windows, prior, options, sigma, lowpass, dw_noise_var)
    fit = _first_fit(problem, options, clock)
    prior_std = error_prior_std(GRADES[options.sensor_grade], GRADES[options.base_grade])
    fit, own = _own_errors(problem, fit, options, prior_std)
    return problem, fit, own


def mount_moves(start: Start, options: CalibrationOptions) -> list[MountMove]:
    """Where the mount moved during the log (:func:`.moves.find_moves`, at the configured
    false-alarm rate), each with the poses of the windows either side, from the fit with the
    IMUs' own errors (``start``: shared by every pose; left out, stretches of different
    driving differ by what those errors alias into the extrinsics); none searched where the
    clock is not followed (``max_clock_drift_ppm: 0``)."""
    problem, fit, _ = start
    if options.max_clock_drift_ppm <= 0 or len(problem.used) < 2 * MIN_SIDE_WINDOWS + 1:
        return []  # (one offset for the log: a drifting clock would look like a mount moving)

    def refit(mask: np.ndarray) -> Fit:
        return problem.fit(fit, fit.free, window_weights=mask.astype(float))

    found = find_moves(problem, fit, options.consistency_alpha, refit)
    edges = [-1, *(m.within for m in found), len(problem.used)]
    fits = []
    for a, b in pairwise(edges):  # the windows between two moves
        weights = np.zeros(len(problem.used))
        weights[a + 1 : b] = 1.0
        fits.append(_weak_at_prior(problem, refit(weights > 0), options, weights))
    out = []
    for move, before, after in zip(found, fits[:-1], fits[1:], strict=True):
        std = np.where(before.free, before.std(), options.translation_bound_m)
        out.append(
            MountMove(
                move.at_s,
                move.at_std_s,
                Transform(before.point.R, before.point.t),
                np.degrees(np.sqrt(np.clip(np.diag(before.rotation_covariance_base()), 0, None))),
                std[TRANSLATION],
                Transform(after.point.R, after.point.t),
                int(problem.used[move.within].number + problem.used[move.within].span),
            )
        )
    return out


def unobservable(prior: Transform, windows: list[WindowInfo], tau: float) -> SensorEstimate:
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
        warnings=[status.unobservable_reason(windows)],
    )


@dataclass(frozen=True)
class ClockEvidence:
    """What the boot's correlation found of the sensor's clock offset."""

    tau0_s: float  # its estimate: the windows are resampled at it
    shown: bool = True  # False: the correlation could not place it
    reason: str = ""  # why not


def bias_model(options: CalibrationOptions) -> BiasModel:
    """How the sensor's relative biases may drift and how large they may be (its options)."""
    return BiasModel(
        options.window_s,
        (options.gyro_bias_walk, ACCEL_BIAS_WALK),
        (options.gyro_bias_prior_std, ACCEL_BIAS_PRIOR_STD),
    )


def make_problem(
    windows: list[WindowMoments],
    prior: Transform,
    options: CalibrationOptions,
    sigma: tuple[float, float],
    lowpass: Lowpass,
    dw_noise_var: float,
) -> Problem:
    declared = error_prior_std(GRADES[options.sensor_grade], GRADES[options.base_grade])
    settings = Settings(
        prior.translation,
        options.translation_bound_m,
        bias_model(options),
        options.max_iterations,
        () if declared[BASE_GYRO_AXES].any() else ("base_gyro_axes",),
    )
    return Problem(windows, settings, sigma, lowpass, dw_noise_var)


def _first_fit(problem: Problem, options: CalibrationOptions, clock: ClockEvidence) -> Fit:
    """The joint fit of the extrinsics and the clock; translation axes the drive does not
    determine (std over a third of the box) are kept at the prior."""
    start = problem.start()
    start.free[TIME_OFFSET] = options.max_time_offset_s > 0 and clock.shown
    start.free[TRANSLATION] = problem.translation_information_diagonal() > 0  # above the noise
    try:
        fit = problem.fit(start, start.free, estimate_scale=True)
    except np.linalg.LinAlgError:  # the lever arm's information, noise taken off, is not positive
        start.free[TRANSLATION] = False
        fit = problem.fit(start, start.free, estimate_scale=True)
    return _weak_at_prior(problem, fit, options)


def _weak_at_prior(
    problem: Problem, fit: Fit, options: CalibrationOptions, weights: np.ndarray | None = None
) -> Fit:
    """``fit`` (of the windows ``weights`` keeps) with the translation axes it does not
    determine (std over a third of the box) kept at the prior, fitted again."""
    bound = OBSERVABLE_FRACTION_OF_BOUND * options.translation_bound_m
    weak = fit.free[TRANSLATION] & (fit.std()[TRANSLATION] >= bound)
    if not weak.any():
        return fit
    free = fit.free.copy()
    free[TRANSLATION] &= ~weak
    t = np.where(weak, problem.settings.translation_prior, fit.point.t)
    return problem.fit(replace(fit, point=replace(fit.point, t=t)), free, window_weights=weights)


def _own_errors(
    problem: Problem, fit: Fit, options: CalibrationOptions, prior_std: np.ndarray
) -> tuple[Fit, dict[str, dict[str, Any]]]:
    """The IMUs' own errors the drive shows (:func:`.checks.own_errors`, a stage of
    :func:`.checks.own_error_stages` at a time), each stage unless taking it in leaves a
    lever-arm axis the fit before determined undetermined (a short drive, or a base gyro's yaw
    scale that a flat drive cannot tell from the lever arm's length: the two then share what
    the drive shows); what is not taken in is carried."""
    found: dict[str, dict[str, Any]] = {}
    for groups in checks.own_error_stages(prior_std):
        after, tested = checks.own_errors(
            problem, fit, options.consistency_alpha, groups, prior_std
        )
        if not _keeps_lever_arm(fit, after, options):
            after, tested = fit, {n: group | {"estimated": False} for n, group in tested.items()}
        fit, found = after, found | tested
    return fit, found


def _keeps_lever_arm(before: Fit, after: Fit, options: CalibrationOptions) -> bool:
    """Whether every lever-arm axis ``before`` determined (std under a third of the box) is
    still determined in ``after``, a fit with more globals free."""
    bound = OBSERVABLE_FRACTION_OF_BOUND * options.translation_bound_m
    determined = before.free[TRANSLATION] & (before.std()[TRANSLATION] < bound)
    return bool(np.all(after.std()[TRANSLATION][determined] < bound))


def _clock(
    problem: Problem, fit: Fit, options: CalibrationOptions, clock: ClockEvidence
) -> tuple[Fit, bool, list[str]]:
    """The clock offset kept where the fit places it to :data:`TIME_OFFSET_MAX_STD_S`; else
    fixed (at the correlation's estimate). Returns the fit, whether it is placed, sentences."""
    if options.max_time_offset_s <= 0:
        return fit, True, []
    if not clock.shown:
        return fit, False, status.clock_sentence(False, clock.reason, None, clock.tau0_s)
    std = fit.std()[TIME_OFFSET]
    if not fit.free[TIME_OFFSET] or std <= TIME_OFFSET_MAX_STD_S:
        return fit, True, []
    free = fit.free.copy()
    free[TIME_OFFSET] = False
    refit = problem.fit(replace(fit, point=replace(fit.point, dtau=0.0)), free)
    return refit, False, status.clock_sentence(True, "", std, clock.tau0_s)


def solve(
    windows: list[WindowMoments],
    prior: Transform,
    options: CalibrationOptions,
    clock: ClockEvidence,
    sigma: tuple[float, float],
    lowpass: Lowpass,
    dw_noise_var: float = 0.0,
    given: tuple[checks.Check, ...] = (),
    start: Start | None = None,
) -> SensorEstimate:
    """The estimate from the selected windows' moments, its checks and honest covariance: the
    fit with the IMUs' own errors (``start``, else :func:`started`), the rigid mount, the clock,
    the rotation agreement, the residual levels, the covariance (:mod:`.uncertainty`).
    ``given``: checks made before (the base IMU's gravity), counted as the others."""
    if start is None:
        start = started(windows, prior, options, clock, sigma, lowpass, dw_noise_var)
    problem, fit, own = start
    alpha = options.consistency_alpha
    prior_std = error_prior_std(GRADES[options.sensor_grade], GRADES[options.base_grade])
    scale = checks.base_scale(own[checks.BASE_SCALE.name], fit)
    rigid, tilted = checks.rigid_mount(problem, fit, alpha)
    if not rigid.passed and _keeps_lever_arm(fit, tilted, options):
        fit = tilted  # (else the tilt and the lever arm share what the drive shows: kept out)
    fit, clock_placed, clock_notes = _clock(problem, fit, options, clock)
    later = [
        checks.rotation_agreement(problem, fit, alpha, prior_std[ACCEL_ROTATION]),
        checks.residual_level(problem, fit),
        checks.prior_rotation(fit.point.R, prior.rotation, options.rotation_bound_deg),
        *given,
        *([] if scale is None else [scale]),
    ]
    found = [rigid, *later]
    failed = [c for c in found if not c.passed]
    floors = (np.radians(options.rotation_floor_deg), options.translation_floor_m)
    base_housing = GRADES[options.base_grade].housing_rad
    spread = uncertainty(problem, fit, failed, floors, prior_std, base_housing)
    observable = fit.free[TRANSLATION].copy()
    warnings = [
        *status.check_sentences([rigid]),
        *clock_notes,
        *status.check_sentences(later),
        *status.uncertainty_sentences(
            spread, len(problem.used), prior.translation, options.translation_bound_m, observable
        ),
    ]
    return _estimate(
        problem,
        fit,
        windows,
        status.status(found, observable, clock_placed, spread),
        spread,
        observable,
        clock,
        clock_placed and options.max_time_offset_s > 0,  # (0: not estimated, not observed)
        warnings,
        found,
        own,
        sigma,
    )


def _estimate(
    problem: Problem,
    fit: Fit,
    windows: list[WindowMoments],
    verdict: str,
    spread: Any,
    observable: np.ndarray,
    clock: ClockEvidence,
    clock_placed: bool,
    warnings: list[str],
    found: list[checks.Check],
    own: dict[str, dict[str, Any]],
    sigma: tuple[float, float],
) -> SensorEstimate:
    """The :class:`SensorEstimate` of a solved problem."""
    last, n_total = problem.n_knots - 1, 3 * problem.samples
    gyro, accel = KNOT["gyro_bias"], KNOT["accel_bias"]
    bias_std = fit.bias_std
    per_window = 3 * problem.samples_per_window
    return SensorEstimate(
        status=verdict,
        T_base_imu=Transform(fit.point.R, fit.point.t),
        covariance=spread.covariance,
        statistical_covariance=spread.statistical,
        translation_observable=observable,
        time_offset_s=float(clock.tau0_s + fit.point.dtau) if clock.shown else 0.0,
        time_offset_std_s=spread.time_offset_std_s,
        gyro_bias=fit.knots[last, gyro].copy(),
        gyro_bias_std=bias_std[gyro] if bias_std is not None else None,
        accel_bias=fit.knots[last, accel].copy(),
        accel_bias_std=bias_std[accel] if bias_std is not None else None,
        bias_knots_s=problem.knot_numbers * problem.settings.biases.spacing_s,
        gyro_bias_knots=fit.knots[:, gyro].copy(),
        accel_bias_knots=fit.knots[:, accel].copy(),
        windows=[w.info for w in windows if w.info is not None],
        residual_rms_gyro=float(np.sqrt(max(fit.cost_g.sum(), 0.0) / n_total)),
        residual_rms_accel=float(np.sqrt(max(fit.cost_a.sum(), 0.0) / n_total)),
        iterations=fit.iterations,
        noise_std={"gyro_radps": sigma[0], "accel_mps2": sigma[1]},
        warnings=warnings,
        notes=status.own_error_sentences(own),
        checks={c.name: {**c.figures, "pass": c.passed} for c in found},
        time_offset_observable=clock_placed,
        tilt_rad_per_mps2=fit.point.tilt.copy(),
        accel_intrinsics=checks.axes_figures(own["accelerometer"]),
        gyro_intrinsics={
            **checks.axes_figures(own["gyro"]),
            "g_sensitivity": checks.g_sensitivity_figures(own["g-sensitivity"]),
        },
        window_residuals=np.column_stack(
            [
                [w.start_s for w in problem.used],
                np.sqrt(np.maximum(fit.cost_g, 0.0) / per_window),
                np.sqrt(np.maximum(fit.cost_a, 0.0) / per_window),
            ]
        ),
    )
