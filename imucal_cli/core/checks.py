"""Tests of the model on the data, each a figure and a verdict (the sentences: :mod:`status`).

- the sensor's own errors (each triad's axis errors, the gyro's g-sensitivity): estimated where
  the drive determines them and a chi-square test finds them;
- the rigid mount: a tilt with the vehicle's specific force (chi-square, 2 dof);
- the rotation from the gyro alone against the one from the accelerometer alone (3 dof);
- the residual levels against the noise the data imply.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from imucal_cli.core.model import (
    ACCEL_ROTATION,
    AXIS_ERRORS,
    BASE_GYRO_AXES,
    N_PARAMETERS,
    PARAMETERS,
    ROTATION,
    SENSOR_ERRORS,
    TILT,
    TRANSLATION,
)
from imucal_cli.core.solver import Fit, Problem
from imucal_cli.types import GRAVITY_MPS2, rotation_type

SCALE, SKEW = AXIS_ERRORS["scale"], AXIS_ERRORS["nonorthogonality"]
#: How far the base IMU's mean specific force may lean from B's z axis (deg).
BASE_GRAVITY_MAX_DEG = 15.0
#: The check holds where the mean is gravity's size: a base that turns over and over about a
#: level axis (a wheel's hub) averages gravity away, and its mean has no direction to test.
BASE_GRAVITY_MIN_FRACTION = 0.5
#: Residual std over the noise the data imply, above which the model does not explain the data.
RESIDUAL_LEVEL_MAX = 2.0
#: What the grid's interpolation and filtering leave of a signal, relative to its RMS about each
#: window's mean: a residual level counts only above it. (Noise-free drives leave 1e-4 of the
#: gyro's and 3e-4 of the accelerometer's.)
PIPELINE_FLOOR = 1e-3
#: A triad's axis errors are estimated where the drive determines them this well (1% of scale,
#: 0.6 deg of non-orthogonality).
INTRINSICS_MAX_STD = 0.01
#: The gyro's g-sensitivity likewise (rad/s per m/s^2): 0.1 deg/s per g, a MEMS part's.
G_SENSITIVITY_MAX_STD = np.radians(0.1) / GRAVITY_MPS2
#: What the checks take as numerically zero (rad, and rad per m/s^2): on noise-free data the
#: Fisher std is round-off, and so is any difference the checks see.
NUMERICAL_ZERO = 1e-6
#: The largest scale error a gyro has (relative): uncalibrated MEMS parts read up to 10-15%
#: off. A fit that asks for more is not finding a scale but a model that fails (aliased
#: motion, saturation, a mount that moves): the lever arm's terms do not scale as one.
BASE_SCALE_PLAUSIBLE = 0.25
#: The prior (rad) that keeps a rotation one equation alone leaves free defined.
ROTATION_PRIOR = np.zeros(N_PARAMETERS)
ROTATION_PRIOR[ROTATION] = 1.0
#: The prior std on each own error while the drive is asked which it determines: a hundred
#: times the std they are estimated to, it moves a determined one by a ten-thousandth.
PROBE_PRIOR_STD = 1.0
#: The probe's prior on the base gyro's axis errors alone.
BASE_AXES_PROBE = np.where(PARAMETERS.mask("base_gyro_axes"), PROBE_PRIOR_STD, 0.0)


@dataclass(frozen=True)
class Errors:
    """A group of own errors tested together (:func:`own_errors`): its name in the notes, its
    block of :data:`PARAMETERS`, the std a component must be determined to for it to be
    estimated, whether the grades' prior alone keeps it, and the largest scale such a part
    reads (None: no bound)."""

    name: str
    block: str
    max_std: float
    expected_by_prior: bool = True
    plausible_scale: float | None = None

    @property
    def which(self) -> slice:
        return PARAMETERS[self.block]

    def plausible(self, value: np.ndarray) -> bool:
        """Whether no scale among the group's values (its one value, or a triad's three) is
        beyond :attr:`plausible_scale`."""
        scales = value if len(value) == 1 else value[SCALE]
        return self.plausible_scale is None or np.abs(scales).max() <= self.plausible_scale


#: The sensor's own errors, in groups each tested apart.
OWN_ERRORS = (
    Errors("accelerometer", "accel_axes", INTRINSICS_MAX_STD),
    Errors("gyro", "gyro_axes", INTRINSICS_MAX_STD),
    Errors("g-sensitivity", "g_sensitivity", G_SENSITIVITY_MAX_STD),
)
#: The accelerometer triad's misalignment to the gyro's: estimated with the others where the
#: grades declared allow one (with ``ideal`` IMUs a disagreement is the rotation check's).
MISALIGNMENT = Errors("misalignment", "accel_rotation", INTRINSICS_MAX_STD)
#: The base gyro's scale error, tested after the sensor's errors: in the gyro's equation it is
#: the sensor gyro's common scale, only the lever arm's terms tell it apart. Left out where
#: the test finds it, it scales every lever arm by as much: it is taken in wherever the drive
#: determines it to 5% (a rear lidar 1 m from the base IMU determines it to 1-1.5%).
BASE_SCALE = Errors("base gyro scale", "base_gyro_scale", 0.05, False, BASE_SCALE_PLAUSIBLE)
#: The base gyro's axis errors (its axes' scales and non-orthogonality, beyond the common
#: scale), tested last where the base's grade declares them (an ``ideal`` base has none: a
#: tilting mount's terms are not taken for them): each is taken in wherever the drive
#: determines it to 5% and a chi-square test finds them.
BASE_AXES = Errors("base gyro", "base_gyro_axes", 0.05, False, BASE_SCALE_PLAUSIBLE)


@dataclass(frozen=True)
class Check:
    """One model-consistency test of the estimate (SPEC ``checks``)."""

    name: str
    passed: bool
    figures: dict[str, Any]
    #: Variance inflation the failed check calls for (1 where it passed).
    inflation: float = 1.0
    #: What the failed check measured of the estimate's error, added to its covariance (6x6:
    #: rotation about base axes, translation), or None.
    cover: np.ndarray | None = None


def chi2_limit(dof: int, alpha: float) -> float:
    """The chi-square quantile a false alarm rate ``alpha`` allows (``chi2.ppf(1 - alpha)``,
    from ``scipy.special``: ``scipy.stats`` takes 0.8 s to import)."""
    from scipy.special import chdtri

    return float(chdtri(dof, alpha))


def _chi2(value: np.ndarray, covariance: np.ndarray) -> float:
    """``v^T C^-1 v``, what is below :data:`NUMERICAL_ZERO` counting as zero."""
    regular = covariance + NUMERICAL_ZERO**2 * np.eye(len(value))
    return float(value @ np.linalg.solve(regular, value))


def rotation_difference(a: Any, b: Any) -> np.ndarray:
    """Rotation vector of ``a b^-1`` (about the base axes)."""
    return (a * b.inv()).as_rotvec()


def _zeroed(fit: Fit, which: np.ndarray) -> Fit:
    """The fit with the own errors ``which`` (a mask over :data:`PARAMETERS`) at zero."""
    errors = np.where(which[SENSOR_ERRORS], 0.0, fit.point.errors)
    return replace(fit, point=replace(fit.point, errors=errors))


def own_error_stages(prior_std: np.ndarray | None) -> tuple[tuple[Errors, ...], ...]:
    """The IMUs' own errors in the order they are tested (:func:`own_errors`, a stage at a
    time): the sensor's (the triads' misalignment too where the grades' prior allows one), then
    the base gyro's common scale, then its axes."""
    sensor: tuple[Errors, ...] = OWN_ERRORS
    if prior_std is not None and prior_std[MISALIGNMENT.which].any():
        sensor = (*OWN_ERRORS, MISALIGNMENT)
    return sensor, (BASE_SCALE,), (BASE_AXES,)


