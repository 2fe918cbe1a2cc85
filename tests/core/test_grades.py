"""IMU grades (SPEC): the priors on each IMU's own errors, and what of them reaches the std."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from scipy.spatial.transform import Rotation

from imucal_cli.core.grades import GRADES, error_prior_std
from imucal_cli.core.model import (
    ACCEL_AXES,
    ACCEL_ROTATION,
    BASE_ACCEL_AXES,
    BASE_GYRO_AXES,
    BASE_GYRO_SCALE,
    EXTRINSICS,
    GYRO_AXES,
    N_PARAMETERS,
    ROTATION,
    SENSOR_ERRORS,
    Point,
)
from imucal_cli.core.solver import Fit
from imucal_cli.core.uncertainty import carried


class _Linear:
    """A linear least-squares problem ``y = J p + noise`` standing in for the solver's: its
    information over any set of globals is ``J^T J`` of those columns."""

    def __init__(self, J: np.ndarray) -> None:
        self.J = J

    def information(self, fit: Fit, free: np.ndarray) -> np.ndarray:
        columns = self.J[:, free]
        return columns.T @ columns


def test_a_held_error_moves_the_estimate_as_the_carried_covariance_says():
    """Least squares over the free globals with an error held at zero: the error ``e`` moves
    the estimate by ``-(J_f^T J_f)^-1 J_f^T J_c e``; over ``e`` drawn from its prior that is the
    covariance :func:`carried` adds (rotation turned into base axes), computed here from the
    regression itself."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(200, N_PARAMETERS))
    free = np.zeros(N_PARAMETERS, dtype=bool)
    free[EXTRINSICS] = True
    prior = np.zeros(N_PARAMETERS)
    prior[ACCEL_AXES] = 0.01
    prior[BASE_GYRO_AXES] = 0.002
    R = Rotation.from_rotvec(rng.normal(size=3))
    fit = Fit(Point(R, np.zeros(3), 0.0), np.zeros((2, 6)), free, 1.0, 1.0)
    held = prior > 0
    # the estimate's response to each held error, by solving the regression for that column
    response = np.linalg.lstsq(J[:, free], -J[:, held], rcond=None)[0]
    expected = response @ np.diag(prior[held] ** 2) @ response.T
    to_base = np.eye(7)
    to_base[ROTATION, ROTATION] = R.as_matrix()
    expected = (to_base @ expected @ to_base.T)[:6, :6]
    np.testing.assert_allclose(carried(_Linear(J), fit, prior), expected, rtol=1e-10, atol=1e-18)
    # an estimated error (free) or one without a prior carries nothing
    fit.free[held] = True
    assert np.all(carried(_Linear(J), fit, prior) == 0.0)


def test_the_priors_follow_the_grades_and_ideal_carries_nothing():
    consumer, tactical = GRADES["consumer"], GRADES["tactical"]
    prior = error_prior_std(consumer, tactical)
    # the gyro's axes are relative: both grades add; the base's own terms take the base's
    assert prior[GYRO_AXES][0] == np.hypot(consumer.scale, tactical.scale)
    assert prior[ACCEL_AXES][0] == consumer.scale
    assert prior[BASE_GYRO_AXES][0] == tactical.scale
    assert prior[BASE_GYRO_SCALE][0] == 0.0  # (the axes carry the grade's scale)
    assert prior[BASE_GYRO_AXES][3] == tactical.nonorthogonality_rad
    assert prior[BASE_ACCEL_AXES][0] == tactical.scale
    assert prior[ACCEL_ROTATION][0] == np.hypot(
        consumer.misalignment_rad, tactical.misalignment_rad
    )
    assert np.all(prior[: SENSOR_ERRORS.start] == 0.0)  # the extrinsics, clock, tilt: none
    assert np.all(error_prior_std(GRADES["ideal"], GRADES["ideal"]) == 0.0)
    # each grade is at least as good as the one before it
    order = ["consumer", "industrial", "tactical", "navigation", "ideal"]
    for worse, better in pairwise(order):
        for field in ("scale", "nonorthogonality_rad", "misalignment_rad", "housing_rad"):
            assert getattr(GRADES[better], field) <= getattr(GRADES[worse], field)


def test_the_base_housing_turns_the_lever_arm_with_the_rotation():
    """A base IMU turned against B by ``rho`` turns every estimate with it: the rotation by
    ``rho`` and the lever arm ``t`` to ``exp(rho) t``. The covariance carried is that map's,
    ``J std^2 J^T`` with ``J = d[rotation, t]/d rho``, checked by turning ``t``."""
    from imucal_cli.core.uncertainty import turned_frame

    rng = np.random.default_rng(11)
    t, std = rng.normal(size=3) * 3.0, np.radians(0.05)
    rho = rng.normal(size=3) * 1e-7
    moved = Rotation.from_rotvec(rho).apply(t) - t
    J = np.zeros((6, 3))
    for k in range(3):  # the map, column by column, from the rotation itself
        step = np.zeros(3)
        step[k] = 1e-7
        J[:3, k] = step / 1e-7
        J[3:, k] = (Rotation.from_rotvec(step).apply(t) - t) / 1e-7
    np.testing.assert_allclose(J[3:] @ rho, moved, rtol=1e-5, atol=1e-15)
    np.testing.assert_allclose(turned_frame(t, std), std**2 * J @ J.T, rtol=1e-5, atol=1e-14)
    assert np.all(turned_frame(t, 0.0) == 0.0)
