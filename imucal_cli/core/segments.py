"""Observability of each motion window (paper eqs. 18-19, and the design matrix of eq. 12).

Rotation: the residual ``R^T w_B - w_I`` of eq. 10 changes with a small rotation ``d`` as
``[u]x d`` (``u = R^T w_B``), so one window's Fisher information is
``I = sum_i J_i^T J_i / s^2`` with ``J_i = -[u_i]x``, 3x3 (eq. 18 in a well-posed form). The
window's constant gyro bias is a nuisance: its Schur complement replaces ``u_i`` by
``u_i - mean(u)``. The accelerometer equation (eq. 11) adds the same form in the specific force
predicted at the IMU, ``v_i = f_B + A_i t`` (the lever arm at its prior), with its own bias
marginalised: that is how gravity and the vehicle's accelerations fix the axis that turning
about one axis leaves free in eq. 10. The singular values of ``I`` (eq. 19) give the
Cramer-Rao bound of the worst-determined rotation axis, ``1 / sqrt(sigma_min)``, and a window
is selected when that bound is below ``max_rotation_std_deg``. Rotation by ``R`` does not
change singular values, so the information is computed in the base frame.

Translation: eq. 12's design matrix ``A_i = [w_B]x^2 + [dw_B]x`` with the window's accelerometer
bias as nuisance gives ``I_t = sum (A_i - mean A)^T (A_i - mean A) / s_a^2``; an axis is
constrained by the window when its bound ``sqrt((I_t^-1)_jj)`` is below a third of the search
box (:data:`OBSERVABLE_FRACTION_OF_BOUND`), i.e. the data, not the box, decides it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.model import ACCEL_DATA, GYRO_DATA, kron_t

#: A translation axis counts as observed when its standard deviation is below this fraction of
#: the search half-width ``translation_bound_m``.
OBSERVABLE_FRACTION_OF_BOUND = 1.0 / 3.0


@dataclass(frozen=True)
class WindowInfo:
    """One window's observability."""

    start_s: float  # grid time of the first sample (s, base clock, relative to the grid origin)
    end_s: float
    min_singular_value: float  # of the rotation Fisher information, rad^-2
    rotation_std_deg: float  # CRLB std of the worst rotation axis
    selected: bool
    translation_std_m: np.ndarray  # (3,) CRLB std per axis from this window alone (inf: none)
    translation_observable: np.ndarray  # (3,) bool
    valid: bool  # False when the window holds a gap in either stream
    count: int = 1  # windows it stands for (old windows merged: memory flat in time)...
    left_out: int = 0  # ... of which not used
    #: The drive's excitation there, from the base IMU: its rate's RMS (rad/s) and its specific
    #: force's std about the window's mean (m/s^2: the vehicle's accelerations and turns).
    rate_rms_radps: float = float("nan")
    accel_std_mps2: float = float("nan")

    @property
    def used(self) -> int:
        """How many windows it stands for enter the estimate."""
        return self.count - self.left_out if self.selected else 0


def window_counts(infos: Sequence[WindowInfo]) -> tuple[int, int]:
    """How many windows the estimate used, and how many there were (old windows merged:
    each stretch stands for its windows)."""
    return sum(info.used for info in infos), sum(info.count for info in infos)


#: One window's observability as :class:`WindowRows` keeps it (85 bytes).
ROW = np.dtype(
    [
        ("start_s", "f8"),
        ("end_s", "f8"),
        ("min_singular_value", "f8"),
        ("rotation_std_deg", "f8"),
        ("translation_std_m", "f8", 3),
        ("selected", "?"),
        ("translation_observable", "?", 3),
        ("valid", "?"),
        ("count", "i4"),
        ("left_out", "i4"),
        ("rate_rms_radps", "f8"),
        ("accel_std_mps2", "f8"),
    ]
)


class WindowRows(Sequence[WindowInfo]):
    """Windows' observability as a table (``segments`` keeps every window of a day: 85 bytes
    each rather than a :class:`WindowInfo` and its two arrays), read back as
    :class:`WindowInfo` s."""

    def __init__(self, rows: np.ndarray | None = None) -> None:
        self._rows = np.zeros(64, ROW) if rows is None else rows
        self._size = 0 if rows is None else len(rows)

    def extend(self, infos: Sequence[WindowInfo]) -> None:
        if self._size + len(infos) > len(self._rows):
            grown = np.zeros(2 * (self._size + len(infos)), ROW)
            grown[: self._size] = self._rows[: self._size]
            self._rows = grown
        for k, info in enumerate(infos, start=self._size):
            self._rows[k] = tuple(getattr(info, name) for name in ROW.names or ())
        self._size += len(infos)

    def sorted(self, more: Sequence[WindowInfo] = ()) -> WindowRows:
        """These rows and ``more`` in the order of their start."""
        both = WindowRows(self._rows[: self._size].copy())
        both.extend(more)
        rows = both._rows[: both._size]
        return WindowRows(rows[np.argsort(rows["start_s"], kind="stable")])

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, k: int) -> WindowInfo:  # type: ignore[override]
        if not -self._size <= k < self._size:
            raise IndexError(k)
        row = self._rows[k % self._size]
        return WindowInfo(
            start_s=float(row["start_s"]),
            end_s=float(row["end_s"]),
            min_singular_value=float(row["min_singular_value"]),
            rotation_std_deg=float(row["rotation_std_deg"]),
            selected=bool(row["selected"]),
            translation_std_m=row["translation_std_m"].copy(),
            translation_observable=row["translation_observable"].copy(),
            valid=bool(row["valid"]),
            count=int(row["count"]),
            left_out=int(row["left_out"]),
            rate_rms_radps=float(row["rate_rms_radps"]),
            accel_std_mps2=float(row["accel_std_mps2"]),
        )