def own_errors(
    problem: Problem,
    fit: Fit,
    alpha: float,
    groups: tuple[Errors, ...],
    prior_std: np.ndarray | None = None,
) -> tuple[Fit, dict[str, dict[str, Any]]]:
    """Own errors (``groups``, those the problem may free) from one joint fit beside what
    ``fit`` frees: the components the drive determines to their group's std (a probe under a
    loose prior asks which), a group kept where a chi-square test at ``alpha`` finds it, or
    the grades' prior (``prior_std``) expects it, and no scale beyond its plausible one is
    asked for. Returns the fit (with the groups kept) and per group ``estimated`` and, where
    any component was determined, ``chi2``, ``dof``, ``value`` and ``std`` (NaN: not
    determined); ``implausible`` and the ``joint`` fit where a scale was beyond it."""
    found: dict[str, dict[str, Any]] = {g.name: {"estimated": False} for g in groups}
    groups = tuple(g for g in groups if problem.may_free(g.block))
    estimable = PARAMETERS.mask(*(g.block for g in groups)) & ~fit.free
    max_std = np.zeros(N_PARAMETERS)
    for g in groups:
        max_std[g.which] = g.max_std
    if not estimable.any():
        return fit, found
    try:
        # (a loose prior: an error the drive does not determine, the y scale of a gyro that
        # only ever turns about x, leaves the equations singular without one)
        probe = problem.fit(
            fit, fit.free | estimable, prior_std=np.where(estimable, PROBE_PRIOR_STD, 0.0)
        )
        shown = estimable & (probe.std() <= max_std)
        if not shown.any():
            return fit, found
        joint = problem.fit(_zeroed(probe, estimable & ~shown), fit.free | shown)
    except np.linalg.LinAlgError:  # the drive does not tell them from what is free
        return fit, found
    kept = fit.free.copy()
    for g in groups:
        group = shown[g.which]
        if not group.any():
            continue
        value = joint.point.own(g.which)
        chi2 = _chi2(value[group], joint.covariance[g.which, g.which][np.ix_(group, group)])
        expected = g.expected_by_prior and prior_std is not None and bool(prior_std[g.which].any())
        present = expected or chi2 > chi2_limit(int(group.sum()), alpha)
        plausible = g.plausible(value)
        found[g.name] = {
            "estimated": bool(present and plausible),
            "chi2": chi2,
            "dof": int(group.sum()),
            "value": value.copy(),
            "std": np.where(group, joint.std()[g.which], np.nan),
        }
        if present and not plausible:  # kept out (a failed check where it is the base's scale)
            found[g.name] |= {"implausible": True, "joint": joint}
        kept[g.which] = group & present & plausible
    if np.array_equal(kept, fit.free):
        return fit, found
    if np.array_equal(kept, fit.free | shown):
        return joint, found
    return problem.fit(_zeroed(joint, shown & ~kept), kept), found


