"""Every sensor's estimate from the windows a :class:`~.streaming.StreamingCalibrator` has
reduced so far (each sensor's is independent of the others'), with what reading and the boot
noted of its IMUs."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from imucal_cli.core.calibrate import ClockEvidence, SensorEstimate, solve, unobservable
from imucal_cli.core.clock import ClockTrack
from imucal_cli.core.status import drift_sentence, imu_notes, step_sentence, unsolved_sentence
from imucal_cli.core.streaming import StreamingCalibrator
from imucal_cli.types import Transform


def estimates(calibrator: StreamingCalibrator) -> dict[str, SensorEstimate]:
    """Every sensor's estimate from the windows reduced so far."""
    return {name: estimate(calibrator, name) for name in calibrator.sensors}


def estimate(calibrator: StreamingCalibrator, name: str) -> SensorEstimate:
    """Sensor ``name``'s estimate from the windows reduced so far."""
    c = calibrator
    setup, windows = c.sensors[name], c.moments(name)
    tau0, offset = c.tau0.get(name, 0.0), c.time_offsets.get(name)
    infos = [w.info for w in windows if w.info is not None]
    if not any(info.selected for info in infos):
        found = unobservable(setup.prior_T_base_imu, infos, tau0)
    else:
        clock = ClockEvidence(
            tau0, offset is None or offset.shown, offset.reason if offset is not None else ""
        )
        try:
            found = solve(
                windows,
                setup.prior_T_base_imu,
                setup.options,
                clock,
                c.sigma[name],
                c.lowpass,
                dw_noise_var=c.dw_noise_var,
                given=c.given_checks,
            )
        except np.linalg.LinAlgError as exc:  # the solver's to say, never the log's fault
            found = unobservable(setup.prior_T_base_imu, infos, tau0)
            found = replace(found, warnings=[unsolved_sentence(str(exc))])
    T = found.T_base_imu  # from the base IMU's position back to B's origin
    T = Transform(T.rotation, T.translation + c.t_base_baseimu)
    notes = [  # the units converted on the way, then each IMU's saturation and silences
        *(f"base: {w}" for w in c.unit_warnings.get(c.base_name, [])),
        *c.unit_warnings.get(name, []),
        *imu_notes(*_imu(c, c.base_name)),
        *imu_notes(*_imu(c, name)),
    ]
    found = replace(found, T_base_imu=T, warnings=notes + found.warnings)
    track = c.clocks.get(name)
    if track is None or found.covariance is None:
        return found
    return _with_drift(found, track)


def _with_drift(found: SensorEstimate, track: ClockTrack) -> SensorEstimate:
    """The estimate with its clock's drift, where the drive shows it, and its steps; where the
    windows were resampled along the track, the offset (at the grid's origin) is the track's."""
    fit = track.fit()
    if fit is None:
        return found
    warnings = [step_sentence(step) for step in track.steps]
    offset, offset_std = found.time_offset_s, found.time_offset_std_s
    if track.followed:
        offset = float(fit.at(np.zeros(1))[0])
        offset_std = float(np.sqrt(fit.var_at(np.zeros(1))[0]))
    drift = drift_std = None
    notes = list(found.notes)
    if fit.shown:
        drift, drift_std = fit.drift, float(np.sqrt(fit.drift_var))
        last = offset + drift * fit.span + sum(step.size_s for step in track.steps)
        notes += [drift_sentence(drift, drift_std, offset, last, track.followed)]
    return replace(
        found,
        time_offset_s=offset,
        time_offset_std_s=offset_std,
        clock_drift=drift,
        clock_drift_std=drift_std,
        warnings=[*found.warnings, *warnings],
        notes=[note for note in notes if note],
    )


def _imu(c: StreamingCalibrator, imu: str) -> tuple[Any, ...]:
    """What the notes of an IMU read: its topic, whether it is the base, its saturation, the
    factors that made it SI, and its silences."""
    return (
        c.labels[imu][0] or imu,
        imu == c.base_name,
        c.saturation[imu],
        c.scales.get(imu, (1.0, 1.0)),
        c.silences.get(imu, []),
    )
