"""The data that flows through imucal: IMU streams and rigid transforms.

Conventions (SPEC): ``T_A_B`` is the pose of frame B expressed in frame A, mapping points
``p_A = R_A_B p_B + t_A_B``. Quaternions are Hamilton, scalar last ``[qx, qy, qz, qw]``.
ROS RPY: ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from imucal_cli.errors import ConfigError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation


def rotation_type() -> type[Rotation]:
    """scipy's Rotation, imported when a rotation is first made: ``scipy.spatial`` takes 0.3 s
    to import, which commands that make none (``inspect``) need not pay."""
    from scipy.spatial.transform import Rotation

    return Rotation


#: Standard gravity (m/s^2).
GRAVITY_MPS2 = 9.80665

#: A gap is a step between consecutive stamps longer than this many median periods: ``inspect``
#: lists it, reading counts it, and a window holding one is not used. Shorter steps (a few
#: dropped messages) are bridged: the spline and the 5 Hz low-pass span them.
GAP_PERIODS = 5.0

#: Largest allowed deviation of an input quaternion's norm from 1.
QUATERNION_NORM_TOLERANCE = 1e-3
#: Largest allowed angle between ``rotation`` and ``rpy_deg`` when both are given (rad).
ROTATION_AGREEMENT_TOLERANCE_RAD = 1e-6


@dataclass(frozen=True)
class ImuStream:
    """One IMU's measurements, sorted by time.

    Attributes
    ----------
    t_ns : (N,) int64 array
        Measurement times (``header.stamp``) in nanoseconds.
    gyro : (N, 3) float64 array
        Angular velocity in rad/s, in the IMU frame.
    accel : (N, 3) float64 array
        Specific force in m/s^2, in the IMU frame.
    frame_id : str
        ``header.frame_id`` of the messages.
    """

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    frame_id: str = ""

    def __post_init__(self) -> None:
        t_ns = np.asarray(self.t_ns, dtype=np.int64)
        gyro = np.asarray(self.gyro, dtype=np.float64).reshape(-1, 3)
        accel = np.asarray(self.accel, dtype=np.float64).reshape(-1, 3)
        if not (len(t_ns) == len(gyro) == len(accel)):
            raise ValueError(
                f"ImuStream: {len(t_ns)} stamps, {len(gyro)} gyro and {len(accel)} accel samples"
            )
        object.__setattr__(self, "t_ns", t_ns)
        object.__setattr__(self, "gyro", gyro)
        object.__setattr__(self, "accel", accel)

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample in seconds."""
        return float(self.t_ns[-1] - self.t_ns[0]) * 1e-9 if len(self) > 1 else 0.0


