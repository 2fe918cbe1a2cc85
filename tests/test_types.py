"""Transform algebra and the SPEC's YAML form."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from imucal_cli.errors import ConfigError
from imucal_cli.types import ImuStream, Transform, rotation_to_rpy, rpy_to_rotation

finite = st.floats(-50.0, 50.0, allow_nan=False)
angles = st.floats(-np.pi, np.pi, allow_nan=False)
pitches = st.floats(-np.pi / 2 + 1e-6, np.pi / 2 - 1e-6, allow_nan=False)


@st.composite
def transforms(draw):
    quat = np.array([draw(st.floats(-1, 1)) for _ in range(4)])
    if np.linalg.norm(quat) < 1e-3:
        quat = np.array([0.0, 0.0, 0.0, 1.0])
    return Transform(Rotation.from_quat(quat), np.array([draw(finite) for _ in range(3)]))


def assert_same(a: Transform, b: Transform, tol: float = 1e-9) -> None:
    np.testing.assert_allclose(a.as_matrix(), b.as_matrix(), atol=tol, rtol=0)


@given(transforms(), transforms(), transforms())
def test_compose_is_associative_and_matches_matrices(a, b, c):
    assert_same((a * b) * c, a * (b * c))
    np.testing.assert_allclose((a * b).as_matrix(), a.as_matrix() @ b.as_matrix(), atol=1e-9)


@given(transforms())
def test_inverse_round_trip(a):
    assert_same(a * a.inverse(), Transform.identity())
    assert_same(a.inverse().inverse(), a)
    np.testing.assert_allclose(a.inverse().as_matrix(), np.linalg.inv(a.as_matrix()), atol=1e-9)


@given(transforms(), st.lists(finite, min_size=3, max_size=3))
def test_apply_maps_points_from_child_to_parent(a, point):
    """T_A_B maps p_A = R p_B + t (SPEC)."""
    p_B = np.array(point)
    expected = (a.as_matrix() @ np.append(p_B, 1.0))[:3]
    np.testing.assert_allclose(a.apply(p_B), expected, atol=1e-9)


@given(angles, pitches, angles)
def test_rpy_is_ros_convention(roll, pitch, yaw):
    """R = Rz(yaw) Ry(pitch) Rx(roll), and the round trip through rpy."""

    def rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    def ry(a):
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    def rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    matrix = rz(yaw) @ ry(pitch) @ rx(roll)
    rotation = rpy_to_rotation(np.array([roll, pitch, yaw]))
    np.testing.assert_allclose(rotation.as_matrix(), matrix, atol=1e-12)
    back = rpy_to_rotation(rotation_to_rpy(rotation))
    assert (back.inv() * rotation).magnitude() < 1e-9


@settings(max_examples=200)
@given(transforms())
def test_dict_round_trip(a):
    d = a.to_dict()
    assert_same(Transform.from_dict(d), a)
    assert_same(
        Transform.from_dict({"translation": d["translation"], "rotation": d["rotation"]}), a
    )
    assert_same(
        Transform.from_dict({"translation": d["translation"], "rpy_deg": d["rpy_deg"]}), a, 1e-8
    )
    assert d["rotation"][3] >= 0.0


def test_from_dict_rejects_disagreeing_rotation_and_rpy():
    d = {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "rpy_deg": [0, 0, 0.01]}
    with pytest.raises(ConfigError) as info:
        Transform.from_dict(d, "cfg.yaml", "sensors.a.T_imu_lidar")
    assert "cfg.yaml" in str(info.value) and "sensors.a.T_imu_lidar.rpy_deg" in str(info.value)


def test_from_dict_accepts_agreeing_rotation_and_rpy():
    q = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat()
    t = Transform.from_dict(
        {"translation": [1, 2, 3], "rotation": list(q), "rpy_deg": [10, 20, 30]}
    )
    np.testing.assert_allclose(np.degrees(t.rpy_rad), [10, 20, 30], atol=1e-9)


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"translation": [0, 0], "rotation": [0, 0, 0, 1]}, "T.translation"),
        ({"translation": [0, 0, "x"], "rotation": [0, 0, 0, 1]}, "T.translation"),
        ({"translation": [0, 0, 0], "rotation": [0, 0, 0, 2]}, "T.rotation"),
        ({"translation": [0, 0, 0], "rotation": [0, 0, 1]}, "T.rotation"),
        ({"translation": [0, 0, 0]}, "T.rotation"),
        ({"rotation": [0, 0, 0, 1]}, "T.translation"),
        ({"translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": 1}, "T.scale"),
        ({"translation": [0, 0, float("nan")], "rotation": [0, 0, 0, 1]}, "T.translation"),
    ],
)
def test_from_dict_errors_name_the_key(data, key):
    with pytest.raises(ConfigError) as info:
        Transform.from_dict(data, "f.yaml", "T")
    assert str(info.value).startswith(f"f.yaml: {key}:")


def test_imu_stream_checks_lengths():
    with pytest.raises(ValueError):
        ImuStream(np.arange(3), np.zeros((2, 3)), np.zeros((3, 3)))
    s = ImuStream(np.arange(3), np.zeros((3, 3)), np.ones((3, 3)), "imu")
    assert s.t_ns.dtype == np.int64 and len(s) == 3
