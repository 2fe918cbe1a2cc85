"""The reported covariance: what the fit's Fisher information says, made honest.

The inverse Fisher information (the residual variance from the fit, corrected for the
low-pass's correlation of neighbouring residuals) is inflated per axis to a delete-a-group
jackknife over the windows where that spreads more, then by the checks that fail; a
translation axis on its box gets the distance to where the data pull it, an axis the drive does
not determine the box's own variance; what the IMUs' own errors the fit holds at zero would
move (their grades' priors) and the config's systematic floors are added.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.checks import Check, rotation_difference
from imucal_cli.core.model import EXTRINSICS, ROTATION, SENSOR_ERRORS, TIME_OFFSET, TRANSLATION
from imucal_cli.core.so3 import skew
from imucal_cli.core.solver import Fit, Problem

#: Delete-a-group jackknife: at most this many groups of consecutive windows.
JACKKNIFE_GROUPS = 10
#: Fewest windows whose jackknife checks the std (the status needs it). Two windows still give
#: a spread (each window alone, one degree of freedom): the std is inflated to it, never
#: shrunk, but it checks nothing.
JACKKNIFE_MIN_WINDOWS = 3
#: Gauss-Newton steps of a replicate, from the full fit (the one-step jackknife): a tenth of
#: the windows left out moves the optimum little, and one step from the full fit lands within
#: second order of it. Replicates converged to 1e-10 rad took 10 steps each and three
#: quarters of the solve's time.
JACKKNIFE_ITERATIONS = 1
#: Gauss-Newton steps of a replicate that leaves half the windows out.
MAX_REPLICATE_ITERATIONS = 10


def jackknife(problem: Problem, fit: Fit) -> np.ndarray | None:
    """Delete-a-group jackknife covariance (7x7: rotation about the base axes, t, tau) of the
    fit's free globals over groups of consecutive windows, or None with fewer than 2 windows.
    It sees what the Fisher information cannot: residuals correlated over seconds, and errors
    that differ from window to window. With two windows a replicate is the other window alone,
    far from the full fit: it is iterated to convergence."""
    K = len(problem.used)
    if K < 2:
        return None
    steps = JACKKNIFE_ITERATIONS if K >= JACKKNIFE_MIN_WINDOWS else MAX_REPLICATE_ITERATIONS
    replicates = []
    for group in np.array_split(np.arange(K), min(K, JACKKNIFE_GROUPS)):
        weights = np.ones(K)
        weights[group] = 0.0
        try:
            rep = problem.fit(fit, fit.free, window_weights=weights, max_iterations=steps)
        except np.linalg.LinAlgError:  # the group held all a sensor's error was known from:
            held = fit.free.copy()  # the replicate keeps the errors at the fit's values
            held[SENSOR_ERRORS] = False
            rep = problem.fit(fit, held, window_weights=weights, max_iterations=steps)
        replicates.append(
            np.concatenate(
                [
                    rotation_difference(rep.point.R, fit.point.R),
                    rep.point.t - fit.point.t,
                    [rep.point.dtau - fit.point.dtau],
                ]
            )
        )
    reps = np.array(replicates)
    G = len(reps)
    centred = reps - reps.mean(axis=0)
    return (G - 1) / G * centred.T @ centred


@dataclass(frozen=True)
class Uncertainty:
    """The reported covariance and what went into it."""

    covariance: np.ndarray  # 6x6: rotation about the base axes (rad), t_base_imu (m)
    #: The statistical part (6x6): the Fisher information's, inflated to the jackknife's
    #: spread; what more driving shrinks. The total adds what the drive cannot resolve: failed
    #: checks, the box, the floors.
    statistical: np.ndarray
    time_offset_std_s: float | None
    jackknifed: bool  # False: too few windows to check the std against the data's spread
    on_box: np.ndarray  # (3,) bool: translation axes resting on their box
    pulls_m: np.ndarray  # (3,) how much further the data pull each axis on the box


def carried(problem: Problem, fit: Fit, prior_std: np.ndarray) -> np.ndarray:
    """What the errors the fit holds at zero (not free, with a prior std in ``prior_std``, per
    global) add to the extrinsics' covariance (6x6, rotation about the base axes): the
    consider covariance ``K P K^T``, ``K = I_ff^-1 I_fc`` the free globals' response to the
    held ones (``I`` the Fisher information of both at the fit), ``P`` their prior."""
    held = ~fit.free & (prior_std > 0)
    if not held.any():
        return np.zeros((6, 6))
    both = fit.free | held
    information = problem.information(fit, both)
    in_both = np.flatnonzero(both)
    f, c = fit.free[in_both], held[in_both]
    response = np.linalg.solve(information[np.ix_(f, f)], information[np.ix_(f, c)])
    spread = np.zeros((len(prior_std), len(prior_std)))
    spread[np.ix_(fit.free, fit.free)] = (response * prior_std[held] ** 2) @ response.T
    return _to_base(fit, spread[EXTRINSICS, EXTRINSICS])[:TIME_OFFSET, :TIME_OFFSET]


def turned_frame(t: np.ndarray, std: float) -> np.ndarray:
    """What a rotation of the base IMU's frame against B (``std`` rad per axis: its alignment
    to its housing, which no drive sees) does to an estimate (6x6, rotation about the base
    axes, translation): the rotation turns by it and the lever arm ``t`` with it, ``dt = rho x
    t = -[t]x rho``."""
    J = np.vstack([np.eye(3), -skew(t)])
    return std**2 * J @ J.T


def _to_base(fit: Fit, covariance: np.ndarray) -> np.ndarray:
    """A 7x7 covariance of the extrinsics and the clock with the rotation about base axes."""
    to_base = np.eye(7)
    to_base[ROTATION, ROTATION] = fit.point.R.as_matrix()
    return to_base @ covariance @ to_base.T


def fisher_extrinsics(fit: Fit) -> np.ndarray:
    """The Fisher covariance of the extrinsics and the clock (7x7), rotation about base axes."""
    return _to_base(fit, fit.covariance[EXTRINSICS, EXTRINSICS])


def uncertainty(
    problem: Problem,
    fit: Fit,
    failed: Sequence[Check],
    floors: tuple[float, float],
    prior_std: np.ndarray | None = None,
    base_housing_std: float = 0.0,
) -> Uncertainty:
    """The covariance to report (module docstring); ``floors``: the systematic std of the
    rotation (rad) and the translation (m) the data cannot see; ``prior_std``: the IMUs' own
    errors' prior (per global, :func:`~imucal_cli.core.grades.error_prior_std`), what of them
    the fit holds at zero carried into the total (:func:`carried`); ``base_housing_std``: the
    base IMU's alignment to its housing (rad per axis, :func:`turned_frame`)."""
    free7 = fit.free[EXTRINSICS]
    fisher = fisher_extrinsics(fit)
    fisher_std = np.sqrt(np.clip(np.diag(fisher), 0.0, None))
    spread = jackknife(problem, fit)
    inflation = np.ones(7)
    if spread is not None:
        jk_std = np.sqrt(np.clip(np.diag(spread), 0.0, None))
        scale = np.where(fisher_std[free7] > 0, fisher_std[free7], np.inf)
        inflation[free7] = np.maximum(1.0, jk_std[free7] / scale)
    cov7 = inflation[:, None] * fisher * inflation[None, :]
    statistical = cov7[:TIME_OFFSET, :TIME_OFFSET].copy()
    if failed:
        cov7 *= max(c.inflation for c in failed)
        for check in failed:  # what each measured of the error
            if check.cover is not None:
                cov7[:TIME_OFFSET, :TIME_OFFSET] += check.cover
    prior, bound = problem.settings.translation_prior, problem.settings.translation_bound_m
    t_free = fit.free[TRANSLATION]
    on_box = t_free & (np.abs(fit.point.t - prior) >= bound * (1.0 - 1e-6))
    pulls = np.where(on_box, np.abs(fit.unconstrained_t - fit.point.t), 0.0)
    for axis in np.flatnonzero(on_box).tolist():  # the std covers where the data pull it
        cov7[TRANSLATION.start + axis, TRANSLATION.start + axis] += pulls[axis] ** 2
    for axis in np.flatnonzero(~t_free).tolist():  # not determined: the box's own variance
        cov7[TRANSLATION.start + axis, TRANSLATION.start + axis] = bound**2 / 3.0
        statistical[TRANSLATION.start + axis, TRANSLATION.start + axis] = bound**2 / 3.0
    cov6 = cov7[:TIME_OFFSET, :TIME_OFFSET].copy()
    if prior_std is not None:
        cov6 += carried(problem, fit, prior_std)
    cov6 += turned_frame(fit.point.t, base_housing_std)
    cov6[ROTATION, ROTATION] += floors[0] ** 2 * np.eye(3)
    cov6[TRANSLATION, TRANSLATION] += floors[1] ** 2 * np.eye(3)
    tau_std = float(np.sqrt(cov7[TIME_OFFSET, TIME_OFFSET])) if fit.free[TIME_OFFSET] else None
    checked = spread is not None and len(problem.used) >= JACKKNIFE_MIN_WINDOWS
    return Uncertainty(cov6, statistical, tau_std, checked, on_box, pulls)