def rpy_to_rotation(rpy_rad: np.ndarray) -> Rotation:
    """ROS RPY (roll, pitch, yaw in rad) to a rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    # Extrinsic x-y-z (lower case in scipy) composes as Rz @ Ry @ Rx.
    return rotation_type().from_euler("xyz", np.asarray(rpy_rad, dtype=np.float64))


def rotation_to_rpy(rotation: Rotation) -> np.ndarray:
    """Rotation to ROS RPY (roll, pitch, yaw) in rad; the inverse of :func:`rpy_to_rotation`.

    Pitch comes from ``atan2(-r20, hypot(r00, r10))`` (well conditioned everywhere), yaw from
    the first column, and roll from what is left, ``Ry(pitch)^T Rz(yaw)^T R``: near gimbal lock
    (pitch near +-90 deg) yaw and roll are not determined one by one, but the angles returned
    rebuild the rotation to round-off, which is what every RPY consumer needs of them.
    """
    R = rotation.as_matrix()
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    rest = (
        rotation_type().from_euler("z", yaw) * rotation_type().from_euler("y", pitch)
    ).inv().as_matrix() @ R
    roll = float(np.arctan2(rest[2, 1], rest[1, 1]))
    return np.array([roll, pitch, yaw])


def _quaternion(value: Any, source: str, key: str) -> Rotation:
    """A quaternion [qx, qy, qz, qw] of norm 1 (within :data:`QUATERNION_NORM_TOLERANCE`)."""
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        raise ConfigError(source, key, f"expected a quaternion [qx, qy, qz, qw], got {value!r}")
    quat = _finite_numbers(value, source, key)
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ConfigError(
            source,
            key,
            f"quaternion norm is {norm:.6g}, not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g})",
        )
    return rotation_type().from_quat(quat / norm)


def _vector3(value: Any, source: str, key: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ConfigError(source, key, f"expected a list of 3 numbers, got {value!r}")
    return _finite_numbers(value, source, key)


def _finite_numbers(value: Any, source: str, key: str) -> np.ndarray:
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
        raise ConfigError(source, key, f"expected numbers, got {value!r}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except OverflowError:  # (an int of hundreds of digits)
        array = np.full(len(value), np.inf)
    if not np.all(np.isfinite(array)):
        raise ConfigError(source, key, f"expected finite numbers, got {value!r}")
    return array


@dataclass(frozen=True)
class Transform:
    """A rigid transform ``T_A_B``: the pose of frame B in frame A.

    Attributes
    ----------
    rotation : scipy.spatial.transform.Rotation
        ``R_A_B``.
    translation : (3,) float64 array
        ``t_A_B`` in metres: the origin of B expressed in A.
    """

    rotation: Rotation
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        translation = np.asarray(self.translation, dtype=np.float64).reshape(3)
        object.__setattr__(self, "translation", translation)

    @staticmethod
    def identity() -> Transform:
        return Transform(rotation_type().identity(), np.zeros(3))

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> Transform:
        """From a 4x4 homogeneous matrix."""
        matrix = np.asarray(matrix, dtype=np.float64)
        return Transform(rotation_type().from_matrix(matrix[:3, :3]), matrix[:3, 3])

    @staticmethod
    def from_rpy(rpy_rad: np.ndarray, translation: np.ndarray) -> Transform:
        return Transform(rpy_to_rotation(rpy_rad), translation)

    def as_matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation.as_matrix()
        matrix[:3, 3] = self.translation
        return matrix

    def compose(self, other: Transform) -> Transform:
        """``T_A_C = T_A_B * T_B_C`` for ``self = T_A_B`` and ``other = T_B_C``."""
        return Transform(
            self.rotation * other.rotation,
            self.rotation.apply(other.translation) + self.translation,
        )

    def __mul__(self, other: Transform) -> Transform:
        return self.compose(other)

    def inverse(self) -> Transform:
        """``T_B_A`` for ``self = T_A_B``."""
        inverse_rotation = self.rotation.inv()
        return Transform(inverse_rotation, -inverse_rotation.apply(self.translation))

    def apply(self, points_B: np.ndarray) -> np.ndarray:
        """Map points from frame B to frame A (N-by-3 or 3)."""
        return self.rotation.apply(points_B) + self.translation

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """Unit quaternion ``[qx, qy, qz, qw]`` with ``qw >= 0``."""
        q = self.rotation.as_quat()
        return -q if q[3] < 0 else q

    @property
    def rpy_rad(self) -> np.ndarray:
        return rotation_to_rpy(self.rotation)

    def to_dict(self) -> dict[str, list[float]]:
        """The SPEC's YAML/JSON form, with ``translation``, ``rotation`` and ``rpy_deg``."""
        return {
            "translation": [float(v) for v in self.translation],
            "rotation": [float(v) for v in self.quaternion_xyzw],
            "rpy_deg": [float(v) for v in np.degrees(self.rpy_rad)],
        }

    @staticmethod
    def from_dict(data: Any, source: str = "<transform>", key: str = "") -> Transform:
        """Parse the SPEC's form; ``rotation`` or ``rpy_deg`` (both: they must agree).

        Raises
        ------
        ConfigError
            Naming ``source`` and the key path ``key.<field>`` of what is wrong.
        """

        def sub(name: str) -> str:
            return f"{key}.{name}" if key else name

        if not isinstance(data, Mapping):
            raise ConfigError(
                source, key, f"expected a mapping with translation and rotation, got {data!r}"
            )
        unknown = sorted(set(map(str, data)) - {"translation", "rotation", "rpy_deg"})
        if unknown:
            raise ConfigError(
                source, sub(unknown[0]), "unknown key (expected translation, rotation or rpy_deg)"
            )
        if "translation" not in data:
            raise ConfigError(source, sub("translation"), "missing required key")
        translation = _vector3(data["translation"], source, sub("translation"))

        rotation = (
            _quaternion(data["rotation"], source, sub("rotation")) if "rotation" in data else None
        )
        if "rpy_deg" in data:
            rotation_rpy = rpy_to_rotation(
                np.radians(_vector3(data["rpy_deg"], source, sub("rpy_deg")))
            )
            if rotation is not None:
                angle = float((rotation.inv() * rotation_rpy).magnitude())
                if angle > ROTATION_AGREEMENT_TOLERANCE_RAD:
                    raise ConfigError(
                        source,
                        sub("rpy_deg"),
                        f"disagrees with {sub('rotation')} by {angle:.3g} rad "
                        f"(tolerance {ROTATION_AGREEMENT_TOLERANCE_RAD:g} rad)",
                    )
            rotation = rotation_rpy if rotation is None else rotation
        if rotation is None:
            raise ConfigError(source, sub("rotation"), "missing: give rotation or rpy_deg")
        return Transform(rotation, translation)

    def __repr__(self) -> str:
        t = np.array2string(self.translation, precision=4)
        rpy = np.array2string(np.degrees(self.rpy_rad), precision=3)
        return f"Transform(t={t} m, rpy={rpy} deg)"


@dataclass(frozen=True)
class DriveStreams:
    """The IMU streams of one log: the base and one per configured sensor (by name)."""

    base: ImuStream
    sensors: Mapping[str, ImuStream]
    t0_ns: int  # first stamp of the log's IMU messages: the origin of report times

    def seconds(self, t_ns: int) -> float:
        return (t_ns - self.t0_ns) * 1e-9
