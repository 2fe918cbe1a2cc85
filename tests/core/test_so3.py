"""Rotation helpers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imucal_cli.core.so3 import rotation_angle_deg


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 90.0, 179.9999, 180.0])
def test_rotation_error_is_safe_near_0_and_180(angle):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    a = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    b = a * Rotation.from_rotvec(np.radians(angle) * axis)
    assert rotation_angle_deg(a, b) == pytest.approx(angle, abs=1e-9)
