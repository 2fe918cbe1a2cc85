"""The calibration config: frozen dataclasses and a strict loader.

Every key is validated: an unknown key, a wrong type, a missing required field, a bound that is
not positive or a quaternion far from unit length raises :class:`ConfigError` naming the file and
the key path (``sensors.front_left_top.T_imu_lidar.rotation``). Nothing is silently "fixed".
``configs/default.yaml`` documents every key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import Any, TypeVar

from imucal_cli.core.grades import GRADES
from imucal_cli.errors import ConfigError, InputError
from imucal_cli.names import name_problem, printable
from imucal_cli.types import Transform

T = TypeVar("T")


@dataclass(frozen=True)
class BaseConfig:
    """The base IMU: the GNSS/INS IMU, at ``T_base_imu`` in frame B."""

    topic: str
    frame: str = "base_link"
    #: Where the base IMU sits in B (default: at B's origin, in B's axes).
    T_base_imu: Transform = field(default_factory=Transform.identity)
    grade: str = "tactical"  # SPEC "IMU grades": a vehicle INS
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
    #: The IMU's frame in /tf_static or the URDF, where its messages' frame_id is not that
    #: frame (empty: the frame_id).
    imu_frame: str = ""
    translation_bound_m: float = 0.3
    #: How far the estimate's rotation may lie from the prior's: a check, not a constraint.
    rotation_bound_deg: float = 20.0
    accel_units: str = "auto"  # auto | mps2 | g
    gyro_units: str = "auto"  # auto | radps | dps
    grade: str = "consumer"  # SPEC "IMU grades": the IMU inside a lidar
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
    max_clock_drift_ppm: float = 200.0  # 0: one offset for the whole log
    epoch_s: float = 300.0  # the timeline's slice
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
    #: Per sensor, where each transform came from: config (or its default) or tf_static
    #: (:func:`imucal_cli.frames.complete_from_log`); empty where no log was asked.
    priors: Mapping[str, Mapping[str, str]] = field(default_factory=dict)

    def imu_names(self) -> dict[str, str]:
        """Every configured IMU topic and the name the calibrator knows it by ("base",
        the sensors')."""
        return {self.base.topic: "base"} | {s.imu_topic: s.name for s in self.sensors}

    def sensor(self, name: str) -> SensorConfig:
        for sensor in self.sensors:
            if sensor.name == name:
                return sensor
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        """The YAML form (as :func:`parse_config` reads it)."""

        def plain(
            section: Any,
        ) -> dict[str, Any]:  # (not asdict: a Transform has its own YAML form)
            values = {  # (an imu_frame not given is the messages' frame_id: left out)
                f.name: getattr(section, f.name)
                for f in dataclass_fields(section)
                if f.name != "name" and getattr(section, f.name) != ""
            }
            return {k: v.to_dict() if isinstance(v, Transform) else v for k, v in values.items()}

        return {
            "base": plain(self.base),
            "sensors": {s.name: plain(s) for s in self.sensors},
            **{name: plain(getattr(self, name)) for name in SECTIONS},
        }


#: The optional sections after ``base`` and ``sensors``, in the YAML's order.
SECTIONS = {
    "rest": RestConfig,
    "gyro_bias": GyroBiasConfig,
    "segments": SegmentsConfig,
    "calibration": CalibrationConfig,
    "stop": StopConfig,
}
#: Keys whose value may be zero (every other number must be positive), and keys with choices.
MAY_BE_ZERO = {
    "rotation_floor_deg",
    "translation_floor_m",
    "max_time_offset_s",
    "max_clock_drift_ppm",
}
CHOICES = {
    "accel_units": ("auto", "mps2", "g"),
    "gyro_units": ("auto", "radps", "dps"),
    "grade": tuple(GRADES),
}
#: Sane ranges of the numbers (inclusive), with why: a value outside is a mistake (a unit, a
#: typo) or would cost unbounded work (``window_s: 1e-6`` over an hour is 3.6 G windows).
RANGES: dict[str, tuple[float, float, str]] = {
    "accel_tolerance_mps2": (0.0, 10.0, "m/s^2"),
    "gyro_tolerance_radps": (0.0, 1.0, "rad/s"),
    "min_duration_s": (0.0, 3600.0, "s"),
    "process_noise_dps": (0.0, 100.0, "deg/s"),
    "initial_std_dps": (0.0, 100.0, "deg/s"),
    "window_s": (1.0, 600.0, "s: a window holds seconds of driving"),
    "max_rotation_std_deg": (0.0, 180.0, "deg"),
    "max_translation_std_m": (0.0, 10.0, "m"),
    "resample_hz": (10.0, 1000.0, "Hz: the fit low-passes at 5 Hz; more only costs memory"),
    "max_time_offset_s": (0.0, 1.0, "s: clocks further apart are another clock, not an offset"),
    "max_clock_drift_ppm": (0.0, 10000.0, "ppm: crystals drift 10-100 ppm"),
    "epoch_s": (10.0, 86400.0, "s"),
    "translation_bound_m": (0.0, 10.0, "m"),
    "rotation_bound_deg": (0.0, 180.0, "deg"),
    "rotation_floor_deg": (0.0, 90.0, "deg"),
    "translation_floor_m": (0.0, 10.0, "m"),
}
#: The name the base IMU goes by beside the sensors' (SPEC biases: ``imus: base:``).
RESERVED_SENSOR_NAME = "base"
#: A lidar's IMU lies inside its housing; a CAD prior inside the vehicle (m).
MAX_IMU_IN_LIDAR_M, MAX_PRIOR_M = 1.0, 100.0
#: Keys that hold a ROS name, and its kind (:func:`imucal_cli.names.name_problem`): they go into
#: launch scripts, URDF and Kalibr files, so anything outside ROS's rules is refused here.
NAME_KINDS = {
    "frame": "frame",
    "lidar_frame": "frame",
    "imu_frame": "frame",
    "topic": "topic",
    "imu_topic": "topic",
}


class _Section:
    """Reads one mapping of the config, tracking which keys were used and the key path."""

    def __init__(self, data: Any, source: str, path: str) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(
                source, path or "<top level>", f"expected a mapping, got {_describe(data)}"
            )
        for key in data:
            if not isinstance(key, str):
                raise ConfigError(
                    source, f"{path}.{key}" if path else str(key), "keys must be strings"
                )
        self.data, self.source, self.path = data, source, path
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def section(self, name: str, required: bool = False) -> _Section:
        self.used.add(name)
        if self.data.get(name) is None:
            if required:
                raise ConfigError(self.source, self.key(name), "missing required section")
            return _Section({}, self.source, self.key(name))
        return _Section(self.data[name], self.source, self.key(name))

    def fields(self, cls: type[T], **given: Any) -> T:
        """A ``cls`` from this section: each field of it read and checked by its type (a
        number, a string, a choice, a transform), ``given`` ones not read; no other key allowed."""
        values = dict(given)
        for f in dataclass_fields(cls):  # type: ignore[arg-type]
            if f.name in given:
                continue
            self.used.add(f.name)
            value, key = self.data.get(f.name), self.key(f.name)
            if value is None:
                if f.default is MISSING and f.default_factory is MISSING:
                    raise ConfigError(self.source, key, "missing required key")
                continue
            values[f.name] = _parse(value, f.name, f.type, self.source, key)
        self.reject_unknown()
        return cls(**values)

    def reject_unknown(self) -> None:
        for key in self.data:
            if key not in self.used:
                raise ConfigError(
                    self.source,
                    self.key(key),
                    f"unknown key (expected one of: {', '.join(sorted(self.used))})",
                )


def _describe(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"


def _parse(value: Any, name: str, kind: Any, source: str, key: str) -> Any:
    """One value by its field's type (as a string: the annotations are postponed)."""
    if kind == "Transform":
        return Transform.from_dict(value, source, key)
    if name in CHOICES:
        if value not in CHOICES[name]:
            raise ConfigError(
                source, key, f"expected one of {', '.join(CHOICES[name])}, got {_describe(value)}"
            )
        return value
    if kind == "str":
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(source, key, f"expected a non-empty string, got {_describe(value)}")
        problem = name_problem(value, NAME_KINDS[name]) if name in NAME_KINDS else None
        if problem:
            raise ConfigError(source, key, problem)
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(source, key, f"expected a number, got {_describe(value)}")
    try:
        number = float(value)
    except OverflowError:  # (an int of hundreds of digits)
        number = math.inf
    if not math.isfinite(number):
        raise ConfigError(source, key, f"expected a finite number, got {value!r}")
    if number < 0 or (number == 0 and name not in MAY_BE_ZERO):
        raise ConfigError(
            source, key, f"must be {'>= 0' if name in MAY_BE_ZERO else '> 0'}, got {value!r}"
        )
    low, high, unit = RANGES.get(name, (-math.inf, math.inf, ""))
    if not low <= number <= high:
        raise ConfigError(source, key, f"must be within {low:g} to {high:g} {unit}, got {value!r}")
    return number


def parse_config(data: Any, source: str = "<config>") -> Config:
    """Validate a config mapping (as loaded from YAML) into a :class:`Config`."""
    top = _Section(data, source, "")
    base = top.section("base", required=True).fields(BaseConfig)
    _within(source, "base.T_base_imu", base.T_base_imu, MAX_PRIOR_M)
    sensors_section = top.section("sensors", required=True)
    if not sensors_section.data:
        raise ConfigError(source, "sensors", "needs at least one sensor")
    sensors = [_sensor(sensors_section, name, source) for name in sensors_section.data]
    _unique(base, sensors, source)
    sections: dict[str, Any] = {
        name: top.section(name).fields(cls) for name, cls in SECTIONS.items()
    }
    if not sections["calibration"].consistency_alpha < 0.5:
        raise ConfigError(
            source,
            "calibration.consistency_alpha",
            f"a false-alarm rate below 0.5, got {sections['calibration'].consistency_alpha!r}",
        )
    top.reject_unknown()
    return Config(base=base, sensors=tuple(sensors), **sections, source=source)


def _within(source: str, key: str, T: Transform, limit: float, hint: str = "") -> None:
    length = math.hypot(*T.translation)  # (no overflow warning at 1e308)
    if length > limit:
        raise ConfigError(
            source,
            f"{key}.translation",
            f"{length:.4g} m from the origin, more than {limit:g} m{'; ' + hint if hint else ''}",
        )


def _sensor(sensors: _Section, name: Any, source: str) -> SensorConfig:
    """One sensor's section, its name and the lengths of its transforms checked."""
    problem = name_problem(name, "sensor")
    if name == RESERVED_SENSOR_NAME:
        problem = (
            f"{name!r} names the base IMU (the documents' base entry, biases' imus.base): "
            "name this lidar otherwise"
        )
    if problem:
        raise ConfigError(source, f"sensors.{printable(name)}", problem)
    sensor = sensors.section(name, required=True).fields(SensorConfig, name=name)
    hint = (
        "a lidar's IMU lies inside its housing: given in mm? (Ouster's metadata is: divide by 1000)"
    )
    _within(source, f"sensors.{name}.T_imu_lidar", sensor.T_imu_lidar, MAX_IMU_IN_LIDAR_M, hint)
    _within(source, f"sensors.{name}.prior_T_base_imu", sensor.prior_T_base_imu, MAX_PRIOR_M)
    return sensor if sensor.lidar_frame else replace(sensor, lidar_frame=f"{name}_lidar")


def _unique(base: BaseConfig, sensors: list[SensorConfig], source: str) -> None:
    """No two IMUs on one topic, no two lidars (or a lidar and the base) on one frame."""
    topics: dict[str, str] = {base.topic: "base.topic"}
    frames: dict[str, str] = {base.frame: "base.frame"}
    for sensor in sensors:
        for value, seen, key in (
            (sensor.imu_topic, topics, "imu_topic"),
            (sensor.lidar_frame, frames, "lidar_frame"),
        ):
            path = f"sensors.{sensor.name}.{key}"
            if value in seen:
                kind = "topic" if key == "imu_topic" else "frame"
                raise ConfigError(
                    source, path, f"{kind} {value!r} is already used by {seen[value]}"
                )
            seen[value] = path


def load_config(path: str | Path) -> Config:
    """Load and validate a YAML config file; it opens no log (what a config leaves out, from a
    log's ``/tf_static`` or a URDF: :func:`imucal_cli.priors.load_config_for`).

    Raises
    ------
    ConfigError
        Naming the file and the key path of the first problem found.
    """
    return parse_config(read_config(path), str(path))


def read_config(path: str | Path) -> Any:
    """A config file's document, as loaded (a :class:`ConfigError` where it is not one)."""
    from imucal_cli.documents import load_document

    try:
        data = load_document(path)
    except InputError as exc:
        raise ConfigError(str(path), "", str(exc).removeprefix(f"{path}: ")) from None
    if data is None:
        raise ConfigError(str(path), "", "the file is empty")
    return data
