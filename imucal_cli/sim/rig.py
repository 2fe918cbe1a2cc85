"""The simulated vehicle's sensor rig: where the lidars sit and where their IMUs are inside them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imucal_cli.types import Transform

#: An Ouster OS1-like lidar: the IMU origin sits at [6.253, -11.775, 7.645] mm in the sensor
#: frame (axes aligned); the lidar frame is rotated 180 deg about z and raised 36.18 mm.
#: T_imu_lidar = T_sensor_imu^-1 * T_sensor_lidar.
T_SENSOR_IMU = Transform.from_rpy(np.zeros(3), np.array([6.253e-3, -11.775e-3, 7.645e-3]))
T_SENSOR_LIDAR = Transform.from_rpy(np.array([0.0, 0.0, np.pi]), np.array([0.0, 0.0, 36.18e-3]))
OUSTER_T_IMU_LIDAR = T_SENSOR_IMU.inverse() * T_SENSOR_LIDAR


@dataclass(frozen=True)
class LidarMount:
    """A lidar with an embedded IMU, mounted on the vehicle."""

    name: str
    T_base_lidar: Transform
    T_imu_lidar: Transform = OUSTER_T_IMU_LIDAR

    @property
    def T_base_imu(self) -> Transform:
        return self.T_base_lidar * self.T_imu_lidar.inverse()

    @property
    def imu_topic(self) -> str:
        return f"/lidar/{self.name}/imu"

    @property
    def imu_frame(self) -> str:
        return f"{self.name}_imu"

    @property
    def lidar_frame(self) -> str:
        return f"{self.name}_lidar"


def _mount(name: str, xyz: list[float], rpy_deg: list[float]) -> LidarMount:
    return LidarMount(name, Transform.from_rpy(np.radians(rpy_deg), np.array(xyz)))


#: A truck cab rig (base at the rear-axle centre, x forward, y left, z up), as in the paper's
#: Fig. 1: the two front-top lidars first, then two rear-top ones. Real yaw and a downward pitch.
DEFAULT_MOUNTS: tuple[LidarMount, ...] = (
    _mount("front_left_top", [4.35, 1.12, 2.95], [1.2, 6.0, 42.0]),
    _mount("front_right_top", [4.35, -1.12, 2.95], [-0.8, 5.5, -44.0]),
    _mount("rear_left_top", [-0.85, 1.20, 3.10], [0.6, 4.0, 133.0]),
    _mount("rear_right_top", [-0.85, -1.20, 3.10], [-0.5, 4.5, -136.0]),
)


def cad_prior(
    T_base_imu: Transform,
    rng: np.random.Generator,
    rotation_std_deg: float = 2.0,
    translation_std_m: float = 0.04,
    translation_limit_m: float = 0.1,
) -> Transform:
    """A CAD estimate: the truth perturbed by a few degrees and centimetres.

    The translation error is clipped to ``translation_limit_m`` per axis so the truth stays
    well inside the default ``translation_bound_m`` box around the prior.
    """
    from scipy.spatial.transform import Rotation

    rotation_error = Rotation.from_rotvec(np.radians(rng.normal(0.0, rotation_std_deg, 3)))
    translation_error = np.clip(
        rng.normal(0.0, translation_std_m, 3), -translation_limit_m, translation_limit_m
    )
    return Transform(
        T_base_imu.rotation * rotation_error, T_base_imu.translation + translation_error
    )


#: The ``wheel`` scenario's rig: IMUs on the wheel itself (the base at the hub), as the real
#: recording had them (one 14 cm out); the IMU is the "lidar" (``T_imu_lidar`` the identity).
WHEEL_MOUNTS: tuple[LidarMount, ...] = tuple(
    LidarMount(name, Transform.from_rpy(np.radians(rpy_deg), np.array(xyz)), Transform.identity())
    for name, xyz, rpy_deg in (
        ("rim", [0.02, 0.14, 0.0], [0.0, 0.0, 0.0]),
        ("spoke", [0.03, -0.06, 0.09], [90.0, 0.0, 30.0]),
    )
)
