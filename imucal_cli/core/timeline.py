"""The timeline: each sensor estimated alone in every epoch of the log (``epoch_s``), from the
same window moments as the whole log's estimate (moments add: no second pass over the data).

An epoch's estimate is a Gauss-Newton fit of its windows alone: the extrinsics and the clock
free (as the whole log's fit frees them), the IMUs' own errors and the mount's tilt held at the
whole log's fit (an epoch of driving rarely shows them, and they are one per IMU), the relative
biases its own. Its std is the fit's (the Fisher information, the residual scale from the
epoch's own residuals): what that epoch alone says. Epochs reduced once stay as they were
computed (:class:`EpochCache`): the follow mode's updates and a log's end solve only the
epochs that changed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from imucal_cli.core.model import SENSOR_ERRORS, TILT, TIME_OFFSET, TRANSLATION
from imucal_cli.core.moments import WindowMoments
from imucal_cli.core.solver import Fit, Problem
from imucal_cli.types import Transform

#: Fewest selected windows an epoch needs for an estimate of its own.
MIN_EPOCH_WINDOWS = 2


@dataclass(frozen=True)
class Epoch:
    """One epoch's estimate: the span of its windows (s, grid clock), how many it used, the
    pose (from the base IMU, as the solve makes it) with its std about the base axes, and the
    clock offset over the epoch (s; None where the log's fit does not estimate it)."""

    index: int
    start_s: float
    end_s: float
    windows: int
    T_base_imu: Transform
    rotation_std_deg: np.ndarray
    translation_std_m: np.ndarray
    time_offset_s: float | None


def epoch_of(window: WindowMoments, epoch_s: float) -> int:
    """The epoch a window belongs to: the one its middle lies in (grid clock)."""
    return int(np.floor(0.5 * (window.start_s + window.end_s) / epoch_s))


def epoch_estimate(
    index: int,
    windows: list[WindowMoments],
    whole: tuple[Problem, Fit],
    problem_of: Callable[[list[WindowMoments]], Problem],
    bound_m: float,
) -> Epoch | None:
    """The estimate of one epoch's windows alone, started from the log's ``fit``; None where
    it holds too few selected windows or its equations do not solve."""
    used = [w for w in windows if w.info is not None and w.info.selected]
    count = sum(w.count - w.left_out for w in used)  # (windows: old ones are merged)
    if count < MIN_EPOCH_WINDOWS:
        return None
    first = used[0].number  # its own bias knots: numbered from its first window
    problem = problem_of([replace(w, number=w.number - first) for w in used])
    log, fit = whole
    free = fit.free.copy()
    free[SENSOR_ERRORS] = False
    free[TILT] = False
    # the log's biases over the epoch, where its knots are the epoch's
    wanted = problem.knot_numbers + first
    if np.isin(wanted, log.knot_numbers).all():
        knots = fit.knots[np.searchsorted(log.knot_numbers, wanted)]
    else:
        knots = np.zeros((problem.n_knots, fit.knots.shape[1]))
    begin = Fit(fit.point, knots.copy(), free, fit.scale_g, fit.scale_a)
    try:
        found = problem.fit(begin, free)
    except np.linalg.LinAlgError:
        return None
    # the std at the epoch's own residual level (the fit weighs by the log's): the covariance
    # scales with the larger of the two equations' ratios
    samples = 3 * problem.samples
    ratio = max(
        np.sqrt(max(found.cost_g.sum(), 0.0) / samples) / fit.scale_g,
        np.sqrt(max(found.cost_a.sum(), 0.0) / samples + problem.eiv_variance(found.point.t))
        / fit.scale_a,
    )
    std = found.std() * ratio
    covariance = found.rotation_covariance_base() * ratio**2
    rotation_std = np.degrees(np.sqrt(np.clip(np.diag(covariance), 0, None)))
    offsets = np.mean([w.offset_s + w.shift_s for w in used])
    return Epoch(
        index,
        used[0].start_s,
        used[-1].end_s,
        count,
        Transform(found.point.R, found.point.t),
        rotation_std,
        np.where(free[TRANSLATION], std[TRANSLATION], bound_m),
        float(offsets + found.point.dtau) if free[TIME_OFFSET] else None,
    )


class EpochCache:
    """Each epoch's estimate, kept once every one of its windows has been reduced (its key: the
    windows it held), so that estimating again solves only the epochs that changed."""

    def __init__(self) -> None:
        self.epochs: dict[int, tuple[tuple[int, int], Epoch | None]] = {}

    def timeline(
        self,
        windows: list[WindowMoments],
        whole: tuple[Problem, Fit],
        problem_of: Callable[[list[WindowMoments]], Problem],
        epoch_s: float,
        bound_m: float,
    ) -> list[Epoch]:
        """The estimate of every epoch that held enough motion, in time order, each started
        from the log's fit (``whole``: its problem and fit); the last epoch (still filling while
        the log is read) is solved every time."""
        groups: dict[int, list[WindowMoments]] = {}
        for w in windows:
            groups.setdefault(epoch_of(w, epoch_s), []).append(w)
        # (epochs whose windows were merged into a neighbour's are gone: what is kept is bounded)
        self.epochs = {index: kept for index, kept in self.epochs.items() if index in groups}
        out = []
        last = max(groups, default=0)
        for index, members in sorted(groups.items()):
            key = (len(members), sum(w.info is not None and w.info.selected for w in members))
            kept = self.epochs.get(index)
            if kept is not None and kept[0] == key and index != last:
                epoch = kept[1]
            else:
                epoch = epoch_estimate(index, members, whole, problem_of, bound_m)
                self.epochs[index] = (key, epoch)
            if epoch is not None:
                out.append(epoch)
        return out
