"""Config loading: defaults, and an error naming file and key for every kind of mistake."""

from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.config import Config, load_config, parse_config
from imucal_cli.errors import ConfigError
from imucal_cli.types import Transform

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "configs" / "default.yaml"


@pytest.fixture()
def base_dict() -> dict:
    return yaml.safe_load(DEFAULT.read_text())


def test_default_config_loads_with_documented_values():
    config = load_config(DEFAULT)
    assert isinstance(config, Config)
    assert [s.name for s in config.sensors] == ["front_left_top", "front_right_top"]
    right = config.sensor("front_right_top")
    assert right.lidar_frame == "front_right_top_lidar"  # the default "<name>_lidar"
    assert right.translation_bound_m == 0.3
    left = config.sensor("front_left_top")
    # rpy_deg [0, 0, 180] and rotation [0, 0, 1, 0] are the same rotation
    assert (left.T_imu_lidar.rotation.inv() * right.T_imu_lidar.rotation).magnitude() < 1e-12
    assert config.calibration.max_time_offset_s == 0.1


def test_optional_sections_take_defaults(base_dict):
    for key in ("rest", "gyro_bias", "segments", "calibration"):
        del base_dict[key]
    del base_dict["base"]["frame"]
    config = parse_config(base_dict, "x.yaml")
    assert config.base.frame == "base_link"
    assert config.segments.window_s == 10.0 and config.rest.min_duration_s == 2.0


def test_to_dict_round_trips(base_dict):
    config = parse_config(base_dict, "x.yaml")
    again = parse_config(config.to_dict(), "y.yaml")
    for a, b in zip(again.sensors, config.sensors, strict=True):
        assert (a.name, a.imu_topic, a.lidar_frame, a.translation_bound_m) == (
            b.name,
            b.imu_topic,
            b.lidar_frame,
            b.translation_bound_m,
        )
        for ta, tb in ((a.T_imu_lidar, b.T_imu_lidar), (a.prior_T_base_imu, b.prior_T_base_imu)):
            np.testing.assert_allclose(ta.as_matrix(), tb.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(
        again.base.T_base_imu.as_matrix(), config.base.T_base_imu.as_matrix(), atol=1e-12
    )
    identity = Transform.identity()
    assert replace(again.base, T_base_imu=identity) == replace(config.base, T_base_imu=identity)
    assert (again.rest, again.gyro_bias, again.segments, again.calibration) == (
        config.rest,
        config.gyro_bias,
        config.segments,
        config.calibration,
    )


def _mutate(data: dict, path: str, value) -> dict:
    data = copy.deepcopy(data)
    keys = path.split(".")
    target = data
    for key in keys[:-1]:
        target = target[key]
    if value is _DELETE:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return data


_DELETE = object()

CASES = [
    ("base.topik", "/x", "base.topik", "unknown key"),
    ("colibration", {}, "colibration", "unknown key"),
    (
        "sensors.front_left_top.imu_topic",
        5,
        "sensors.front_left_top.imu_topic",
        "expected a non-empty string",
    ),
    ("sensors.front_left_top.imu_topic", _DELETE, "sensors.front_left_top.imu_topic", "missing"),
    (
        "sensors.front_left_top.T_imu_lidar.rotation",
        [0, 0, 0.5, 0.5],
        "sensors.front_left_top.T_imu_lidar.rotation",
        "norm",
    ),
    (
        "sensors.front_left_top.T_imu_lidar.rotation",
        [0, 0, 1, 0.001],
        "sensors.front_left_top.T_imu_lidar.rpy_deg",
        "disagrees",
    ),
    (
        "sensors.front_left_top.prior_T_base_imu",
        _DELETE,
        "sensors.front_left_top.prior_T_base_imu",
        "missing",
    ),
    (
        "sensors.front_left_top.translation_bound_m",
        0,
        "sensors.front_left_top.translation_bound_m",
        "> 0",
    ),
    (
        "sensors.front_left_top.translation_bound_m",
        -0.1,
        "sensors.front_left_top.translation_bound_m",
        "> 0",
    ),
    (
        "sensors.front_left_top.translation_bound_m",
        "0.3",
        "sensors.front_left_top.translation_bound_m",
        "expected a number",
    ),
    (
        "sensors.front_left_top.translation_bound_m",
        True,
        "sensors.front_left_top.translation_bound_m",
        "expected a number",
    ),
    (
        "sensors.front_right_top.imu_topic",
        "/gnss/imu",
        "sensors.front_right_top.imu_topic",
        "already used",
    ),
    (
        "sensors.front_right_top.lidar_frame",
        "front_left_top_lidar",
        "sensors.front_right_top.lidar_frame",
        "already used",
    ),
    ("rest.min_duration_s", float("inf"), "rest.min_duration_s", "finite"),
    ("segments.window_s", 0.0, "segments.window_s", "> 0"),
    ("segments", [1, 2], "segments", "expected a mapping"),
    ("calibration.max_time_offset_s", -1.0, "calibration.max_time_offset_s", ">= 0"),
    ("sensors", {}, "sensors", "at least one"),
    ("base", _DELETE, "base", "missing"),
]


@pytest.mark.parametrize(
    ("path", "value", "key", "problem"), CASES, ids=[c[2] + ":" + c[3] for c in CASES]
)
def test_errors_name_file_and_key(base_dict, path, value, key, problem):
    with pytest.raises(ConfigError) as info:
        parse_config(_mutate(base_dict, path, value), "vehicle.yaml")
    message = str(info.value)
    assert message.startswith(f"vehicle.yaml: {key}:"), message
    assert problem in message


def test_zero_time_offset_is_allowed(base_dict):
    config = parse_config(_mutate(base_dict, "calibration.max_time_offset_s", 0), "x.yaml")
    assert config.calibration.max_time_offset_s == 0.0


def test_duplicate_yaml_keys_are_rejected(tmp_path):
    text = DEFAULT.read_text().replace("  front_right_top:\n", "  front_left_top:\n")
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value) and "duplicate key 'front_left_top'" in str(info.value)