def base_scale(found: dict[str, Any], fit: Fit) -> Check | None:
    """The base gyro's scale as :func:`own_errors` found it, where the fit asked for one no
    gyro has (:data:`BASE_SCALE_PLAUSIBLE`): a failed check that covers the estimate's move
    between ``fit`` (the scale held) and the fit that took it. None where it did not."""
    if not found.get("implausible"):
        return None
    joint: Fit = found["joint"]
    delta = rotation_difference(joint.point.R, fit.point.R)
    dt = joint.point.t - fit.point.t
    cover = np.zeros((6, 6))
    cover[ROTATION, ROTATION] = np.outer(delta, delta)
    cover[TRANSLATION, TRANSLATION] = np.outer(dt, dt)
    figures = {
        "scale": float(found["value"][0]),
        "std": float(found["std"][0]),
        "chi2": float(found["chi2"]),
        "dof": 1,
        "plausible": BASE_SCALE_PLAUSIBLE,
    }
    return Check("base_gyro_scale", False, figures, 1.0, cover)


def rigid_mount(problem: Problem, fit: Fit, alpha: float) -> tuple[Check, Fit]:
    """The mount's tilt with the vehicle's specific force, with the sensor's errors found in
    the model (an accelerometer's scale factors look like a tilt where they are not). Where
    the problem may free the base gyro's axes (its grade declares them) and the fit holds
    them, the tilt is tested
    with them free as well: a base gyro's yaw scale the own errors' test did not take in
    scales the centripetal term as a tilt with the lateral force would. Returns the check and
    the fit with the tilt estimated (the estimate where the check fails: the tilting mount's,
    at rest)."""
    with_tilt = fit.free.copy()
    with_tilt[TILT] = True
    tilted = tested = problem.fit(fit, with_tilt)
    if problem.may_free("base_gyro_axes") and not fit.free[BASE_GYRO_AXES].any():
        with_tilt[BASE_GYRO_AXES] = True  # (a loose prior keeps what the drive leaves defined)
        try:
            tested = problem.fit(fit, with_tilt, prior_std=BASE_AXES_PROBE)
        except np.linalg.LinAlgError:  # a drive too poor for them: the tilt tested alone
            pass
    k, cov_k = tested.point.tilt, tested.covariance[TILT, TILT]
    chi2 = _chi2(k, cov_k)
    figures = {
        "tilt_deg_per_mps2": np.degrees(k).tolist(),
        "std": np.degrees(np.sqrt(np.diag(cov_k))).tolist(),
        "chi2": chi2,
        "dof": 2,
    }
    return Check("rigid_mount", chi2 <= chi2_limit(2, alpha), figures), tilted


