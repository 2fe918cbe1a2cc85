"""Smooth vehicle trajectories with exact derivatives.

A :class:`Trajectory` is a quintic B-spline of the base frame's world position and of its ROS RPY
angles (``R_W_B = Rz(yaw) Ry(pitch) Rx(roll)``). Velocity, acceleration, angular velocity and
angular acceleration follow from the spline derivatives in closed form, so the specific force at
any lever-arm point is exact (to floating-point precision), not a finite-difference estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from imucal_cli.types import GRAVITY_MPS2

#: The world frame W is ENU-like: z up, gravity along -z.
GRAVITY_W = np.array([0.0, 0.0, -GRAVITY_MPS2])


@dataclass(frozen=True)
class KinematicState:
    """The base frame's motion at N instants.

    Attributes
    ----------
    R_world_base : Rotation (N)
    p_world : (N, 3) position of the base origin in W, m
    v_world : (N, 3) velocity in W, m/s
    a_world : (N, 3) acceleration in W, m/s^2
    w_base : (N, 3) angular velocity of B expressed in B, rad/s
    dw_base : (N, 3) its time derivative, rad/s^2
    """

    R_world_base: Rotation
    p_world: np.ndarray
    v_world: np.ndarray
    a_world: np.ndarray
    w_base: np.ndarray
    dw_base: np.ndarray

    @property
    def f_base(self) -> np.ndarray:
        """Specific force at the base origin in B: ``R_W_B^T (a_W - g_W)``, m/s^2."""
        return self.R_world_base.inv().apply(self.a_world - GRAVITY_W)

    def specific_force_at(self, t_base_point: np.ndarray) -> np.ndarray:
        """Specific force (in B) at a point fixed to the body at ``t_base_point`` (in B).

        ``f_B + dw_B x t + w_B x (w_B x t)`` (rigid-body kinematics; SPEC, paper eq. 11).
        """
        t = np.asarray(t_base_point, dtype=np.float64)
        w = self.w_base
        return (
            self.f_base
            + np.cross(self.dw_base, t)
            + np.cross(w, np.cross(w, np.broadcast_to(t, w.shape)))
        )


def euler_rates_to_body(
    rpy: np.ndarray, drpy: np.ndarray, ddrpy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Body angular velocity and acceleration from ROS RPY angles and their derivatives.

    For ``R = Rz(yaw) Ry(pitch) Rx(roll)``, with ``R^T dR/dt = [w]x``::

        w = [roll' - yaw' sin(pitch),
             pitch' cos(roll) + yaw' sin(roll) cos(pitch),
             -pitch' sin(roll) + yaw' cos(roll) cos(pitch)]

    and ``dw`` its exact time derivative. Arrays are (N, 3).
    """
    phi, theta = rpy[:, 0], rpy[:, 1]
    dphi, dtheta, dpsi = drpy[:, 0], drpy[:, 1], drpy[:, 2]
    ddphi, ddtheta, ddpsi = ddrpy[:, 0], ddrpy[:, 1], ddrpy[:, 2]
    sphi, cphi = np.sin(phi), np.cos(phi)
    sth, cth = np.sin(theta), np.cos(theta)
    w = np.column_stack(
        [dphi - dpsi * sth, dtheta * cphi + dpsi * sphi * cth, -dtheta * sphi + dpsi * cphi * cth]
    )
    dw = np.column_stack(
        [
            ddphi - ddpsi * sth - dpsi * dtheta * cth,
            ddtheta * cphi
            - dtheta * dphi * sphi
            + ddpsi * sphi * cth
            + dpsi * dphi * cphi * cth
            - dpsi * dtheta * sphi * sth,
            -ddtheta * sphi
            - dtheta * dphi * cphi
            + ddpsi * cphi * cth
            - dpsi * dphi * sphi * cth
            - dpsi * dtheta * cphi * sth,
        ]
    )
    return w, dw


@dataclass(frozen=True)
class Trajectory:
    """Base-frame motion as quintic B-splines of world position and ROS RPY angles."""

    position_world: BSpline  # t [s] -> (3,) m
    rpy: BSpline  # t [s] -> (roll, pitch, yaw) rad, yaw unwrapped
    t_start_s: float
    t_end_s: float

    @staticmethod
    def from_samples(t_s: np.ndarray, position_world: np.ndarray, rpy: np.ndarray) -> Trajectory:
        """Interpolate smooth samples (N, 3) on a time grid with quintic splines."""
        t_s = np.asarray(t_s, dtype=np.float64)
        return Trajectory(
            make_interp_spline(t_s, np.asarray(position_world, dtype=np.float64), k=5),
            make_interp_spline(t_s, np.asarray(rpy, dtype=np.float64), k=5),
            float(t_s[0]),
            float(t_s[-1]),
        )

    def state(self, t_s: np.ndarray) -> KinematicState:
        """Exact kinematics at times ``t_s`` (seconds, inside the trajectory's span)."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        angles = self.rpy(t_s)
        w, dw = euler_rates_to_body(angles, self.rpy(t_s, nu=1), self.rpy(t_s, nu=2))
        return KinematicState(
            R_world_base=Rotation.from_euler("xyz", angles),
            p_world=self.position_world(t_s),
            v_world=self.position_world(t_s, nu=1),
            a_world=self.position_world(t_s, nu=2),
            w_base=w,
            dw_base=dw,
        )