runner = CliRunner()


def test_cli_config_error_exit_2_one_line_no_traceback(tmp_path, base_dict):
    path = tmp_path / "bad.yaml"
    bad = _mutate(base_dict, "sensors.front_left_top.T_imu_lidar.rotation", [0, 0, 0.5, 0.5])
    path.write_text(yaml.safe_dump(bad))
    result = runner.invoke(app, ["check-config", str(path)])
    assert result.exit_code == 2
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr
    assert str(path) in lines[0] and "sensors.front_left_top.T_imu_lidar.rotation" in lines[0]


@pytest.mark.parametrize("content", ["", "base: [\n", "- 1\n- 2\n"])
def test_cli_unreadable_config_exit_2(tmp_path, content):
    path = tmp_path / "broken.yaml"
    path.write_text(content)
    result = runner.invoke(app, ["check-config", str(path)])
    assert result.exit_code == 2 and str(path) in result.stderr and "Traceback" not in result.stderr


def test_cli_missing_config_exit_2(tmp_path):
    result = runner.invoke(app, ["check-config", str(tmp_path / "none.yaml")])
    assert result.exit_code == 2 and "none.yaml" in result.stderr


def test_cli_check_config_prints_defaults_filled_in(base_dict, tmp_path):
    del base_dict["rest"]
    path = tmp_path / "ok.yaml"
    path.write_text(yaml.safe_dump(base_dict))
    result = runner.invoke(app, ["check-config", str(path), "--json"])
    assert result.exit_code == 0
    import json

    assert json.loads(result.stdout)["rest"]["min_duration_s"] == 2.0


def test_a_key_left_empty_takes_its_default(base_dict):
    """``key:`` with no value (YAML null) is the key's default, as if it were left out: the
    lidar frame's (which is named after the sensor) as well as a number's."""
    name = next(iter(base_dict["sensors"]))
    base_dict["sensors"][name]["lidar_frame"] = None
    base_dict["sensors"][name]["translation_bound_m"] = None
    sensor = parse_config(base_dict, "x.yaml").sensor(name)
    assert sensor.lidar_frame == f"{name}_lidar" and sensor.translation_bound_m == 0.3


def test_check_config_prints_no_negative_zero():
    """An angle that is zero is printed 0.0, not -0.0 (issue 32, item 9)."""
    from conftest import SAMPLE_DATA
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    result = CliRunner().invoke(app, ["check-config", str(SAMPLE_DATA / "aggressive.config.yaml")])
    assert (
        result.exit_code == 0
        and "rpy_deg: [0.0, 0.0, 180.0]" in result.stdout
        and "-0.0," not in result.stdout
    )


def test_grades_default_to_a_consumer_lidar_imu_and_a_tactical_ins(base_dict):
    """SPEC grades: the housing alignment a grade carries joins the rotation floor of both
    IMUs (consumer 0.5 deg, tactical 0.05 deg); ``ideal`` adds none."""
    from imucal_cli.core.grades import GRADES
    from imucal_cli.pipeline import options_for

    config = parse_config(base_dict, "x.yaml")
    assert config.base.grade == "tactical" and all(s.grade == "consumer" for s in config.sensors)
    floor = options_for(config, config.sensors[0]).rotation_floor_deg
    assert floor == pytest.approx(0.5, rel=1e-12)  # the base's 0.05 deg: with its lever arm
    assert GRADES["ideal"].housing_rad == 0.0
    options = options_for(config, config.sensors[0])
    assert (options.sensor_grade, options.base_grade) == ("consumer", "tactical")
    with pytest.raises(ConfigError, match="grade"):
        parse_config(_mutate(base_dict, "base.grade", "excellent"), "x.yaml")


def test_a_sensor_named_base_is_refused_not_confused_with_the_base_imu(base_dict):
    """``base`` is the base IMU's name beside the sensors' (the biases document's
    ``imus.base``): a lidar named so came back unobservable ("every window has a gap") and
    another inconsistent with 1,040 deg of std, exit 0. Now the config says so."""
    sensors = base_dict["sensors"]
    sensors["base"] = sensors.pop("front_left_top")
    with pytest.raises(ConfigError) as info:
        parse_config(base_dict, "vehicle.yaml")
    assert str(info.value).startswith("vehicle.yaml: sensors.base: 'base' names the base IMU")


@pytest.mark.parametrize(
    "value", ["2001-13-45", "1" * 5000, "0x" + "f" * 300], ids=["date", "int", "hex"]
)
def test_yaml_scalars_python_cannot_hold_are_an_error_naming_the_file(base_dict, tmp_path, value):
    """PyYAML builds a date of month 13, a 5,000-digit int or a 300-digit hex and Python
    refuses it (or its float): a traceback escaped, in configs and truth files alike."""
    path = tmp_path / "vehicle.yaml"
    text = yaml.safe_dump(base_dict).replace("min_duration_s: 2.0", f"min_duration_s: {value}")
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(str(path))
    assert "no number or date" in str(caught.value) or "rest.min_duration_s" in str(caught.value)
    result = CliRunner().invoke(app, ["evaluate", str(path), str(path)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert result.stderr.count("\n") == 1 and "vehicle.yaml" in result.stderr