def rotation_agreement(
    problem: Problem, fit: Fit, alpha: float, misalignment_std: np.ndarray | None = None
) -> Check:
    """The rotation from the gyro alone against the one from the accelerometer alone: one
    linear step each from the joint solution (a direction one equation alone leaves free stays
    put, with its large covariance, instead of wandering off). Where the triads' misalignment
    is not estimated, the grades' prior on it (``misalignment_std``, rad per axis) is a
    disagreement the model allows."""
    rotation_only = PARAMETERS.mask("rotation")
    by_gyro = problem.fit(
        fit, rotation_only, use=(True, False), max_iterations=1, prior_std=ROTATION_PRIOR
    )
    # the free globals the accelerometer holds, but the clock and its own rotation
    accel_only = fit.free & PARAMETERS.mask(
        "rotation",
        "translation",
        "tilt",
        "accel_axes",
        "base_gyro_scale",
        "base_gyro_axes",
        "base_accel_axes",
    )
    by_accel = problem.fit(
        fit, accel_only, use=(False, True), max_iterations=1, prior_std=ROTATION_PRIOR
    )
    delta = rotation_difference(by_accel.point.R, by_gyro.point.R)
    allowed = np.zeros((3, 3))
    if misalignment_std is not None and not fit.free[ACCEL_ROTATION].any():
        allowed = np.diag(np.square(misalignment_std))
    chi2 = _chi2(
        delta, by_gyro.rotation_covariance_base() + by_accel.rotation_covariance_base() + allowed
    )
    figures = {"chi2": chi2, "dof": 3, "difference_deg": float(np.degrees(np.linalg.norm(delta)))}
    passed = chi2 <= chi2_limit(3, alpha)
    return Check(
        "gyro_vs_accel_rotation",
        passed,
        figures,
        1.0,
        None if passed else _cover(problem, fit, delta),
    )


def _cover(problem: Problem, fit: Fit, delta: np.ndarray) -> np.ndarray:
    """What a rotation discrepancy ``delta`` (base axes) between the gyro and the accelerometer
    measures of the estimate's error: the rotation may be either equation's (``delta``), and
    the lever arm moves by as much as refitting it at the gyro's rotation moves it. Added to
    the covariance (``delta delta^T`` and ``dt dt^T``): the std then covers the discrepancy the
    check saw, not a token share of it."""
    free = fit.free.copy()
    free[ROTATION] = False
    turned = replace(fit.point, R=rotation_type().from_rotvec(-delta / 2.0) * fit.point.R)
    try:
        refit = problem.fit(replace(fit, point=turned), free)
    except np.linalg.LinAlgError:  # the rotation held, the IMUs' errors are not determined:
        free[SENSOR_ERRORS] = False  # held at their estimates
        refit = problem.fit(replace(fit, point=turned), free)
    dt = 2.0 * (refit.point.t - fit.point.t)  # (half the discrepancy each way)
    cover = np.zeros((6, 6))
    # along delta the discrepancy itself; across it the triads' common turn against the housing
    # that no data show, as large per axis as a misalignment that size
    cover[ROTATION, ROTATION] = np.outer(delta, delta) + delta @ delta / 3.0 * np.eye(3)
    cover[TRANSLATION, TRANSLATION] = np.outer(dt, dt)
    return cover


