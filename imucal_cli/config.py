"""The calibration config: frozen dataclasses and a strict loader.

Every key is validated: an unknown key, a wrong type, a missing required field, a bound that is
not positive or a quaternion far from unit length raises :class:`ConfigError` naming the file and
the key path (``sensors.front_left_top.T_imu_lidar.rotation``). Nothing is silently "fixed".
``configs/default.yaml`` documents every key.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from imucal_cli.errors import ConfigError, InputError
from imucal_cli.types import Transform

T = TypeVar("T")


@dataclass(frozen=True)
class BaseConfig:
    """The base IMU: the GNSS/INS IMU, already expressed in frame B."""

    topic: str
    frame: str = "base_link"
    accel_units: str = "auto"  # auto | mps2 | g
    gyro_units: str = "auto"  # auto | radps | dps


@dataclass(frozen=True)
class SensorConfig:
    """One lidar with an embedded IMU."""

    name: str
    imu_topic: str
    T_imu_lidar: Transform
    prior_T_base_imu: Transform
    lidar_frame: str = ""
    translation_bound_m: float = 0.3
    accel_units: str = "auto"  # auto | mps2 | g
    gyro_units: str = "auto"  # auto | radps | dps
    rotation_floor_deg: float = 0.0  # systematic std the data cannot see, added to the result's
    translation_floor_m: float = 0.0


@dataclass(frozen=True)
class RestConfig:
    """Rest detection, paper eq. 5."""

    accel_tolerance_mps2: float = 0.1
    gyro_tolerance_radps: float = 0.02
    min_duration_s: float = 2.0


@dataclass(frozen=True)
class GyroBiasConfig:
    """Gyro bias Kalman filter, paper eqs. 7-9 (``Q``, ``P0`` as standard deviations in deg/s)."""

    process_noise_dps: float = 0.1
    initial_std_dps: float = 0.3


@dataclass(frozen=True)
class SegmentsConfig:
    """Observability windows, paper eqs. 18-19."""

    window_s: float = 10.0
    max_rotation_std_deg: float = 1.0


@dataclass(frozen=True)
class CalibrationConfig:
    resample_hz: float = 100.0
    max_time_offset_s: float = 0.1
    consistency_alpha: float = 0.001  # false-alarm rate of each model-consistency check


@dataclass(frozen=True)
class StopConfig:
    """When ``calibrate --until-converged`` may stop: every sensor ``ok`` within these stds."""

    max_rotation_std_deg: float = 0.1
    max_translation_std_m: float = 0.02


@dataclass(frozen=True)
class Config:
    base: BaseConfig
    sensors: tuple[SensorConfig, ...]
    rest: RestConfig = field(default_factory=RestConfig)
    gyro_bias: GyroBiasConfig = field(default_factory=GyroBiasConfig)
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    stop: StopConfig = field(default_factory=StopConfig)
    source: str = "<config>"

    def sensor(self, name: str) -> SensorConfig:
        for sensor in self.sensors:
            if sensor.name == name:
                return sensor
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        """The YAML form (as :func:`parse_config` reads it)."""
        sensors: dict[str, Any] = {}
        for s in self.sensors:
            sensors[s.name] = {
                "imu_topic": s.imu_topic,
                "lidar_frame": s.lidar_frame,
                "T_imu_lidar": s.T_imu_lidar.to_dict(),
                "prior_T_base_imu": s.prior_T_base_imu.to_dict(),
                "translation_bound_m": s.translation_bound_m,
                "accel_units": s.accel_units,
                "gyro_units": s.gyro_units,
                "rotation_floor_deg": s.rotation_floor_deg,
                "translation_floor_m": s.translation_floor_m,
            }
        return {
            "base": asdict(self.base),
            "sensors": sensors,
            "rest": asdict(self.rest),
            "gyro_bias": asdict(self.gyro_bias),
            "segments": asdict(self.segments),
            "calibration": asdict(self.calibration),
            "stop": asdict(self.stop),
        }


class _Section:
    """Reads one mapping of the config, tracking which keys were used and the key path."""

    def __init__(self, data: Any, source: str, path: str) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(source, path or "<top level>", f"expected a mapping, got {_describe(data)}")
        for key in data:
            if not isinstance(key, str):
                raise ConfigError(source, self._join(path, str(key)), "keys must be strings")
        self.data = data
        self.source = source
        self.path = path
        self.used: set[str] = set()

    @staticmethod
    def _join(path: str, key: str) -> str:
        return f"{path}.{key}" if path else key

    def key(self, name: str) -> str:
        return self._join(self.path, name)

    def get(self, name: str, parse: Callable[[Any, str], T], default: T | None = None) -> T:
        self.used.add(name)
        if name not in self.data or self.data[name] is None:
            if default is None:
                raise ConfigError(self.source, self.key(name), "missing required key")
            return default
        return parse(self.data[name], self.key(name))

    def section(self, name: str, required: bool = False) -> _Section:
        self.used.add(name)
        if name not in self.data or self.data[name] is None:
            if required:
                raise ConfigError(self.source, self.key(name), "missing required section")
            return _Section({}, self.source, self.key(name))
        return _Section(self.data[name], self.source, self.key(name))

    def reject_unknown(self, allowed: set[str] | None = None) -> None:
        known = self.used if allowed is None else allowed
        for key in self.data:
            if key not in known:
                expected = ", ".join(sorted(known))
                raise ConfigError(self.source, self.key(key), f"unknown key (expected one of: {expected})")


def _describe(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"


def _string(source: str) -> Callable[[Any, str], str]:
    def parse(value: Any, key: str) -> str:
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(source, key, f"expected a non-empty string, got {_describe(value)}")
        return value

    return parse


def _number(source: str, positive: bool = True, allow_zero: bool = False) -> Callable[[Any, str], float]:
    def parse(value: Any, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(source, key, f"expected a number, got {_describe(value)}")
        number = float(value)
        if not math.isfinite(number):
            raise ConfigError(source, key, f"expected a finite number, got {value!r}")
        if positive and (number < 0 or (number == 0 and not allow_zero)):
            bound = ">= 0" if allow_zero else "> 0"
            raise ConfigError(source, key, f"must be {bound}, got {value!r}")
        return number

    return parse


ACCEL_UNITS = ("auto", "mps2", "g")
GYRO_UNITS = ("auto", "radps", "dps")


def _choice(source: str, choices: tuple[str, ...]) -> Callable[[Any, str], str]:
    def parse(value: Any, key: str) -> str:
        if value not in choices:
            raise ConfigError(source, key, f"expected one of {', '.join(choices)}, got {_describe(value)}")
        return value

    return parse


def _transform(source: str) -> Callable[[Any, str], Transform]:
    def parse(value: Any, key: str) -> Transform:
        return Transform.from_dict(value, source, key)

    return parse


def parse_config(data: Any, source: str = "<config>") -> Config:
    """Validate a config mapping (as loaded from YAML) into a :class:`Config`."""
    top = _Section(data, source, "")
    string, positive, transform = _string(source), _number(source), _transform(source)
    non_negative = _number(source, allow_zero=True)

    base_section = top.section("base", required=True)
    accel_units, gyro_units = _choice(source, ACCEL_UNITS), _choice(source, GYRO_UNITS)
    base = BaseConfig(
        topic=base_section.get("topic", string),
        frame=base_section.get("frame", string, BaseConfig.frame),
        accel_units=base_section.get("accel_units", accel_units, BaseConfig.accel_units),
        gyro_units=base_section.get("gyro_units", gyro_units, BaseConfig.gyro_units),
    )
    base_section.reject_unknown()

    sensors_section = top.section("sensors", required=True)
    if not sensors_section.data:
        raise ConfigError(source, "sensors", "needs at least one sensor")
    sensors: list[SensorConfig] = []
    for name in sensors_section.data:
        s = sensors_section.section(name, required=True)
        sensor = SensorConfig(
            name=name,
            imu_topic=s.get("imu_topic", string),
            lidar_frame=s.get("lidar_frame", string, f"{name}_lidar"),
            T_imu_lidar=s.get("T_imu_lidar", transform),
            prior_T_base_imu=s.get("prior_T_base_imu", transform),
            translation_bound_m=s.get(
                "translation_bound_m", positive, SensorConfig.translation_bound_m
            ),
            accel_units=s.get("accel_units", accel_units, SensorConfig.accel_units),
            gyro_units=s.get("gyro_units", gyro_units, SensorConfig.gyro_units),
            rotation_floor_deg=s.get("rotation_floor_deg", non_negative, SensorConfig.rotation_floor_deg),
            translation_floor_m=s.get("translation_floor_m", non_negative, SensorConfig.translation_floor_m),
        )
        s.reject_unknown()
        sensors.append(sensor)
    sensors_section.reject_unknown()

    topics: dict[str, str] = {base.topic: "base.topic"}
    frames: dict[str, str] = {base.frame: "base.frame"}
    for sensor in sensors:
        key = f"sensors.{sensor.name}.imu_topic"
        if sensor.imu_topic in topics:
            raise ConfigError(
                source, key, f"topic {sensor.imu_topic!r} is already used by {topics[sensor.imu_topic]}"
            )
        topics[sensor.imu_topic] = key
        key = f"sensors.{sensor.name}.lidar_frame"
        if sensor.lidar_frame in frames:
            raise ConfigError(
                source, key, f"frame {sensor.lidar_frame!r} is already used by {frames[sensor.lidar_frame]}"
            )
        frames[sensor.lidar_frame] = key

    r = top.section("rest")
    rest = RestConfig(
        accel_tolerance_mps2=r.get("accel_tolerance_mps2", positive, RestConfig.accel_tolerance_mps2),
        gyro_tolerance_radps=r.get("gyro_tolerance_radps", positive, RestConfig.gyro_tolerance_radps),
        min_duration_s=r.get("min_duration_s", positive, RestConfig.min_duration_s),
    )
    r.reject_unknown()

    g = top.section("gyro_bias")
    gyro_bias = GyroBiasConfig(
        process_noise_dps=g.get("process_noise_dps", positive, GyroBiasConfig.process_noise_dps),
        initial_std_dps=g.get("initial_std_dps", positive, GyroBiasConfig.initial_std_dps),
    )
    g.reject_unknown()

    seg = top.section("segments")
    segments = SegmentsConfig(
        window_s=seg.get("window_s", positive, SegmentsConfig.window_s),
        max_rotation_std_deg=seg.get(
            "max_rotation_std_deg", positive, SegmentsConfig.max_rotation_std_deg
        ),
    )
    seg.reject_unknown()

    c = top.section("calibration")
    calibration = CalibrationConfig(
        resample_hz=c.get("resample_hz", positive, CalibrationConfig.resample_hz),
        max_time_offset_s=c.get(
            "max_time_offset_s", _number(source, allow_zero=True), CalibrationConfig.max_time_offset_s
        ),
        consistency_alpha=c.get("consistency_alpha", positive, CalibrationConfig.consistency_alpha),
    )
    if not calibration.consistency_alpha < 0.5:
        raise ConfigError(source, "calibration.consistency_alpha", f"a false-alarm rate below 0.5, got {calibration.consistency_alpha!r}")
    c.reject_unknown()

    st = top.section("stop")
    stop = StopConfig(
        max_rotation_std_deg=st.get("max_rotation_std_deg", positive, StopConfig.max_rotation_std_deg),
        max_translation_std_m=st.get("max_translation_std_m", positive, StopConfig.max_translation_std_m),
    )
    st.reject_unknown()
    top.reject_unknown()

    return Config(
        base=base,
        sensors=tuple(sensors),
        rest=rest,
        gyro_bias=gyro_bias,
        segments=segments,
        calibration=calibration,
        stop=stop,
        source=source,
    )


def load_config(path: str | Path) -> Config:
    """Load and validate a YAML config file.

    Raises
    ------
    ConfigError
        Naming the file and the key path of the first problem found.
    """
    from imucal_cli.documents import load_document

    try:
        data = load_document(path)
    except InputError as exc:
        raise ConfigError(str(path), "", str(exc).removeprefix(f"{path}: ")) from None
    if data is None:
        raise ConfigError(str(path), "", "the file is empty")
    return parse_config(data, str(path))
