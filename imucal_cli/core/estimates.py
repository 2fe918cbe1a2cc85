"""Every sensor's estimate from the windows a :class:`~.streaming.StreamingCalibrator` has
reduced so far (each sensor's is independent of the others'), with what reading and the boot
noted of its IMUs."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from imucal_cli.core.calibrate import (
    ClockEvidence,
    SensorEstimate,
    make_problem,
    mount_moves,
    solve,
    started,
    unobservable,
)
from imucal_cli.core.clock import ClockTrack
from imucal_cli.core.moments import WindowMoments
from imucal_cli.core.status import (
    drift_sentence,
    imu_notes,
    step_sentence,
    unsolved_sentence,
)
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
    track = c.clocks.get(name)
    infos = [w.info for w in windows if w.info is not None]
    if not any(info.selected for info in infos):
        found = unobservable(setup.prior_T_base_imu, infos, tau0)
    else:
        clock = ClockEvidence(
            tau0, offset is None or offset.shown, offset.reason if offset is not None else ""
        )
        line = track.fit() if track is not None and track.followed else None
        for w in windows:  # the track's offset beyond the one each was resampled at
            middle = np.array([0.5 * (w.start_s + w.end_s)])
            w.shift_s = 0.0 if line is None else float(line.at(middle)[0]) - w.offset_s
        try:
            found = _solved(c, name, windows, clock)
        except np.linalg.LinAlgError as exc:  # the solver's to say, never the log's fault
            found = unobservable(setup.prior_T_base_imu, infos, tau0)
            found = replace(found, warnings=[unsolved_sentence(str(exc))])
    T = _in_b(c, found.T_base_imu)
    notes = [  # the units converted on the way, then each IMU's saturation and silences
        *(f"base: {w}" for w in c.unit_warnings.get(c.base_name, [])),
        *c.unit_warnings.get(name, []),
        *imu_notes(*_imu(c, c.base_name)),
        *imu_notes(*_imu(c, name)),
    ]
    found = replace(found, T_base_imu=T, warnings=notes + found.warnings)
    if track is None or found.covariance is None:
        return found
    since = found.moves[-1].first_window if found.moves else 0
    used = [w for w in windows if w.info is not None and w.info.selected and w.number >= since]
    return _with_drift(found, track, used, tau0)


def _solved(
    c: StreamingCalibrator, name: str, windows: list[WindowMoments], clock: ClockEvidence
) -> SensorEstimate:
    """The estimate of the windows after the mount's last move (every window where it did
    not move), with the moves (:func:`~.calibrate.mount_moves`) where a rigid pose each side
    explains the data."""
    setup = c.sensors[name]
    args = (setup.prior_T_base_imu, setup.options, clock, c.sigma[name], c.lowpass)
    start = started(windows, *args, c.dw_noise_var)
    moves = mount_moves(start, setup.options)
    now = [w for w in windows if not moves or w.number >= moves[-1].first_window]
    # the fit of the pose the vehicle has now: the windows after the last move
    last = started(now, *args, c.dw_noise_var) if moves else start
    found = solve(now, *args, dw_noise_var=c.dw_noise_var, given=c.given_checks, start=last)
    # a move is said only where a rigid pose each side explains the data: every stretch
    # between the moves consistent on its own (else what moved is not the mount: a model
    # the data break, which one estimate of every window says)
    starts = [0, *(m.first_window for m in moves)]
    stretches = [
        [w for w in windows if first <= w.number and w.number + w.span < move.first_window]
        for first, move in zip(starts, moves, strict=False)
    ]
    if moves and (
        found.status == "inconsistent"
        or any(_inconsistent(stretch, c, name, clock) for stretch in stretches)
    ):
        moves, last = [], start
        found = solve(
            windows, *args, dw_noise_var=c.dw_noise_var, given=c.given_checks, start=start
        )
    moves = [
        replace(
            m,
            T_base_imu_before=_in_b(c, m.T_base_imu_before),
            T_base_imu_after=_in_b(c, m.T_base_imu_after),
        )
        for m in moves
    ]
    opts, epochs = setup.options, c.epochs[name]
    timeline = epochs.timeline(
        windows,
        last[:2],  # (the IMUs' own errors of the pose now: a blend of poses would bias them)
        lambda part: make_problem(part, *args[:2], *args[3:], c.dw_noise_var),
        opts.epoch_s,
        opts.translation_bound_m,
    )
    timeline = [replace(e, T_base_imu=_in_b(c, e.T_base_imu)) for e in timeline]
    return replace(found, moves=moves, timeline=timeline)


def _in_b(c: StreamingCalibrator, T_base_imu: Transform) -> Transform:
    """A pose the solve made from the base IMU's position, from B's origin."""
    return Transform(T_base_imu.rotation, T_base_imu.translation + c.t_base_baseimu)


def _inconsistent(
    windows: list[WindowMoments], c: StreamingCalibrator, name: str, clock: ClockEvidence
) -> bool:
    """Whether the windows fail a model-consistency check, estimated on their own."""
    if not any(w.info is not None and w.info.selected for w in windows):
        return False
    setup = c.sensors[name]
    try:
        found = solve(
            windows,
            setup.prior_T_base_imu,
            setup.options,
            clock,
            c.sigma[name],
            c.lowpass,
            dw_noise_var=c.dw_noise_var,
        )
    except np.linalg.LinAlgError:
        return True
    return found.status == "inconsistent"


def _with_drift(
    found: SensorEstimate, track: ClockTrack, windows: list[WindowMoments], tau0: float
) -> SensorEstimate:
    """The estimate with its clock's drift, where the drive shows it, and its steps; where the
    windows were resampled along the track, the offset (at the grid's origin) is the track's."""
    fit = track.fit()
    if fit is None:
        return found
    warnings = [step_sentence(step) for step in track.steps]
    offset, offset_std = found.time_offset_s, found.time_offset_std_s
    if track.followed and found.time_offset_observable and windows:
        # the track, at the level the solve placed (its one offset is beyond the track's)
        offset = float(fit.at(np.zeros(1))[0]) + found.time_offset_s - tau0
        middle = float(np.mean([0.5 * (w.start_s + w.end_s) for w in windows]))
        offset_std = float(
            np.sqrt((found.time_offset_std_s or 0.0) ** 2 + middle**2 * fit.drift_var)
        )
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