def residual_level(problem: Problem, fit: Fit) -> Check:
    """The residuals' std of the fit reported (``fit``, with the IMUs' own errors it took in)
    against the noise the data imply (and what the pipeline leaves)."""
    noise = np.array(problem.sigma) * np.sqrt(problem.gain)
    expected = np.hypot(noise, PIPELINE_FLOOR * np.array(problem.signal_rms))
    n = 3 * problem.samples
    levels = np.sqrt([max(fit.cost_g.sum(), 0.0) / n, max(fit.cost_a.sum(), 0.0) / n]) / expected
    passed = bool(np.all(levels <= RESIDUAL_LEVEL_MAX))
    figures = {
        "gyro": float(levels[0]),
        "accel": float(levels[1]),
        # the level the residuals are held to (per grid sample, after the low-pass)
        "expected_gyro_radps": float(expected[0]),
        "expected_accel_mps2": float(expected[1]),
    }
    return Check("residual_level", passed, figures, float(max(1.0, np.max(levels) ** 2)))


def base_gravity(mean_f: np.ndarray) -> Check:
    """The base IMU's mean specific force (in B's axes, as ``base.T_base_imu`` turns it) against
    B's z axis: a drive's mean is gravity within a few degrees (roads slope, vehicles lean), so
    an INS on its side or upside down that the config does not declare shows here (a yaw about
    gravity does not)."""
    norm = float(np.linalg.norm(mean_f))
    angle = float(np.degrees(np.arccos(np.clip(mean_f[2] / norm, -1.0, 1.0)))) if norm else 180.0
    if norm < BASE_GRAVITY_MIN_FRACTION * GRAVITY_MPS2:  # (turning over and over: no test)
        return Check("base_gravity", True, {"angle_deg": None, "mean_mps2": norm})
    return Check("base_gravity", angle <= BASE_GRAVITY_MAX_DEG, {"angle_deg": angle})


def prior_rotation(R_base_imu: Any, prior_R_base_imu: Any, bound_deg: float) -> Check:
    """The estimate's rotation against the prior's (SPEC ``rotation_bound_deg``): a CAD prior is
    a few degrees off, an IMU frame turned 180 deg from what the config or the log's tree says
    (an Ouster ``T_imu_lidar`` without its yaw, a driver whose IMU ``frame_id`` is the lidar's)
    is not; the data then place the IMU right and the lidar wrong, by the same turn."""
    angle = float(np.degrees(np.linalg.norm(rotation_difference(R_base_imu, prior_R_base_imu))))
    return Check("prior_rotation", angle <= bound_deg, {"angle_deg": angle, "bound_deg": bound_deg})


def axes_figures(found: dict[str, Any]) -> dict[str, Any]:
    """A triad's axis errors as the calibrate document gives them."""
    if "value" not in found:
        return found
    value, std = found["value"], found["std"]
    return {
        "estimated": found["estimated"],
        "chi2": found["chi2"],
        "dof": found["dof"],
        "scale": value[SCALE].tolist(),
        "nonorthogonality_deg": np.degrees(value[SKEW]).tolist(),
        "scale_std": std[SCALE].tolist(),
        "nonorthogonality_std_deg": np.degrees(std[SKEW]).tolist(),
    }


def g_sensitivity_figures(found: dict[str, Any]) -> dict[str, Any]:
    """The gyro's g-sensitivity ``G`` (the IMU's axes) in deg/s per g."""
    if "value" not in found:
        return found
    per_g = np.degrees(1.0) * GRAVITY_MPS2
    return {
        "estimated": found["estimated"],
        "chi2": found["chi2"],
        "dof": found["dof"],
        "dps_per_g": (per_g * found["value"]).reshape(3, 3).tolist(),
        "std_dps_per_g": (per_g * found["std"]).reshape(3, 3).tolist(),
    }
