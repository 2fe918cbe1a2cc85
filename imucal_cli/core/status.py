"""The status of an estimate and every sentence the estimator says, from the figures.

``ok``: every check passed, every axis determined, the clock placed, the std checked against
the data's spread. ``inconsistent``: a check failed. ``partial``: the rest of a result.
``unobservable``: no window with enough motion (the prior is returned).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from imucal_cli.core.checks import SCALE, SKEW, Check
from imucal_cli.core.segments import WindowInfo
from imucal_cli.core.timing import TIME_OFFSET_MAX_STD_S
from imucal_cli.core.uncertainty import Uncertainty
from imucal_cli.types import GRAVITY_MPS2


def status(
    checks: Sequence[Check], observable: np.ndarray, clock_placed: bool, spread: Uncertainty
) -> str:
    """ok, partial or inconsistent (see the module's text)."""
    if any(not c.passed for c in checks):
        return "inconsistent"
    if not observable.all() or spread.on_box.any() or not clock_placed or not spread.jackknifed:
        return "partial"
    return "ok"


def unobservable_reason(windows: Sequence[WindowInfo]) -> str:
    """Why no window was selected: gaps in the data (dropped or missing samples), or motion."""
    broken = sum(w.count for w in windows if not w.valid)  # (old windows merged: each counts)
    total = sum(w.count for w in windows)
    if windows and broken == total:
        return (
            f"every window ({broken}) has a gap in the data (samples missing or dropped): "
            "the prior is returned"
        )
    if broken:
        return (
            f"no window carried enough motion ({broken} of {total} have a gap in the "
            "data): the prior is returned"
        )
    return "no window carried enough motion: the prior is returned"


def own_error_sentences(found: dict[str, dict[str, Any]]) -> list[str]:
    """The sensor's own errors the model took in: of each group, the components the drive
    determined (``-``: held)."""
    out = []
    for name, group in found.items():
        if not group["estimated"]:
            continue
        value, shown = group["value"], ~np.isnan(group["std"])
        angle = [f"{v:+.3f}" if s else "-" for v, s in zip(np.degrees(value), shown, strict=True)]
        if name == "g-sensitivity":
            what = "gyro g-sensitivity"
            detail = f"largest {np.degrees(np.max(np.abs(value))) * GRAVITY_MPS2:.3f} deg/s per g"
        elif name == "misalignment":
            what = "the accelerometer triad's misalignment to the gyro's"
            detail = ", ".join(angle) + " deg"
        elif name == "base gyro scale":
            what = "the base gyro's scale error"
            detail = f"{100 * value[0]:+.2f}% (it scales the lever arm's terms)"
        else:
            what = f"{name} axis errors"
            scale = [f"{100 * v:+.2f}%" if s else "-" for v, s in zip(value, shown, strict=True)]
            parts = [("scale ", scale[SCALE], ""), ("non-orthogonality ", angle[SKEW], " deg")]
            detail = "; ".join(
                f"{label}{', '.join(values)}{unit}"
                for label, values, unit in parts
                if values != ["-"] * 3
            )
        out.append(
            f"{what} estimated with the extrinsics: {detail} "
            f"(chi2 {group['chi2']:.0f}, {group['dof']} dof)"
        )
    return out


def check_sentences(checks: Sequence[Check]) -> list[str]:
    """What each failed check means."""
    out = []
    for check in checks:
        if check.passed:
            continue
        f = check.figures
        if check.name == "rigid_mount":
            roll, pitch = f["tilt_deg_per_mps2"]
            out.append(
                f"the mount is not rigid: it tilts {roll:.3f} deg (roll) and {pitch:.3f} deg "
                "(pitch) per m/s^2 of the vehicle's lateral and longitudinal specific force "
                f"(chi2 {f['chi2']:.1f}, 2 dof); the rotation given is the mount's at rest"
            )
        elif check.name == "gyro_vs_accel_rotation":
            out.append(
                f"the gyro and the accelerometer disagree on the rotation by "
                f"{f['difference_deg']:.3f} deg (chi2 {f['chi2']:.1f}, 3 dof): their axes are "
                "misaligned differently, or the mount moves"
            )
        elif check.name == "base_gravity":
            out.append(
                f"the base IMU's gravity lies {f['angle_deg']:.1f} deg from B's z axis: the base "
                "IMU is not posed as the config says (base.T_base_imu), and every estimate is "
                "turned with it"
            )
        elif check.name == "base_gyro_scale":
            out.append(
                f"the lever arms' terms ask for a base gyro scale error of {f['scale']:+.0%} "
                f"(chi2 {f['chi2']:.0f}, 1 dof), more than any gyro has: the model does not "
                "hold (aliased or saturated motion, a moving mount); the estimate is given "
                "without it, its std covering the difference"
            )
        elif check.name == "prior_rotation":
            out.append(
                f"the data put the IMU {f['angle_deg']:.0f} deg from its prior (rotation_bound_deg "
                f"{f['bound_deg']:g}): check T_imu_lidar and the IMU's frame_id; the lidar's pose "
                "is as wrong as they are"
            )
        elif check.name == "residual_level":
            out.append(
                f"residuals {f['gyro']:.1f}x (gyro) and {f['accel']:.1f}x (accelerometer) the "
                "noise the data imply: the model does not explain the data (units, a moving "
                "mount, a time-varying offset?)"
            )
    return out


def clock_sentence(shown: bool, reason: str, std_s: float | None, tau0_s: float) -> list[str]:
    """Why the clock offset was not estimated: the correlation could not place it (``shown``
    False, ``reason``), or the fit's std ``std_s`` was too large (kept at ``tau0_s``)."""
    if not shown:
        why = reason or "the drive does not show it"
        return [f"clock offset not observable ({why}): not estimated, kept at 0"]
    if std_s is not None:
        return [
            f"clock offset not observable: std {std_s * 1e3:.1f} ms > "
            f"{TIME_OFFSET_MAX_STD_S * 1e3:g} ms; kept at the correlation's {tau0_s * 1e3:.1f} ms"
        ]
    return []


def uncertainty_sentences(
    spread: Uncertainty, windows: int, prior_t: np.ndarray, bound: float, observable: np.ndarray
) -> list[str]:
    """Too few windows for the jackknife, axes on their box, axes kept at the prior."""
    out = []
    if not spread.jackknifed:
        out.append(
            f"only {windows} window(s) with enough motion: too few to check the std "
            "against the data's spread"
        )
    for axis in np.flatnonzero(spread.on_box).tolist():
        out.append(
            f"translation {'xyz'[axis]} rests on its box (prior {prior_t[axis]:+.3f} +- "
            f"{bound:g} m): the data pull it {spread.pulls_m[axis]:.3f} m further; the prior may "
            "be wrong"
        )
    if not observable.all():
        missing = ", ".join("xyz"[a] for a in np.flatnonzero(~observable))
        out.append(f"translation {missing} not determined by the drive: kept at the prior")
    return out


def unsolved_sentence(why: str) -> str:
    """The solve failed on windows with motion (a factorisation the data leave singular)."""
    return (
        f"the drive's equations for this sensor could not be solved ({why}): the motion "
        "does not determine its pose as the model states it; the prior is returned"
    )


#: What driving supplies information about each axis (the lever arm enters through
#: ``([w]x^2 + [dw]x) t``: x and y through the yaw rate and its changes, z through roll and pitch).
MANOEUVRES = {
    "rotation x (roll)": "roll motion: crossfall, speed bumps, turns taken briskly",
    "rotation y (pitch)": "pitch motion: braking and accelerating, speed bumps",
    "rotation z (yaw)": "turns in both directions",
    "translation x": "turns in both directions and changes of turn rate (slalom, roundabouts)",
    "translation y": "turns in both directions and changes of turn rate (slalom, roundabouts)",
    "translation z": "roll and pitch motion: speed bumps, crossfall, braking and accelerating",
}


def every_axis_missing() -> list[str]:
    """Nothing determined yet: every axis, with the driving that supplies it."""
    return [f"{axis}: {what}" for axis, what in MANOEUVRES.items()]


def missing_axes(estimate: Any, stop: Any) -> list[str]:
    """The axes whose std is not yet within the ``stop:`` targets, each with the driving that
    supplies it: from the estimate's statistical std (what more driving shrinks)."""
    if estimate.statistical_covariance is None:
        return every_axis_missing()
    # the statistical std: what more driving shrinks (the total adds what it cannot)
    rotation = estimate.statistical_rotation_std_deg
    translation = estimate.statistical_translation_std_m
    assert rotation is not None and translation is not None
    names = list(MANOEUVRES)
    out = [
        f"{names[k]}: {MANOEUVRES[names[k]]} (std {rotation[k]:.3g} deg, target "
        f"{stop.max_rotation_std_deg:g})"
        for k in range(3)
        if rotation[k] > stop.max_rotation_std_deg
    ]
    out += [
        f"{names[3 + k]}: {MANOEUVRES[names[3 + k]]} (std {translation[k]:.3g} m, target "
        f"{stop.max_translation_std_m:g})"
        for k in range(3)
        if translation[k] > stop.max_translation_std_m or not estimate.translation_observable[k]
    ]
    return out


def imu_notes(
    topic: str,
    is_base: bool,
    saturation: Any,
    scales: tuple[float, float],
    silences: list[list[float | None]],
) -> list[str]:
    """What an estimate says of one of its IMUs: where it saturates, and where it stopped
    while the others went on."""
    notes = [
        f"{topic}: the {triad_name} saturates at {triad.level * scale:.4g} {unit} "
        f"({triad.readings} readings there): the windows that hold one are not used"
        for triad, triad_name, unit, scale, saturates in zip(
            saturation.triads,
            ("gyro", "accelerometer"),
            ("rad/s", "m/s^2"),
            scales,
            saturation.saturated(scales),
            strict=True,
        )
        if saturates
    ]
    for start, end in silences:
        notes.append(
            f"{topic} sent nothing from {start:.1f} s"
            + (f" to {end:.1f} s" if end is not None else " to the end of the log")
            + " while the other IMUs went on: the windows there are not used for "
            + ("any sensor" if is_base else "this sensor")
        )
    return notes


def drift_sentence(drift: float, std: float, first: float, last: float, followed: bool) -> str:
    """A note on a clock that drifts from the base's (s/s, its std), with its offset at the
    grid's origin and a span later (s); none where it does not drift beyond 3 std."""
    if not followed or abs(drift) <= 3.0 * std:
        return ""
    return (
        f"clock drifts {1e6 * drift:+.1f} +- {1e6 * std:.1f} ppm against the base's (offset "
        f"{1e3 * first:+.2f} ms at the start, {1e3 * last:+.2f} ms at the end): followed"
    )


def step_sentence(step: Any) -> str:
    """A warning on a clock that stepped (a :class:`~.clock.Step`)."""
    return (
        f"clock stepped by {1e3 * step.size_s:+.1f} +- {1e3 * step.std_s:.1f} ms at "
        f"{step.at_s:.0f} s (re-synchronised?): followed; the windows around it not used"
    )


def move_sentence(at_s: float, at_std_s: float, rotation_deg: float, translation_m: float) -> str:
    """A warning on a mount that moved during the log."""
    return (
        f"the mount moved at {at_s:.0f} +- {at_std_s:.0f} s by {rotation_deg:.2f} deg and "
        f"{1e3 * translation_m:.1f} mm (a knock? a loose bracket?): its pose and status are of "
        "the data after it"
    )
