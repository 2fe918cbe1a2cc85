"""Per-IMU rests and biases without any other sensor (paper section IV-C, eqs. 5-9), streamed.

- Samples are summed into short blocks (:data:`BLOCK_S`): count, mean and spread of the
  accelerometer and the gyro. Memory: a few numbers a block that holds samples, about 2 MB an
  hour of samples, whatever the span of their stamps.
- Rest (eq. 5, with a test that does not depend on the bias it is about to estimate): blocks
  whose mean specific force is within ``accel_tolerance`` of its mean over the second around,
  and whose mean gyro magnitude is within ``gyro_tolerance``, held for ``min_duration_s``. An
  accelerometer bias of any size leaves the test unchanged (the paper's ``|R^T g - f|`` fails
  at rest for a bias past the tolerance).
  Statistics use each rest without its first and last :data:`REST_EDGE_S` seconds
  (:data:`BASE_REST_EDGE_S` for the base gyro's bias that ``calibrate`` takes off).
- Accelerometer bias and noise at each rest (eq. 6). At one rest pose only the
  gravity-parallel component of the bias separates from tilt, so the bias given here is that
  component, ``(|mean f| - g)`` along ``mean f``; ``calibrate`` gives the full vector relative to
  the base IMU.
- Gyro bias (eqs. 7-9): the mean of the first rest, then a Kalman filter with random-walk
  process noise ``Q`` and each rest's samples as measurements (``y = w``, ``H = I``), updated
  once per rest in information form (the bias random walk within a rest is neglected).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imucal_cli.core.signals import true_runs
from imucal_cli.types import GRAVITY_MPS2

#: Seconds of samples summed into one block.
BLOCK_S = 0.1
#: Blocks on each side of a block whose mean is its reference in the rest test.
LOCAL_BLOCKS = 5
#: Seconds dropped at each end of a rest before averaging (settling, creeping off).
REST_EDGE_S = 1.0
#: Seconds dropped at each end of a rest before the base gyro's bias is taken from it: the body
#: still pitches and rolls on its suspension there (a simulated town drive's rests, about the
#: level axes: 3.5e-4 rad/s rms of error with 1 s off each end, 3e-5 with 3 s).
BASE_REST_EDGE_S = 3.0
#: A rest's specific force turned beyond the accelerometer's noise (chi-square of the turn
#: about two level axes, 1 in 1,000).
TURN_CHI2 = -2.0 * np.log(1e-3)
#: A turn of a rest's specific force that no bias would be wrong by (rad): over the shortest
#: rest's middle, 2 s, 5e-6 rad/s.
TURN_FLOOR_RAD = 1e-5
#: Blocks behind the newest that samples may still come for (reordering): judged later.
SETTLE_BLOCKS = 100
#: Blocks held before the tracker judges those it can (10 minutes; 13 numbers a block).
JUDGE_BLOCKS = 6000
# block sums: n, then sum and sum of squares of (accel - reference) and (gyro - reference)
_N, _FA, _FA2, _W, _W2 = 0, slice(1, 4), slice(4, 7), slice(7, 10), slice(10, 13)


@dataclass(frozen=True)
class RestPeriod:
    start_s: float  # seconds from the IMU's first sample
    end_s: float
    accel_bias: np.ndarray  # (3,) gravity-parallel component, m/s^2
    accel_noise_std: np.ndarray  # (3,) m/s^2
    gyro_mean: np.ndarray  # (3,) rad/s
    gyro_noise_var: np.ndarray  # (3,) per-sample variance, (rad/s)^2
    samples: int
    accel_up: np.ndarray = field(
        default_factory=lambda: np.array([0.0, 0.0, 1.0])
    )  # (3,) mean f / |mean f|
    #: The specific force kept its direction from the rest's first second to its last, within
    #: the accelerometer's noise (:data:`TURN_CHI2`): the body did not tilt (air suspension
    #: levelling, a bus kneeling, a load) or creep, and the rates about the level axes are bias.
    level: bool = True

    @property
    def accel_bias_along_gravity(self) -> float:
        """The bias along the measured specific force (up): ``|mean f| - g``, m/s^2."""
        return float(np.sum(self.accel_bias * self.accel_up))


@dataclass(frozen=True)
class BiasReport:
    """What one IMU alone says about its biases."""

    first_ns: int  # the IMU's first stamp: rest times count from it
    rest_periods: list[RestPeriod]
    accel_bias: np.ndarray  # (3,) from the last rest (eq. 6 keeps it until the next one)
    accel_noise_std: np.ndarray  # (3,)
    gyro_bias_initial: np.ndarray  # (3,) eq. 7: the mean of the first rest (zero without one)
    gyro_bias_final: np.ndarray  # (3,)
    gyro_bias_track_std: np.ndarray  # (3,) spread of the tracked bias over the log (time-weighted)
    gyro_bias_final_std: np.ndarray  # (3,) sqrt(diag P) at the end

    @property
    def warnings(self) -> list[str]:
        if self.rest_periods:
            return []
        return [
            "no rest found: the accelerometer bias is zero and its noise the median spread of "
            "short blocks, the gyro bias its prior"
        ]


class BiasTracker:
    """One IMU's rests and biases; feed samples in time order with :meth:`add`, then
    :meth:`report`. Blocks are judged (rest or not) once no sample can still come for them
    (:data:`SETTLE_BLOCKS`) and no rest spans them, and are then let go: memory follows the
    longest rest, not the log's length or the span of its stamps (a clock that jumps a year
    costs nothing)."""

    def __init__(
        self,
        accel_tolerance: float,
        gyro_tolerance: float,
        min_duration_s: float,
        process_noise: float,
        initial_std: float,
        edge_s: float = REST_EDGE_S,
    ) -> None:
        self.accel_tolerance, self.gyro_tolerance, self.min_duration_s = (
            accel_tolerance,
            gyro_tolerance,
            min_duration_s,
        )
        self.edge_s = edge_s
        self.process_noise, self.initial_std = process_noise, initial_std
        self.first_ns: int | None = None
        self.reference = np.zeros(6)  # the first sample: sums of squares about it keep their digits
        self._blocks: list[np.ndarray] = []  # per batch: the blocks it fills (ascending) ...
        self._sums: list[np.ndarray] = []  # ... and their sums (rows of 13)
        self._rests: list[RestPeriod] = []  # found in the blocks judged
        self._judged_to = 0  # the blocks before this one are judged (and those kept, context)
        self._spreads: list[
            np.ndarray
        ] = []  # the judged blocks' accelerometer spread, while no rest is found (the fallback)
        self._last_block = -1
        self._rows = 0  # blocks held (about: before merging)
        self._next_judge = JUDGE_BLOCKS

    def add(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        if not len(t_ns):
            return
        if self.first_ns is None:
            self.first_ns = int(t_ns.min())
            self.reference = np.concatenate([accel[0], gyro[0]])
        block = np.maximum((t_ns - self.first_ns) // int(BLOCK_S * 1e9), 0)
        late = block < self._judged_to  # (later than the settling allows: not placed)
        if late.any():
            block, gyro, accel = block[~late], gyro[~late], accel[~late]
            if not len(block):
                return
        a, w = accel - self.reference[:3], gyro - self.reference[3:]
        self._add(block, np.column_stack([np.ones(len(block)), a, a * a, w, w * w]))
        self._last_block = max(self._last_block, int(block.max()))
        self._rows += len(self._blocks[-1])
        if self._rows > self._next_judge or len(self._blocks) > 256:  # (the lists stay short)
            self._rows = len(self.blocks()[0])
            if self._rows > self._next_judge:
                self._judge(final=False)
                self._rows = len(self.blocks()[0])
                self._next_judge = (
                    self._rows + JUDGE_BLOCKS
                )  # (a long rest held: not judged again at once)

    def _add(self, block: np.ndarray, columns: np.ndarray) -> None:
        low, high = int(block.min()), int(block.max()) + 1
        if high - low <= 4 * len(block) + 64:  # the usual batch: blocks side by side
            index, blocks = block - low, np.arange(low, high)
        else:  # stamps far apart (a clock jump): the blocks they fill, not the span between
            blocks, index = np.unique(block, return_inverse=True)
        sums = np.column_stack(
            [np.bincount(index, columns[:, k], len(blocks)) for k in range(columns.shape[1])]
        )
        filled = sums[:, _N] > 0
        self._blocks.append(blocks[filled])
        self._sums.append(sums[filled])

    def blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """The blocks held (ascending: those not judged yet, and the context before them) and
        their sums, merged over every batch."""
        if not self._blocks:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 13))
        blocks, sums = np.concatenate(self._blocks), np.concatenate(self._sums)
        if len(blocks) > 1 and not (np.diff(blocks) > 0).all():
            blocks, index = np.unique(blocks, return_inverse=True)
            sums = np.column_stack([np.bincount(index, sums[:, k], len(blocks)) for k in range(13)])
        self._blocks, self._sums = [blocks], [sums]
        return blocks, sums

    def _still(
        self, blocks: np.ndarray, sums: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The blocks laid out in time (where blocks are missing, at most LOCAL_BLOCKS + 1 empty
        rows: the mean over the blocks around sees the same blocks as in time, and a rest
        cannot span them), each block's row there, and which rows are at rest (eq. 5)."""
        rows = np.concatenate(
            [[0], np.cumsum(np.minimum(np.diff(blocks), LOCAL_BLOCKS + 1))]
        ).astype(np.int64)
        dense = np.zeros((rows[-1] + 1 if len(rows) else 0, 13))
        dense[rows] = sums
        n = np.maximum(dense[:, _N], 1.0)[:, None]
        accel_mean, gyro_mean = dense[:, _FA] / n, dense[:, _W] / n + self.reference[3:]
        # the accelerometer's block mean against its mean over the blocks around (1 s): motion
        # moves it, a bias does not, and the noise is averaged down to a tenth of a second's
        kernel = np.ones(2 * LOCAL_BLOCKS + 1)

        def around(column: np.ndarray) -> np.ndarray:  # each block's sum over the blocks around it
            return np.convolve(column, kernel)[
                LOCAL_BLOCKS : LOCAL_BLOCKS + len(column)
            ]  # ("same", also when shorter than the kernel)

        weight = around(dense[:, _N])
        local = (
            np.column_stack([around(dense[:, k]) for k in range(_FA.start, _FA.stop)])
            / np.maximum(weight, 1.0)[:, None]
        )
        still = (
            (dense[:, _N] >= 2)
            & (np.linalg.norm(accel_mean - local, axis=1) <= self.accel_tolerance)
            & (np.linalg.norm(gyro_mean, axis=1) <= self.gyro_tolerance)
        )
        return dense, rows, still

    def _judge(self, final: bool) -> None:
        """Find the rests among the blocks held, up to the last block that is not at rest and
        whose neighbourhood no sample can still change (all of them when ``final``); keep only
        what follows it, and the blocks before it that its neighbours' test looks at."""
        blocks, sums = self.blocks()
        if not len(blocks):
            return
        dense, rows, still = self._still(blocks, sums)
        if final:
            cut = len(dense)
        else:
            settled = (
                rows[int(np.searchsorted(blocks, self._last_block - SETTLE_BLOCKS))] - LOCAL_BLOCKS
            )
            moving = np.flatnonzero(~still[: max(settled, 0)])
            if not len(moving):
                return  # a rest may go on: hold every block
            cut = int(moving[-1])
        block_of = np.full(len(dense), -1, dtype=np.int64)
        block_of[rows] = blocks  # (a rest lies in blocks side by side: rows and blocks agree there)
        edge = round(self.edge_s / BLOCK_S)
        for a, b in true_runs(still[:cut]):
            if block_of[a] < self._judged_to or (b - a) * BLOCK_S < self.min_duration_s:
                continue  # (a run in the context kept from before was judged then)
            inner = slice(a + edge, b - edge) if b - a > 2 * edge + 1 else slice(a, b)
            self._rests.append(
                self._rest(dense[inner], block_of[a] * BLOCK_S, (block_of[b - 1] + 1) * BLOCK_S)
            )
        cut_block = int(blocks[-1]) + 1 if final else int(block_of[cut])
        if self._rests:  # the fallback's spreads are not needed any more
            self._spreads = []
        else:
            judged = (blocks >= self._judged_to) & (blocks < cut_block)
            n = np.maximum(sums[judged, _N], 1.0)[:, None]
            self._spreads.append(
                np.sqrt(np.maximum(sums[judged, _FA2] / n - (sums[judged, _FA] / n) ** 2, 0.0))
            )
        keep = rows >= cut - LOCAL_BLOCKS  # the context of the blocks still to judge
        self._blocks, self._sums = [blocks[keep]], [sums[keep]]
        self._judged_to = cut_block

    def rests(self) -> list[RestPeriod]:
        """Every rest among the samples fed, the last blocks judged too."""
        self._judge(final=True)
        return list(self._rests)

    def report(self) -> BiasReport:
        rests = self.rests()
        spread = np.concatenate(self._spreads) if self._spreads else np.zeros((0, 3))
        span_s = (self._last_block + 1) * BLOCK_S if self._last_block >= 0 else 0.0
        return self._track(rests, spread, span_s)

    def _rest(self, sums: np.ndarray, start_s: float, end_s: float) -> RestPeriod:
        count = float(sums[:, _N].sum())
        mean_a = sums[:, _FA].sum(axis=0) / count
        std_a = np.sqrt(np.maximum(sums[:, _FA2].sum(axis=0) / count - mean_a**2, 0.0))
        f = mean_a + self.reference[:3]
        up = f / np.linalg.norm(f)
        bias = (float(np.linalg.norm(f)) - GRAVITY_MPS2) * up
        mean_w = sums[:, _W].sum(axis=0) / count
        var_w = np.maximum(sums[:, _W2].sum(axis=0) / count - mean_w**2, 1e-12)
        gyro_mean = mean_w + self.reference[3:]
        level = _level(sums, self.reference[:3])
        return RestPeriod(start_s, end_s, bias, std_a, gyro_mean, var_w, int(count), up, level)

    def _track(self, rests: list[RestPeriod], block_spread: np.ndarray, end_s: float) -> BiasReport:
        """The gyro bias Kalman filter over the rests (eqs. 7-9), to ``end_s``; ``block_spread``
        the accelerometer's spread in each block that holds samples (the fallback without a
        rest)."""
        q = self.process_noise**2
        x = rests[0].gyro_mean.copy() if rests else np.zeros(3)
        P = np.full(3, self.initial_std**2)
        values, durations, last_s = [x.copy()], [0.0], 0.0
        for rest in rests:
            P = P + q * (rest.start_s - last_s)
            P_new = 1.0 / (1.0 / P + rest.samples / rest.gyro_noise_var)
            x = P_new * (x / P + rest.samples * rest.gyro_mean / rest.gyro_noise_var)
            durations[-1] += rest.start_s - last_s
            values.append(x.copy())
            durations.append(0.0)
            P, last_s = P_new, rest.start_s
        durations[-1] += end_s - last_s
        P = P + q * (end_s - last_s)
        v, d = np.array(values), np.array(durations)
        weights = d / d.sum() if d.sum() > 0 else np.full(len(d), 1.0 / len(d))
        mean = weights @ v
        last = rests[-1] if rests else None
        return BiasReport(
            first_ns=self.first_ns or 0,
            rest_periods=rests,
            accel_bias=last.accel_bias if last else np.zeros(3),
            accel_noise_std=last.accel_noise_std
            if last
            else (np.median(block_spread, axis=0) if len(block_spread) else np.zeros(3)),
            gyro_bias_initial=values[0],
            gyro_bias_final=x,
            gyro_bias_track_std=np.sqrt(weights @ (v - mean) ** 2),
            gyro_bias_final_std=np.sqrt(P),
        )