def _std_from_information(info: np.ndarray) -> np.ndarray:
    """Standard deviations from a 3x3 information matrix, or a stack of them (..., 3, 3);
    infinite where it is singular."""
    s = np.linalg.eigvalsh(
        info
    )  # ascending; negative where noise was taken off (not positive definite)
    singular = (s[..., 0] <= np.abs(s[..., -1]) * 1e-12) | (s[..., 0] <= 0)
    out = np.full(info.shape[:-1], np.inf)
    if not np.all(singular):
        regular = ~singular
        out[regular] = np.sqrt(np.diagonal(np.linalg.inv(info[regular]), axis1=-2, axis2=-1))
    return out


def _centred(S: np.ndarray, P: np.ndarray | slice, one: int) -> np.ndarray:
    """Each window's scatter of ``P x`` about its mean, from its moments ``S`` (their ``one``
    column's own moment is the count: a window's samples, a merged stretch's weight of its
    constant); ``P`` a matrix, or a slice where it only picks entries of ``x`` (then no
    arithmetic: the same numbers, far fewer steps)."""
    n = S[:, one, one][:, None, None]
    if isinstance(P, slice):
        mean = S[:, P, one][:, :, None] / n
        return S[:, P, P] - n * mean @ mean.transpose(0, 2, 1)
    mean = np.einsum("ij,kj->ki", P, S[:, :, one])[:, :, None] / n
    return np.einsum("ij,kjl,ml->kim", P, S, P) - n * mean @ mean.transpose(0, 2, 1)


def _rotation_information(C: np.ndarray, std: float) -> np.ndarray:
    """The rotation's Fisher information from the scatter ``C`` of ``u`` (``J = -[u]x``)."""
    trace = np.trace(C, axis1=1, axis2=2)[:, None, None]
    return (trace * np.eye(3) - C) / std**2


def window_infos_from_moments(
    spans: list[tuple[float, float, bool]],
    samples: np.ndarray,
    S_gyro: np.ndarray,
    S_accel: np.ndarray,
    lever_arm: np.ndarray,
    gyro_noise_std: float,
    accel_noise_std: float,
    max_rotation_std_deg: float,
    translation_bound_m: float,
    dw_noise_var: float = 0.0,
) -> list[WindowInfo]:
    """:func:`window_infos_from_moments`: K windows at once: ``spans`` (start, end, valid),
    ``samples`` (K,), ``S_gyro`` (K, 14, 14), ``S_accel`` (K, 33, 33)."""
    n = samples.astype(np.float64)[:, None, None]

    one_g, one_a = GYRO_DATA.index("one"), ACCEL_DATA.index("one")
    P_v = np.zeros((3, ACCEL_DATA.size))  # v = f_B + A t at the prior's lever arm
    P_v[:, ACCEL_DATA["f_B"]] = np.eye(3)
    P_v[:, ACCEL_DATA["vec_A"]] = kron_t(lever_arm)
    info = _rotation_information(_centred(S_gyro, GYRO_DATA["w_B"], one_g), gyro_noise_std)
    info += _rotation_information(_centred(S_accel, P_v, one_a), accel_noise_std)
    sigma_min = np.clip(np.linalg.eigvalsh(info)[:, 0], 0.0, None)
    with np.errstate(divide="ignore"):
        std_deg = np.where(sigma_min > 0, np.degrees(1.0 / np.sqrt(sigma_min)), np.inf)
    C_A = _centred(S_accel, ACCEL_DATA["vec_A"], one_a).reshape(
        -1, 3, 3, 3, 3
    )  # blocks (j, k) of vec A
    # sum A^T A, less what the angular acceleration's noise adds (E [n]x^T [n]x = 2 s^2 I):
    # information the noise fakes is none
    t_info = (
        np.einsum("kjala->kjl", C_A) - n * 2.0 * dw_noise_var * np.eye(3)
    ) / accel_noise_std**2
    t_stds = _std_from_information(t_info)
    w_B, f_B = GYRO_DATA["w_B"], ACCEL_DATA["f_B"]
    with np.errstate(invalid="ignore", divide="ignore"):  # (a window without samples: nan)
        rate_rms = np.sqrt(np.einsum("kii->k", S_gyro[:, w_B, w_B]) / n[:, 0, 0])
        mean_f = S_accel[:, f_B, one_a] / n[:, 0]
        f_var = np.einsum("kii->k", S_accel[:, f_B, f_B]) / n[:, 0, 0] - (mean_f**2).sum(axis=1)
        accel_std = np.sqrt(np.clip(f_var, 0.0, None))
    out = []
    for k, (start, end, valid) in enumerate(spans):
        t_std = t_stds[k].copy()
        out.append(
            WindowInfo(
                start_s=start,
                end_s=end,
                min_singular_value=float(sigma_min[k]),
                rotation_std_deg=float(std_deg[k]),
                selected=bool(valid and std_deg[k] < max_rotation_std_deg),
                translation_std_m=t_std,
                translation_observable=t_std < OBSERVABLE_FRACTION_OF_BOUND * translation_bound_m,
                valid=bool(valid),
                rate_rms_radps=float(rate_rms[k]),
                accel_std_mps2=float(accel_std[k]),
            )
        )
    return out
