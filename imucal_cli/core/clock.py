"""A sensor's clock offset followed through the drive: a lidar IMU stamped by its own oscillator
drifts from the base's clock by the crystal's error (10-100 ppm, 36-360 ms an hour), so one
offset for the whole log would leave residuals that grow with time.

Each window measures the offset still left after resampling (:func:`window_offsets`: the
sensor's rates against the base's turned by the block's own rotation, and the base's angular
acceleration), and
:class:`ClockTrack` fits ``offset(t) = tau + drift (t - t_mid)`` to them by weighted least
squares (sums only: memory flat in the log's length). The schedule resamples each block at
the track's prediction and, where a block's own measurements show the prediction off,
resamples it again at the corrected offsets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: The offset a block's measurements must show (beyond their 3 std) before it is resampled again.
MIN_CORRECTION_S = 5e-4
#: A window's clock measurement: its number, start (s), middle (s), offset (s), variance.
Row = tuple[int, float, float, float, float]
#: Windows whose measurements join a clock's line together: the calibrator's blocks.
GROUP_WINDOWS = 6
#: A clock offset (s) as a function of the grid's times (s).
Offset = Callable[[np.ndarray], np.ndarray]


def constant(value: float) -> Offset:
    """One offset for every time."""
    return lambda t: np.full(np.shape(t), value)


#: An offset off by more than this (s) is resampled again: the solve refines one offset for the
#: log only to first order.
MAX_LEVEL_S = 3e-3
#: A step of the clock is said where a new piece of the line stands off the last by this many
#: of the step's std and :data:`MIN_STEP_S`.
STEP_STD = 5.0
MIN_STEP_S = 1e-3
#: ... and where every window but the one holding it lies this close to the pieces of the line.
STEP_FIT_STD = 4.0
#: The drift is said (and followed) where the drive pins the change it makes over the log to
#: within this (s), as the offset itself (:data:`~.timing.TIME_OFFSET_MAX_STD_S`).
DRIFT_SHOWN_S = 2e-3


def window_offsets(
    w_B: np.ndarray,
    dw_B: np.ndarray,
    w_I: np.ndarray,
    valid: np.ndarray,
    at: list[tuple[int, int]],
    noise_gain: float,
) -> list[tuple[float, float] | None]:
    """Per window (rows ``i0 .. i0 + n``), the offset of the sensor's clock beyond the one it
    was resampled at and its variance, or None where the window does not show it.

    A sensor sample read ``delta`` too early is ``w_I(t) = R^T w_B(t - delta) + b``, so
    ``w_I - R^T w_B = b - delta R^T dw_B`` to first order, with ``R^T`` from the block's own
    rates (Kabsch/Horn, each side centred: the relative gyro bias taken off) and ``b`` per
    window; the variance is from the regression's own residuals, which the low-pass made
    correlated over ``1 / noise_gain`` samples (its white-noise gain)."""
    out: list[tuple[float, float] | None] = [None] * len(at)
    if np.count_nonzero(valid) < 10:
        return out
    a, b = w_I[valid], w_B[valid]
    U, _, Vt = np.linalg.svd((a - a.mean(axis=0)).T @ (b - b.mean(axis=0)))
    R_IB = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt  # w_I ~ R_IB w_B
    residual = w_I - w_B @ R_IB.T
    slope = -(dw_B @ R_IB.T)
    for k, (i0, n) in enumerate(at):
        keep = valid[i0 : i0 + n]
        m = int(np.count_nonzero(keep))
        if m < max(10, n // 2):
            continue
        r, g = residual[i0 : i0 + n][keep], slope[i0 : i0 + n][keep]
        # unknowns [b (3), delta]: the bias's columns are identities, so b = mean(r - delta g)
        g_centred, r_centred = g - g.mean(axis=0), r - r.mean(axis=0)
        energy = float(np.sum(g_centred * g_centred))
        if energy <= 0:
            continue
        delta = float(np.sum(g_centred * r_centred)) / energy
        left = r_centred - delta * g_centred
        variance = float(np.sum(left * left)) / max(3 * m - 4, 1) / energy / noise_gain
        if np.isfinite(variance) and variance > 0:
            out[k] = (delta, variance)
    return out


@dataclass(frozen=True)
class ClockFit:
    """The line through a track's measurements: one drift, a level per piece (a step of the
    clock starts a piece), and their variances (scaled by the fit's reduced chi-square where
    that is above 1: the measurements scatter more than their noise)."""

    drift: float  # s/s
    drift_var: float
    #: Per piece: (from s, mean time s, level at it s, its variance).
    pieces: tuple[tuple[float, float, float, float], ...]
    span: float  # s the measurements cover (as a uniform spread with their weights' variance)
    reduced_chi2: float = 1.0  # of the measurements about the line

    def _piece(self, t: np.ndarray) -> np.ndarray:
        starts = np.array([p[0] for p in self.pieces])
        return np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)

    def at(self, t: np.ndarray) -> np.ndarray:
        """The offset at ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        pieces = np.array(self.pieces)[self._piece(t)]
        return pieces[..., 2] + self.drift * (t - pieces[..., 1])

    def var_at(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        pieces = np.array(self.pieces)[self._piece(t)]
        return pieces[..., 3] + (t - pieces[..., 1]) ** 2 * self.drift_var

    @property
    def shown(self) -> bool:
        """Whether the drive pins the drift's change of the offset over the log (to
        :data:`DRIFT_SHOWN_S`)."""
        return float(np.sqrt(self.drift_var)) * self.span <= DRIFT_SHOWN_S


def _fits(fit: ClockFit, rows: list[Row], scale: float) -> bool:
    """Whether every one of ``rows`` lies within :data:`STEP_FIT_STD` of its std (its own
    and the line's, times ``scale``: how far the track's measurements scatter) of the line."""
    if not rows:
        return True
    t = np.array([row[2] for row in rows])
    y, variance = np.array([row[3] for row in rows]), np.array([row[4] for row in rows])
    std = np.sqrt(scale * (variance + fit.var_at(t)))
    return bool(np.all(np.abs(y - fit.at(t)) <= STEP_FIT_STD * std))


@dataclass(frozen=True)
class Step:
    """A step of a sensor's clock (re-synchronised): when (s, grid clock), by how much (s)."""

    at_s: float
    size_s: float
    std_s: float


@dataclass
class ClockTrack:
    """One sensor's clock offset through time (seconds of the grid clock): every window's
    measured offset, fitted with a line per piece between the clock's steps and one drift
    (:class:`ClockFit`; sums only). ``tau0``: the boot's offset, the windows' until the track
    stands off it; ``max_drift``: the largest drift allowed (s/s); 0 follows none."""

    tau0: float
    max_drift: float
    #: Per piece: its start (s) and the weighted sums w, w t, w t^2, w y, w t y, w y^2.
    pieces: list[tuple[float, np.ndarray]] = field(default_factory=lambda: [(-np.inf, np.zeros(6))])
    count: int = 0
    steps: list[Step] = field(default_factory=list)
    #: Whether windows were resampled at anything but ``tau0``.
    followed: bool = False
    _fitted: tuple[ClockFit | None] | None = field(default=None, repr=False, compare=False)
    #: This group's windows measured so far (:data:`GROUP_WINDOWS`).
    group: list[Row] = field(default_factory=list)
    #: Windows measured but not in the line yet, ``(number, start s, t s, offset s,
    #: variance)``: the last block's last ones, off the line (a step may lie in them).
    pending: list[Row] = field(default_factory=list)
    _reach: tuple[tuple[float, int, int, bool], float] | None = field(default=None, repr=False)

    def add(self, t: float, offset: float, variance: float) -> None:
        """A window's measured offset (s) at ``t`` (s), with its variance."""
        w = 1.0 / variance
        self.pieces[-1][1][:] += w * np.array([1.0, t, t * t, offset, t * offset, offset**2])
        self.count += 1
        self._fitted = None

    def measure(self, rows: list[Row]) -> list[int]:
        """Windows' measurements ``(number, start s, t s, offset s, variance)`` as they are
        reduced: they join the line a group of :data:`GROUP_WINDOWS` at a time (by window
        number), so that the line, and the offsets it predicts, are the same however the
        windows were reduced (in blocks, or one by one while following a recording). Returns
        the windows not to be used (:meth:`add_block`)."""
        unused = []
        for row in rows:
            if self.group and row[0] // GROUP_WINDOWS != self.group[0][0] // GROUP_WINDOWS:
                unused += self.flush()
            self.group.append(row)
        if self.group and self.group[-1][0] % GROUP_WINDOWS == GROUP_WINDOWS - 1:
            unused += self.flush()
        return unused

    def flush(self) -> list[int]:
        """The group so far into the line (the log ended, or the group is whole)."""
        group, self.group = self.group, []
        return self.add_block(group) if group else []

    def add_block(self, rows: list[Row]) -> list[int]:
        """A block's windows' measurements ``(number, start s, t s, offset s, variance)``, a
        step of the clock found first (:meth:`find_step`, over the windows held back from the
        last block and these): returns the windows that may hold it or were resampled before
        it was found (not to be used; none without a step). Without a step, the block's last
        windows (two at most) that lie off the line are held back for the next block."""
        sequence, held = [*self.pending, *rows], len(self.pending)
        self.pending = []
        found = self.find_step(sequence)
        if found is None:
            held_back = self._off_the_line(sequence)
            for row in sequence[: len(sequence) - held_back]:
                self.add(*row[2:])
            self.pending = sequence[len(sequence) - held_back :]
            return []
        straddler, size, std = found
        for row in sequence[:straddler]:
            self.add(*row[2:])
        start = sequence[straddler + 1][1]
        self.steps.append(Step(start, size, std))
        self.new_piece(start)
        for row in sequence[straddler + 1 :]:
            self.add(*row[2:])
        resampled_before = {row[0] for row in sequence[straddler:held]}
        return sorted(resampled_before | {sequence[straddler][0], sequence[straddler + 1][0]})

    def _off_the_line(self, sequence: list[Row]) -> int:
        """How many of the last two windows of ``sequence`` lie off the line through the track
        and the windows before them (the last, or both; an off window followed by one on the
        line is a window of its own, kept)."""
        if len(sequence) < 2:
            return 0
        trial = self._copy()
        for row in sequence[:-2]:
            trial.add(*row[2:])
        fit = trial.fit()
        if fit is None or _fits(fit, sequence[-1:], 1.0):
            return 0
        return 1 if _fits(fit, sequence[-2:-1], 1.0) else 2

    def _copy(self) -> ClockTrack:
        trial = ClockTrack(self.tau0, self.max_drift)
        trial.pieces = [(start, sums.copy()) for start, sums in self.pieces]
        trial.count = self.count
        return trial

    def fit(self) -> ClockFit | None:
        """The line through the measurements; None before two (or with no drift followed).
        Kept until a measurement or a piece is added: the schedule asks it at every batch."""
        if self._fitted is None:
            self._fitted = (self._fit(),)
        return self._fitted[0]

    def _fit(self) -> ClockFit | None:
        if self.count < 2 or self.max_drift <= 0:
            return None
        sums = np.array([s for _, s in self.pieces if s[0] > 0])
        W, Wt, Wtt, Wy, Wty, Wyy = sums.T
        t_mid, level = Wt / W, Wy / W
        Stt, Sty = Wtt - W * t_mid**2, Wty - t_mid * Wy
        if Stt.sum() <= 0:
            return None
        drift = float(np.clip(Sty.sum() / Stt.sum(), -self.max_drift, self.max_drift))
        chi2 = float(np.sum(Wyy - W * level**2 - 2 * drift * Sty + drift**2 * Stt))
        dof = self.count - len(sums) - 1
        scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
        starts = [start for start, s in self.pieces if s[0] > 0]
        pieces = tuple(
            (float(a), float(m), float(v), scale / float(w))
            for a, m, v, w in zip(starts, t_mid, level, W, strict=True)
        )
        span = 2.0 * np.sqrt(3.0 * Stt.sum() / W.sum())
        reduced = chi2 / dof if dof > 0 else 1.0
        return ClockFit(drift, scale / float(Stt.sum()), pieces, float(span), reduced)

    def find_step(self, sequence: list[Row]) -> tuple[int, float, float] | None:
        """Where windows' measurements (not yet in the line) show the clock stepped: the window
        that holds the step, such that a new piece of the line (the drift shared) fits every
        window after it, at least two, with a step beyond :data:`STEP_STD` of its std and
        :data:`MIN_STEP_S`, and every other window lies on its piece; of several, the one whose
        line fits best. Returns (the window's place in ``sequence``, the step, its std)."""
        base = self.fit()
        scale = max(1.0, base.reduced_chi2) if base is not None else 1.0
        best: tuple[float, int, float, float] | None = None
        for straddler in range(len(sequence) - 2):
            trial = self._copy()
            for row in sequence[:straddler]:
                trial.add(*row[2:])
            if trial.pieces[-1][1][0] <= 0:  # nothing before it: no line to step from
                continue
            trial.new_piece(sequence[straddler + 1][1])
            for row in sequence[straddler + 1 :]:
                trial.add(*row[2:])
            fit = trial.fit()
            if fit is None or len(fit.pieces) < 2:
                continue
            (_, mid_old, old, var_old), (_, mid_new, new, var_new) = fit.pieces[-2:]
            step = new - old + fit.drift * (mid_old - mid_new)
            std = float(np.sqrt(var_old + var_new + (mid_old - mid_new) ** 2 * fit.drift_var))
            significant = abs(step) > max(STEP_STD * std, MIN_STEP_S)
            others = [*sequence[:straddler], *sequence[straddler + 1 :]]
            better = best is None or fit.reduced_chi2 < best[0]
            if significant and better and _fits(fit, others, scale):
                best = (fit.reduced_chi2, straddler, step, std)
        return None if best is None else best[1:]

    def new_piece(self, at_s: float) -> None:
        """What follows ``at_s`` is a new piece of the line (the clock stepped there)."""
        self.pieces.append((at_s, np.zeros(6)))
        self._fitted = None

    def predictor(self, t_block: np.ndarray) -> Offset:
        """The offsets to resample a block (its times ``t_block``, s) at, as a function of
        time fixed now: the line, once the clock is seen to change (:meth:`changes`), else
        ``tau0``."""
        fit = self.fit()
        if fit is not None and (self.followed or self.changes(fit, t_block)):
            self.followed = True
            return fit.at
        return constant(self.tau0)

    def reach(self, t: float) -> float:
        """How far (s) the offset a block is resampled at stands from 0 at ``t``: the
        predictor's, kept until the track changes (the schedule asks at every batch)."""
        key = (t, self.count, len(self.pieces), self.followed)
        if self._reach is None or self._reach[0] != key:
            at = np.array([t])
            self._reach = (key, abs(float(self.predictor(at)(at)[0])))
        return self._reach[1]

    def changes(self, fit: ClockFit, t: np.ndarray) -> bool:
        """Whether the clock's offset changes, beyond what the fit's one offset (the solver's
        to refine) takes: a step, a drift beyond 3 std that moves the offset by
        :data:`MIN_CORRECTION_S` over the measurements, or the line off ``tau0`` at ``t`` by
        more than :data:`MAX_LEVEL_S`."""
        drift_std = float(np.sqrt(fit.drift_var))
        drifts = abs(fit.drift) > 3.0 * drift_std and abs(fit.drift) * fit.span > MIN_CORRECTION_S
        level = np.abs(fit.at(np.asarray(t, dtype=np.float64)) - self.tau0) > MAX_LEVEL_S
        return bool(self.steps) or drifts or bool(np.any(level))

    def correction(self, t: np.ndarray, used: np.ndarray) -> Offset | None:
        """The line, as a function of time fixed now, where the clock changes
        (:meth:`changes`) and the line stands off the offsets ``used`` at times ``t`` beyond a
        level (the solver's one offset takes that) by more than its 3 std and
        :data:`MIN_CORRECTION_S`, or by :data:`MAX_LEVEL_S`; else None."""
        fit = self.fit()
        if fit is None or not (self.followed or self.changes(fit, t)):
            return None
        t = np.asarray(t, dtype=np.float64)
        off = fit.at(t) - used
        shape = np.abs(off - off.mean()) > np.maximum(
            3.0 * np.sqrt(fit.var_at(t)), MIN_CORRECTION_S
        )
        if not (np.any(shape) or np.any(np.abs(off) > MAX_LEVEL_S)):
            return None
        self.followed = True
        return fit.at
