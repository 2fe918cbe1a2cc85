"""The base IMU where it is (``base.T_base_imu``): an INS away from B's origin and turned."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import lidar_error

from imucal_cli.api import calibrate_streams
from imucal_cli.config import parse_config
from imucal_cli.errors import ConfigError
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.types import Transform

#: An INS upside down and yawed 90 deg, 1.4 m ahead of the rear axle and 0.75 m up (issue 30).
INS = Transform.from_rpy(np.radians([180.0, 0.0, 90.0]), np.array([1.4, 0.0, 0.75]))


def _errors(drive, result):
    """Per sensor: rotation error about base axes (rad), translation error (m), and the std."""
    out = {}
    for mount in drive.mounts:
        error, std = lidar_error(drive, result, mount.name)
        out[mount.name] = (error[:3], error[3:], std)
    return out


def test_a_noise_free_drive_with_the_ins_turned_and_away_comes_back_exactly():
    options = DriveOptions(
        scenario="aggressive",
        duration_s=81.0,
        seed=2,
        noise_scale=0.0,
        time_offsets_s=(0.0,),
        sensors=4,
        base_T_base_imu=INS,
    )
    drive = simulate_drive(options)
    config = drive.config()
    assert np.allclose(config.base.T_base_imu.as_matrix(), INS.as_matrix())
    result = calibrate_streams(drive.streams(), config)
    for name, (rotation, translation, _) in _errors(drive, result).items():
        assert result.estimates[name].status == "ok", name
        assert np.degrees(np.linalg.norm(rotation)) < 1e-3, name
        assert np.linalg.norm(translation) < 1e-3, name


@pytest.mark.parametrize("seed", [3, 4])
def test_the_ins_away_from_the_origin_calibrates_as_well_as_its_twin_at_the_origin(seed):
    """Same drive and noise, the base IMU at the origin or where ``INS`` puts it: both within
    4 std on every axis, the std within 20% of each other (the issue's bound)."""
    results = {}
    for pose in (Transform.identity(), INS):
        drive = simulate_drive(
            DriveOptions(scenario="aggressive", seed=seed, sensors=4, base_T_base_imu=pose)
        )
        results[pose is INS] = _errors(drive, calibrate_streams(drive.streams(), drive.config()))
    for name, (rotation, translation, std) in results[True].items():
        assert np.all(np.abs(rotation) < 4 * std[:3]), (name, rotation / std[:3])
        assert np.all(np.abs(translation) < 4 * std[3:]), (name, translation / std[3:])
        twin_std = results[False][name][2]
        np.testing.assert_allclose(std, twin_std, rtol=0.2, err_msg=name)


def test_the_config_takes_the_base_pose_and_bounds_it():
    document = simulate_drive(DriveOptions(duration_s=30.0)).config_document()
    assert np.array_equal(parse_config(document).base.T_base_imu.as_matrix(), np.eye(4))
    document["base"]["T_base_imu"] = {"translation": [1.4, 0.0, 0.75], "rpy_deg": [180, 0, 90]}
    parsed = parse_config(document, "c.yaml").base.T_base_imu
    np.testing.assert_allclose(parsed.as_matrix(), INS.as_matrix(), atol=1e-12)
    document["base"]["T_base_imu"] = {"translation": [140.0, 0.0, 0.0], "rpy_deg": [0, 0, 0]}
    with pytest.raises(ConfigError, match=r"base\.T_base_imu\.translation"):
        parse_config(document, "c.yaml")


def test_an_ins_upside_down_that_the_config_does_not_declare_is_not_called_ok():
    """Its gravity points down B's z: every sensor `inconsistent`, the check saying why (a yaw
    alone would not show: nothing in the data tells B's heading from the INS's)."""
    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=81.0, seed=6, base_T_base_imu=INS)
    )
    config = drive.config(lambda document: document["base"].pop("T_base_imu"))
    assert np.array_equal(config.base.T_base_imu.as_matrix(), np.eye(4))
    result = calibrate_streams(drive.streams(), config)
    for name, estimate in result.estimates.items():
        assert estimate.status == "inconsistent", name
        assert estimate.checks["base_gravity"]["pass"] is False
        assert estimate.checks["base_gravity"]["angle_deg"] > 170.0
        assert any("base.T_base_imu" in w for w in estimate.warnings), estimate.warnings
