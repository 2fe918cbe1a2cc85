"""The outcome of a calibration: every sensor's estimate with what the run measured."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from imucal_cli.config import Config
from imucal_cli.core.calibrate import SensorEstimate
from imucal_cli.types import Transform


@dataclass(frozen=True)
class CalibrationResult:
    estimates: dict[str, SensorEstimate]
    config: Config
    #: Median sample rate of each IMU ("base" and the sensor names), where measured (Hz).
    rates_hz: Mapping[str, float] = field(default_factory=dict)
    #: White-noise density of each IMU's gyro and accelerometer (rad/s/sqrt(Hz), m/s^2/sqrt(Hz)).
    noise_density: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    def T_base_lidar(self, name: str) -> Transform:
        return self.estimates[name].T_base_imu * self.config.sensor(name).T_imu_lidar

    @property
    def all_ok(self) -> bool:
        return all(e.status == "ok" for e in self.estimates.values())
