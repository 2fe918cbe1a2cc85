"""The shipped sample data: small, readable, consistent with its truth and config."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from conftest import ROOT, SAMPLE_DATA

from imucal_cli.config import load_config
from imucal_cli.reading import read_imu
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.types import Transform

SAMPLES = {"aggressive": 81.0, "urban": 283.0}


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_sample_log_is_small_and_complete(name):
    log = SAMPLE_DATA / f"{name}.mcap"
    assert log.stat().st_size < 5 * 1024 * 1024
    config = load_config(SAMPLE_DATA / f"{name}.config.yaml")
    assert (ROOT / "configs" / f"sample_{name}.yaml").read_text() == (
        SAMPLE_DATA / f"{name}.config.yaml"
    ).read_text()
    truth = yaml.safe_load((SAMPLE_DATA / f"{name}.truth.yaml").read_text())
    assert truth["scenario"] == name and truth["duration_s"] == SAMPLES[name]
    topics = [config.base.topic] + [s.imu_topic for s in config.sensors]
    reads = read_imu(log, topics)
    for read in reads.values():
        assert read.stream.duration_s == pytest.approx(SAMPLES[name], abs=0.05)
        assert len(read.stream) > 0.99 * 100 * SAMPLES[name]
    for sensor in config.sensors:
        T_base_imu = Transform.from_dict(truth["sensors"][sensor.name]["T_base_imu"])
        assert np.all(
            np.abs(sensor.prior_T_base_imu.translation - T_base_imu.translation)
            < sensor.translation_bound_m
        )


def test_sample_data_is_reproducible():
    """The aggressive sample is what `imucal simulate --scenario aggressive --seed 1` makes.

    The simulator computes in double precision through BLAS, whose kernel is chosen per processor
    (and by OPENBLAS_CORETYPE) and rounds differently (here up to 1e-9 m/s^2 on the base's
    specific force, against 5e-3 m/s^2 of sensor noise); its sensors then round their output to
    what they publish (the base to float32, the lidar IMUs to a fixed LSB), where such a
    difference can land a value on the next output step. So the sample agrees with the
    simulation to the resolution each sensor publishes at (one float32 step at the largest value
    of a base axis; one LSB for a lidar IMU), and its stamps, integers, exactly."""
    drive = simulate_drive(DriveOptions(scenario="aggressive", seed=1))
    options = drive.options
    config = load_config(SAMPLE_DATA / "aggressive.config.yaml")
    reads = read_imu(
        SAMPLE_DATA / "aggressive.mcap", [config.base.topic, config.sensors[0].imu_topic]
    )

    base_read, base_sim = reads[config.base.topic].stream, drive.base.stream
    assert options.base_model.float32_output
    float32_step = np.spacing(np.abs(base_sim.accel).max(axis=0).astype(np.float32)).astype(
        np.float64
    )
    assert np.all(np.abs(base_read.accel - base_sim.accel) <= float32_step)
    assert np.array_equal(base_read.t_ns, base_sim.t_ns)

    lidar_read, lidar_sim = (
        reads[config.sensors[0].imu_topic].stream,
        drive.sensors[config.sensors[0].name].stream,
    )
    lsb = options.lidar_model.gyro_lsb
    assert lsb > 0
    assert np.all(np.abs(lidar_read.gyro - lidar_sim.gyro) <= lsb * (1 + 1e-9))
    assert np.array_equal(lidar_read.t_ns, lidar_sim.t_ns)