def _level(sums: np.ndarray, reference: np.ndarray) -> bool:
    """Whether a rest's specific force (its blocks' sums about ``reference``) kept its
    direction from the first second to the last: a body that turns by ``theta`` about a level
    axis turns it by ``-theta``, ``f_first x f_last = -|f|^2 theta``; the turn's chi-square
    against the two seconds' means' noise within :data:`TURN_CHI2` (or the turn within
    :data:`TURN_FLOOR_RAD`)."""
    k = round(1.0 / BLOCK_S)
    if len(sums) < 2 * k:
        return True
    ends = []
    for part in (sums[:k], sums[-k:]):
        n = part[:, _N].sum()
        mean = part[:, _FA].sum(axis=0) / n
        ends.append((mean + reference, (part[:, _FA2].sum(axis=0) / n - mean**2) / n))
    (first, var_first), (last, var_last) = ends
    g2 = float(np.linalg.norm(first) * np.linalg.norm(last))
    turn = np.cross(first, last) / g2  # (-theta)
    var_turn = float(np.mean(var_first + var_last)) / g2  # (about each level axis)
    return bool(turn @ turn <= TURN_CHI2 * var_turn + TURN_FLOOR_RAD**2)


@dataclass
class BaseGyroBias:
    """A gyro's bias as the last samples that held a rest showed it (:func:`rest_rate`, with
    eq. 5's tolerances); None before any. Only the middle of a rest counts: each end loses
    ``edge_s``, and a rest must keep 2 s after that. About the level axes only the rests that
    did not tilt count; where all of the last samples' rests tilted, the value it had there."""

    accel_tolerance: float
    gyro_tolerance: float
    min_duration_s: float
    edge_s: float = BASE_REST_EDGE_S
    value: np.ndarray | None = None

    def update(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        shortest = max(self.min_duration_s, 2.0 * self.edge_s + 2.0)
        tolerances = (self.accel_tolerance, self.gyro_tolerance, shortest, self.edge_s)
        found = rest_rate(t_ns, gyro, accel, *tolerances, previous=self.value)
        if found is not None:
            self.value = found


def rest_rate(
    t_ns: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    accel_tolerance: float,
    gyro_tolerance: float,
    min_duration_s: float,
    edge_s: float = BASE_REST_EDGE_S,
    previous: np.ndarray | None = None,
) -> np.ndarray | None:
    """The gyro's mean rate over the rests among these samples (eq. 5's test), each rest
    without ``edge_s`` at either end and weighted by its samples; None where they hold no
    rest. A vehicle that stops does not turn, but its body pitches and rolls on the suspension
    for a second or two after (and before it drives off): the ends are not its bias. About
    the level axes, only the rests whose specific force kept its direction count
    (:attr:`RestPeriod.level`): the bias that fits every rest's vertical rate and every such
    rest's rates about the level axes, by least squares; where none did, ``previous`` about
    the level axes (zero without)."""
    tracker = BiasTracker(accel_tolerance, gyro_tolerance, min_duration_s, 0.0, 1.0, edge_s)
    tracker.add(t_ns, gyro, accel)
    rests = tracker.rests()  # (not the report: its gyro-bias filter is not wanted here)
    if not rests:
        return None
    counts = np.array([r.samples for r in rests], dtype=np.float64)
    up = np.array([r.accel_up for r in rests])
    level = np.array([r.level for r in rests])
    # what each rest shows of the bias: every axis, or the vertical
    shows = np.where(level[:, None, None], np.eye(3), up[:, :, None] * up[:, None])
    found = np.einsum("n,nij,nj->i", counts, shows, np.array([r.gyro_mean for r in rests]))
    if level.any():
        return np.linalg.solve(np.einsum("n,nij->ij", counts, shows), found)
    vertical = np.einsum("n,ni->i", counts, up)
    vertical /= np.linalg.norm(vertical)
    kept = np.zeros(3) if previous is None else previous - (previous @ vertical) * vertical
    return found / counts.sum() + kept
