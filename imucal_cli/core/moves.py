"""Mounts that moved during the log (a knock, a loose bracket): a change-point test over the
windows, against the hypothesis of one pose.

Each used window's information about the extrinsics (rotation and lever arm) and its gradient
at a fit, its own biases eliminated, are what a window says of the pose (:func:`window_terms`).
For a move within window ``k`` (which then holds both poses and is left out), the likelihood
ratio of two poses (the windows before it, after it) against one is
``s_B^T I_B^+ s_B + s_A^T I_A^+ s_A - s^T I^+ s`` (the sums of the windows' gradients ``s``
and information ``I`` on either side), chi-square with as many degrees of freedom as the
extrinsics either side determines. The largest over the splits is tested at the configured
false-alarm rate divided among them (Bonferroni), the ratio first divided by how much more
the windows scatter about their side's pose than their information says (:func:`scatter`: what
the model leaves out moves each window a little); a move found, each side is fitted again and
searched in turn, so several moves in one log are found one after another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.model import ROTATION, TIME_OFFSET, TRANSLATION
from imucal_cli.core.solver import Fit, Problem

#: Fewest windows on either side of a move (each side's pose is fitted from them).
MIN_SIDE_WINDOWS = 2
#: The most moves one log is searched for.
MAX_MOVES = 8
#: Eigenvalues of the information below this fraction of its largest are not determined.
RANK_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Move:
    """Where a sensor's mount moved: in window ``within`` (its place among the problem's used
    windows; it holds both poses and is used for neither), at ``at_s`` (s, grid clock: the
    window's middle) with its std, and the test's statistic and threshold."""

    within: int
    at_s: float
    at_std_s: float
    statistic: float
    threshold: float


def window_terms(problem: Problem, fit: Fit) -> tuple[np.ndarray, np.ndarray]:
    """Per used window, the information (K, 6, 6) and gradient (K, 6) of the extrinsics
    ``[rotation (IMU axes), translation]`` at ``fit``, weighted as the fit weighs its
    residuals, each window's own biases eliminated (free in that window alone)."""
    lin = problem.linearised(fit.point, fit.knots)
    K = len(problem.used)
    information, gradient = np.zeros((K, 7, 7)), np.zeros((K, 7))
    weight_g = problem.gain / fit.scale_g**2
    weight_a = problem.gain / fit.scale_a**2
    wanted = np.r_[
        np.arange(ROTATION.start, ROTATION.stop),
        np.arange(TRANSLATION.start, TRANSLATION.stop),
        [TIME_OFFSET],
    ]
    parts = [(lin.gyro, problem.globals_g, weight_g, [problem.S_g])]
    parts.append((lin.accel, problem.globals_a, weight_a, problem.accel_moments()))
    for equations, globals_, weight, chunks in parts:
        rows = [i for i, p in enumerate(globals_) if p in wanted]
        where = [int(np.flatnonzero(wanted == globals_[i])[0]) for i in rows]
        D = equations.D[rows]  # (p, 3, dim)
        S = np.concatenate(chunks)  # (K, dim, dim)
        DS = D[None] @ S[:, None]  # (K, p, 3, dim)
        H = DS.reshape(K, len(rows), -1) @ D.reshape(len(rows), -1).T
        coupling = equations.coupling[:, rows, :]  # (K, p, 6)
        g_own = equations.gradient[:, rows]
        g_bias = equations.gradient[:, len(globals_) :]
        B = (
            equations.bias
            + 1e-12 * np.eye(6) * np.trace(equations.bias, axis1=1, axis2=2)[:, None, None]
        )
        right = np.concatenate([coupling.transpose(0, 2, 1), g_bias[..., None]], axis=2)
        solved = np.linalg.solve(B, right)
        H -= coupling @ solved[:, :, : len(rows)]
        g = g_own - (coupling @ solved[:, :, len(rows) :])[..., 0]
        information[np.ix_(range(K), where, where)] += weight * H
        gradient[:, where] += weight * g
    return information, gradient


def _quadratic(info: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``s^T info^+ s`` and the rank of ``info`` (its determined directions), of each of a
    stack of them (``info`` (..., n, n), ``s`` (..., n))."""
    values, vectors = np.linalg.eigh(info)
    largest = np.maximum(values.max(axis=-1, keepdims=True), 0.0)
    keep = values > RANK_TOLERANCE * largest
    projected = np.einsum("...ij,...i->...j", vectors, s)
    terms = np.divide(projected**2, values, out=np.zeros_like(values), where=keep)
    return terms.sum(axis=-1), np.count_nonzero(keep, axis=-1)


def best_split(information: np.ndarray, gradient: np.ndarray) -> tuple[int, float, int, np.ndarray]:
    """The window the mount most likely moved in (left out: it holds both poses), by the
    likelihood ratio of a pose each side, the windows before it and after it, against one
    pose, each side's clock offset its own in both (a clock that stepped is not a move); the
    ratio, its degrees of freedom, and every window's ratio. ``information`` (K, 7, 7) and
    ``gradient`` (K, 7): the pose (6), then the clock offset."""
    K = len(gradient)
    I_cum, s_cum = np.cumsum(information, axis=0), np.cumsum(gradient, axis=0)
    ratios = np.full(K, -np.inf)
    dofs = np.zeros(K, dtype=int)
    j = np.arange(MIN_SIDE_WINDOWS, K - MIN_SIDE_WINDOWS)
    if len(j):
        I_before, s_before = I_cum[j - 1], s_cum[j - 1]
        I_after, s_after = I_cum[-1] - I_cum[j], s_cum[-1] - s_cum[j]
        before, rank_before = _quadratic(I_before, s_before)
        after, rank_after = _quadratic(I_after, s_after)
        one, rank_one = _quadratic(*_one_pose(I_before, s_before, I_after, s_after))
        ratios[j], dofs[j] = before + after - one, rank_before + rank_after - rank_one
    k = int(np.argmax(ratios))
    return k, float(ratios[k]), int(dofs[k]), ratios


def _one_pose(
    I_before: np.ndarray, s_before: np.ndarray, I_after: np.ndarray, s_after: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The information and gradient of one pose for both sides and a clock offset each: the
    unknowns ``[pose (6), offset before, offset after]`` (stacks of them, the sides' last
    axes 7)."""
    info, s = np.zeros((*s_before.shape[:-1], 8, 8)), np.zeros((*s_before.shape[:-1], 8))
    for side, (I_side, s_side) in enumerate(((I_before, s_before), (I_after, s_after))):
        at = np.array([0, 1, 2, 3, 4, 5, 6 + side])
        info[..., at[:, None], at] += I_side
        s[..., at] += s_side
    return info, s


def scatter(information: np.ndarray, gradient: np.ndarray, within: int) -> float:
    """How much more the windows scatter about their side's pose (before and after window
    ``within``, which is left out) than their information says, at least 1: what the model
    leaves out (a clock followed to within its noise, an IMU's own errors) moves each window a
    little, and must not be taken for a move of the mount."""
    chi2, dof = _misfit(information, gradient, within)
    return max(1.0, chi2 / dof) if dof > 0 else 1.0


def _misfit(information: np.ndarray, gradient: np.ndarray, within: int) -> tuple[float, int]:
    """The windows' chi-square about their side's pose (window ``within`` left out) and its
    degrees of freedom."""
    chi2, dof = 0.0, 0
    for side in (slice(0, within), slice(within + 1, len(gradient))):
        I_side, s_side = information[side], gradient[side]
        if len(s_side) < 2:
            continue
        values, vectors = np.linalg.eigh(I_side.sum(axis=0))
        keep = values > RANK_TOLERANCE * max(float(values.max()), 0.0)
        mean = vectors[:, keep] @ ((vectors[:, keep].T @ s_side.sum(axis=0)) / values[keep])
        q, rank = _quadratic(I_side, s_side - I_side @ mean)
        chi2, dof = chi2 + float(q.sum()), dof + int(rank.sum())
        dof -= int(np.count_nonzero(keep))
    return chi2, dof


def find_moves(
    problem: Problem, fit: Fit, alpha: float, refit: Callable[[np.ndarray], Fit]
) -> list[Move]:
    """Every move of the mount in the problem's used windows, in time order: binary
    segmentation, each segment fitted on its own (``refit(mask) -> Fit``) before it is
    searched."""
    from scipy.special import chdtri

    K = len(problem.used)
    moves: list[Move] = []
    segments = [(0, K, fit)]
    while segments and len(moves) < MAX_MOVES:
        start, stop, at_fit = segments.pop()
        if stop - start < 2 * MIN_SIDE_WINDOWS + 1:  # (and the one it lies in)
            continue
        information, gradient = window_terms(problem, at_fit)
        I_seg, s_seg = information[start:stop], gradient[start:stop]
        k, ratio, dof, ratios = best_split(I_seg, s_seg)
        splits = stop - start - 2 * MIN_SIDE_WINDOWS
        threshold = float(chdtri(max(dof, 1), alpha / splits)) if dof else np.inf
        if not ratio > threshold * scatter(I_seg, s_seg, k):
            continue
        # the window that holds it: of that and its neighbours, the one that leaves the
        # windows either side nearest their sides' poses, each side fitted on its own
        sides = {c: _sides(problem, refit, start, start + c, stop) for c in _around(k, ratios)}
        k = min(sides, key=lambda c: sides[c][0])
        windows = problem.used[start:stop]
        times = np.array([0.5 * (w.start_s + w.end_s) for w in windows])
        profile = times[ratios >= ratio - 1.0]  # the profile's 1-sigma interval
        window_s = windows[k].end_s - windows[k].start_s
        at_std = max(window_s / np.sqrt(12.0), (profile.max() - profile.min()) / 2.0)
        moves.append(Move(start + k, float(times[k]), float(at_std), ratio, threshold))
        before, after = sides[k][1:]
        segments += [(start, start + k, before), (start + k + 1, stop, after)]
    return sorted(moves, key=lambda m: m.within)


def _around(k: int, ratios: np.ndarray) -> list[int]:
    """Window ``k`` and its neighbours that may hold a move (enough windows either side)."""
    return [j for j in (k - 1, k, k + 1) if 0 <= j < len(ratios) and ratios[j] > -np.inf]


def _sides(
    problem: Problem, refit: Callable[[np.ndarray], Fit], start: int, within: int, stop: int
) -> tuple[float, Fit, Fit]:
    """The windows before and after window ``within`` (of ``start .. stop``) fitted each on
    their own, and their cost (weighted as the fits weigh it)."""
    cost, fits = 0.0, []
    for a, b in ((start, within), (within + 1, stop)):
        mask = np.zeros(len(problem.used), dtype=bool)
        mask[a:b] = True
        fit = refit(mask)
        cost += float(
            np.sum(fit.cost_g[mask]) / fit.scale_g**2 + np.sum(fit.cost_a[mask]) / fit.scale_a**2
        )
        fits.append(fit)
    return cost, fits[0], fits[1]
