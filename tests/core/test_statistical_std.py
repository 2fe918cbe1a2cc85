"""Two stds (SPEC): the total users gate on, and the statistical one more driving shrinks."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.api import calibrate_streams
from imucal_cli.config import parse_config
from imucal_cli.core.status import missing_axes
from imucal_cli.outputs import calibration_document
from imucal_cli.sim import DriveOptions, simulate_drive

FLOOR_DEG, FLOOR_M = 0.05, 0.01


@pytest.fixture(scope="module")
def floored():
    """An aggressive drive calibrated with systematic floors on every sensor."""
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=81.0, seed=12))
    document = drive.config_document()
    for sensor in document["sensors"].values():
        sensor["rotation_floor_deg"], sensor["translation_floor_m"] = FLOOR_DEG, FLOOR_M
    config = parse_config(document, "floored.yaml")
    return drive, config, calibrate_streams(drive.streams(), config)


def test_the_total_is_the_statistical_std_and_the_floors_the_drive_cannot_see(floored):
    _, _, result = floored
    for name, estimate in result.estimates.items():
        assert estimate.status == "ok", (name, estimate.warnings)
        statistical = np.diag(estimate.statistical_covariance)
        total = np.diag(estimate.covariance)
        floors = np.array([np.radians(FLOOR_DEG)] * 3 + [FLOOR_M] * 3) ** 2
        np.testing.assert_allclose(total, statistical + floors, rtol=1e-12)
        assert np.all(estimate.statistical_rotation_std_deg < estimate.rotation_std_deg)


def test_the_document_gives_the_statistical_std(floored):
    _, _, result = floored
    document = calibration_document(result, "drive.mcap")
    for name, s in document["sensors"].items():
        estimate = result.estimates[name]
        statistical = s["statistical_std"]
        np.testing.assert_allclose(
            statistical["rotation_deg"], estimate.statistical_rotation_std_deg
        )
        np.testing.assert_allclose(
            statistical["translation_m"], estimate.statistical_translation_std_m
        )
        assert all(
            a < b for a, b in zip(statistical["rotation_deg"], s["rotation_std_deg"], strict=True)
        )


def test_stop_targets_are_met_by_the_statistical_std_not_the_floors(floored):
    """A target below the floor but above the statistical std is met: more driving cannot
    shrink a floor, so ``--until-converged`` would otherwise wait for ever."""
    _, config, result = floored
    estimate = next(iter(result.estimates.values()))
    target_r = float(np.max(estimate.statistical_rotation_std_deg)) * 1.01
    target_t = float(np.max(estimate.statistical_translation_std_m)) * 1.01
    assert target_r < FLOOR_DEG and target_t < FLOOR_M
    stop = config.stop.__class__(max_rotation_std_deg=target_r, max_translation_std_m=target_t)
    assert missing_axes(estimate, stop) == []
