"""The shipped sample data: small, readable, consistent with its truth and config."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from conftest import ROOT, SAMPLE_DATA

from imucal_cli.config import load_config
from imucal_cli.io.logs import read_imu
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.types import Transform

SAMPLES = {"aggressive": 81.0, "urban": 283.0}


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_sample_log_is_small_and_complete(name):
    log = SAMPLE_DATA / f"{name}.mcap"
    assert log.stat().st_size < 5 * 1024 * 1024
    config = load_config(SAMPLE_DATA / f"{name}.config.yaml")
    assert (ROOT / "configs" / f"sample_{name}.yaml").read_text() == (SAMPLE_DATA / f"{name}.config.yaml").read_text()
    truth = yaml.safe_load((SAMPLE_DATA / f"{name}.truth.yaml").read_text())
    assert truth["scenario"] == name and truth["duration_s"] == SAMPLES[name]
    topics = [config.base.topic] + [s.imu_topic for s in config.sensors]
    reads = read_imu(log, topics)
    for read in reads.values():
        assert read.stream.duration_s == pytest.approx(SAMPLES[name], abs=0.05)
        assert len(read.stream) > 0.99 * 100 * SAMPLES[name]
    for sensor in config.sensors:
        T_base_imu = Transform.from_dict(truth["sensors"][sensor.name]["T_base_imu"])
        assert np.all(np.abs(sensor.prior_T_base_imu.translation - T_base_imu.translation) < sensor.translation_bound_m)


def test_sample_data_is_reproducible():
    """The aggressive sample is exactly what `imucal simulate --scenario aggressive --seed 1` makes."""
    drive = simulate_drive(DriveOptions(scenario="aggressive", seed=1))
    config = load_config(SAMPLE_DATA / "aggressive.config.yaml")
    reads = read_imu(SAMPLE_DATA / "aggressive.mcap", [config.base.topic, config.sensors[0].imu_topic])
    assert np.array_equal(reads[config.base.topic].stream.accel, drive.base.stream.accel)
    simulated = drive.sensors[config.sensors[0].name].stream
    assert np.array_equal(reads[config.sensors[0].imu_topic].stream.gyro, simulated.gyro)
    assert np.array_equal(reads[config.sensors[0].imu_topic].stream.t_ns, simulated.t_ns)
