"""IMU grades (SPEC "IMU grades"): a prior on each IMU's own errors, from datasheets.

Every figure is one standard deviation per axis, about a third of the tolerance a datasheet
gives as its limit (a typical figure where it gives one). ``configs/default.yaml`` documents
the same numbers. The calibration estimates the errors a drive determines and carries the
rest into the reported std (:func:`error_prior_std`, :func:`imucal_cli.core.uncertainty.carried`);
an IMU's alignment to its housing no drive can see: it joins the rotation's floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imucal_cli.core.model import (
    ACCEL_AXES,
    ACCEL_ROTATION,
    AXIS_ERRORS,
    BASE_ACCEL_AXES,
    BASE_GYRO_AXES,
    G_SENSITIVITY,
    GYRO_AXES,
    N_PARAMETERS,
)
from imucal_cli.types import GRAVITY_MPS2

DEG = np.pi / 180.0
#: g-sensitivity in deg/s per g, to rad/s per m/s^2.
DPS_PER_G = DEG / GRAVITY_MPS2


@dataclass(frozen=True)
class Grade:
    """One grade's prior (one std per axis)."""

    scale: float  # scale-factor error of either triad (fraction)
    nonorthogonality_rad: float  # a triad's axes off orthogonal (cross-axis sensitivity)
    misalignment_rad: float  # the gyro triad against the accelerometer triad
    g_sensitivity: float  # the gyro's error per specific force (rad/s per m/s^2)
    housing_rad: float  # the triads against the housing the extrinsics refer to
    #: The bias random walks in Kalibr's terms (gyro rad/s^2/sqrt(Hz), accelerometer
    #: m/s^3/sqrt(Hz)), an order of magnitude for the class: what a base IMU's export says,
    #: which no drive measures apart from its sensors' (None: the drive's figure is used).
    random_walks: tuple[float, float] | None = None


#: consumer: phone-class MEMS, the IMUs inside lidars (InvenSense ICM-20948 and ICM-42688,
#: Bosch BMI088: sensitivity tolerance +-1.5%, cross-axis sensitivity +-2%, gyro g-sensitivity
#: about 0.1 deg/s/g; the die placed on its board to about +-1 deg). industrial: MEMS modules
#: calibrated by their maker (Analog Devices ADIS16470/16500, Xsens MTi-600, VectorNav VN-100:
#: scale 0.1-0.3%, axis misalignment 0.05-0.2 deg, g-sensitivity about 0.01 deg/s/g).
#: tactical: a vehicle INS (Honeywell HG4930, Novatel SPAN, FOG units such as the KVH 1750:
#: scale factors 100-500 ppm, misalignment about 0.01-0.03 deg, g-sensitivity negligible).
#: navigation: ring-laser and high-end FOG units (scale factors of a few ppm). ideal: simulated
#: IMUs only, no errors.
#: The random walks: industrial as EuRoC's Kalibr file gives its ADIS16448 (1.94e-5, 3.0e-3),
#: consumer parts a few times worse, a tactical INS (bias stability 0.25 deg/h, 25 ug) and a
#: navigation unit one and two orders better.
GRADES = {
    "consumer": Grade(0.005, 0.4 * DEG, 0.1 * DEG, 0.1 * DPS_PER_G, 0.5 * DEG, (1e-4, 4e-3)),
    "industrial": Grade(0.001, 0.05 * DEG, 0.05 * DEG, 0.01 * DPS_PER_G, 0.1 * DEG, (2e-5, 3e-3)),
    "tactical": Grade(3e-4, 0.01 * DEG, 0.01 * DEG, 0.001 * DPS_PER_G, 0.05 * DEG, (1e-6, 1e-4)),
    "navigation": Grade(2e-5, 0.002 * DEG, 0.002 * DEG, 0.0, 0.01 * DEG, (1e-7, 1e-5)),
    "ideal": Grade(0.0, 0.0, 0.0, 0.0, 0.0),
}


def _axes(grade: Grade) -> np.ndarray:
    """A triad's six axis errors' prior std (:data:`~imucal_cli.core.model.AXIS_ERRORS`)."""
    out = np.zeros(AXIS_ERRORS.size)
    out[AXIS_ERRORS["scale"]] = grade.scale
    out[AXIS_ERRORS["nonorthogonality"]] = grade.nonorthogonality_rad
    return out


def error_prior_std(sensor: Grade, base: Grade) -> np.ndarray:
    """The prior std of every global (0 where none: the extrinsics, the clock, the tilt) from
    the two IMUs' grades. The model's sensor errors are relative to the base's: where both
    IMUs' errors enter alike the two priors add (the gyro's axes, its g-sensitivity, the
    triads' misalignment); the base's own terms (its gyro's axes in the lever arm's terms, its
    accelerometer's axes) take the base's, and the sensor accelerometer's axes the sensor's. The
    base gyro's common scale beyond its axes' (a gyro that reads low) has none: the axes carry
    the grade's scale."""
    out = np.zeros(N_PARAMETERS)
    out[ACCEL_AXES] = _axes(sensor)
    out[GYRO_AXES] = np.hypot(_axes(sensor), _axes(base))
    out[G_SENSITIVITY] = np.hypot(sensor.g_sensitivity, base.g_sensitivity)
    out[ACCEL_ROTATION] = np.hypot(sensor.misalignment_rad, base.misalignment_rad)
    out[BASE_GYRO_AXES] = _axes(base)
    out[BASE_ACCEL_AXES] = _axes(base)
    return out
