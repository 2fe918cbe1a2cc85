"""Each window reduced to the second moments of its data vectors (:mod:`.model`'s layouts).

The base's part of each data vector is shared by every sensor, so a window's moments are held
as the base's block (upper triangles, once per window) and each sensor's own rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.model import ACCEL_BASE, ACCEL_DATA, ACCEL_OWN, GYRO_BASE, GYRO_DATA, GYRO_OWN
from imucal_cli.core.segments import WindowInfo


@dataclass(frozen=True)
class BaseMoments:
    """The base IMU's block of a window's moments, shared by every sensor (upper triangles)."""

    packed_gyro: np.ndarray  # of the (8, 8) block of x_g's base part (GYRO_BASE)
    packed_accel: np.ndarray  # of the (30, 30) block of x_a's base part (ACCEL_BASE)


@dataclass
class WindowMoments:
    """One window reduced to what the estimator needs: the second moments ``S = sum x x^T``,
    held as the base's block (shared between sensors) and the sensor's own rows."""

    number: int
    start_s: float
    end_s: float
    valid: bool  # no gap in either stream
    base: BaseMoments
    rows_gyro: np.ndarray  # (6, 14): [w_I, f_I]^T x_g
    rows_accel: np.ndarray  # (3, 33): f_I^T x_a
    samples: int
    info: WindowInfo | None = None  # observability, filled in (in bulk) when first needed


_UPPER = {"gyro": np.triu_indices(GYRO_BASE.size), "accel": np.triu_indices(ACCEL_BASE.size)}


def base_moments(G_gyro: np.ndarray, G_accel: np.ndarray) -> BaseMoments:
    """The base block from the Gram matrices ``X^T X`` of the base part of the data vectors,
    (8, 8) for the gyro and (30, 30) for the accelerometer."""
    return BaseMoments(G_gyro[_UPPER["gyro"]], G_accel[_UPPER["accel"]])


def assemble_moments(windows: Sequence[WindowMoments], which: str) -> np.ndarray:
    """The full moments ``S`` of several windows, (K, dim, dim), ``which`` "gyro" or "accel"."""
    if which == "gyro":
        dim, own = GYRO_DATA.size, GYRO_OWN
        rows = np.stack([w.rows_gyro for w in windows])
        packed = np.stack([w.base.packed_gyro for w in windows])
    else:
        dim, own = ACCEL_DATA.size, ACCEL_OWN
        rows = np.stack([w.rows_accel for w in windows])
        packed = np.stack([w.base.packed_accel for w in windows])
    upper = _UPPER[which]
    full = np.empty((len(windows), dim, dim))
    full[:, own + upper[0], own + upper[1]] = packed
    full[:, own + upper[1], own + upper[0]] = packed
    full[:, 0:own, :] = rows
    full[:, :, 0:own] = rows.transpose(0, 2, 1)
    return full
