"""Small SO(3) helpers."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` for a 3-vector or a stack (N, 3) -> (N, 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def skew_squared(v: np.ndarray) -> np.ndarray:
    """``[v]x^2 = v v^T - |v|^2 I`` for a stack (N, 3) -> (N, 3, 3): the centripetal operator."""
    v = np.asarray(v, dtype=np.float64)
    outer = v[..., :, None] * v[..., None, :]
    return outer - np.einsum("...i,...i->...", v, v)[..., None, None] * np.eye(3)


def rotation_angle_deg(a: Rotation, b: Rotation) -> float:
    """Angle of ``a^-1 b`` in degrees (paper eq. 21), numerically safe near 0 and 180 deg.

    ``arccos((tr - 1) / 2)`` loses precision near 0 and 180 deg; the angle of the relative
    rotation's quaternion, ``2 atan2(|q_xyz|, |q_w|)``, does not.
    """
    q = (a.inv() * b).as_quat()
    return float(np.degrees(2.0 * np.arctan2(np.linalg.norm(q[:3]), abs(q[3]))))
