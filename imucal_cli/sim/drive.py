"""A whole simulated drive: trajectory, rig, every IMU, and the truth and config documents."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any

import numpy as np

from imucal_cli.config import CalibrationConfig, GyroBiasConfig, RestConfig, SegmentsConfig
from imucal_cli.io.writers import TopicData
from imucal_cli.sim.imu import MEMS_LIDAR, TACTICAL_BASE, ImuErrorModel, SimulatedImu, simulate_imu
from imucal_cli.sim.rig import DEFAULT_MOUNTS, LidarMount, cad_prior
from imucal_cli.sim.scenarios import SCENARIOS, VehicleDynamics, make_scenario
from imucal_cli.sim.trajectory import Trajectory
from imucal_cli.types import Transform

BASE_TOPIC = "/gnss/imu"
BASE_FRAME = "base_link"
DEFAULT_T0_NS = 1_700_000_000_000_000_000


@dataclass(frozen=True)
class DriveOptions:
    """What to simulate. ``noise_scale`` multiplies every random error (0: ideal sensors)."""

    scenario: str = "urban"
    duration_s: float | None = None  # None: the scenario's default
    seed: int = 0
    sensors: int = 2
    noise_scale: float = 1.0
    time_offsets_s: tuple[float, ...] | None = None  # per sensor; None: drawn uniformly
    max_time_offset_s: float = 0.005  # range of the drawn offsets
    base_model: ImuErrorModel = TACTICAL_BASE
    lidar_model: ImuErrorModel = MEMS_LIDAR
    lidar_rate_hz: float | None = None  # None: the model's rate
    mounts: tuple[LidarMount, ...] = field(default=DEFAULT_MOUNTS)
    dynamics: VehicleDynamics | None = None  # None: a bus/truck on its suspension
    t0_ns: int = DEFAULT_T0_NS


@dataclass(frozen=True)
class SimulatedDrive:
    options: DriveOptions
    trajectory: Trajectory
    mounts: tuple[LidarMount, ...]
    base: SimulatedImu
    sensors: dict[str, SimulatedImu]
    time_offsets_s: dict[str, float]
    priors: dict[str, Transform]

    def topics(self) -> dict[str, TopicData]:
        """The IMU topics to write, with their log (receive) times."""
        out = {BASE_TOPIC: TopicData(self.base.stream, self.base.log_time_ns)}
        for mount in self.mounts:
            imu = self.sensors[mount.name]
            out[mount.imu_topic] = TopicData(imu.stream, imu.log_time_ns)
        return out

    def truth_document(self) -> dict[str, Any]:
        """The SPEC truth file, plus ``T_base_imu``, time offsets and the true biases."""

        def biases(imu: SimulatedImu) -> dict[str, Any]:
            out = {}
            for key, values in (("gyro_bias_radps", imu.gyro_bias), ("accel_bias_mps2", imu.accel_bias)):
                out[key] = {
                    "initial": values[0].tolist(),
                    "final": values[-1].tolist(),
                    "mean": values.mean(axis=0).tolist(),
                }
            return out

        sensors: dict[str, Any] = {}
        for mount in self.mounts:
            sensors[mount.name] = {
                "imu_topic": mount.imu_topic,
                "T_base_lidar": mount.T_base_lidar.to_dict(),
                "T_base_imu": mount.T_base_imu.to_dict(),
                "T_imu_lidar": mount.T_imu_lidar.to_dict(),
                "time_offset_s": self.time_offsets_s[mount.name],
                **biases(self.sensors[mount.name]),
            }
        pairs = {
            f"{a.name}/{b.name}": (a.T_base_lidar.inverse() * b.T_base_lidar).to_dict()
            for a, b in combinations(sorted(self.mounts, key=lambda m: m.name), 2)
        }
        o = self.options
        return {
            "generator": "imucal simulate",
            "scenario": o.scenario,
            "duration_s": self.trajectory.t_end_s - self.trajectory.t_start_s,
            "seed": o.seed,
            "noise_scale": o.noise_scale,
            "t0_ns": o.t0_ns,
            "base": {"topic": BASE_TOPIC, "frame": BASE_FRAME, **biases(self.base)},
            "sensors": sensors,
            "pairs": pairs,
        }

    def config_document(self) -> dict[str, Any]:
        """A calibration config for this drive: supplier ``T_imu_lidar`` and the CAD priors."""
        from dataclasses import asdict

        sensors = {
            mount.name: {
                "imu_topic": mount.imu_topic,
                "lidar_frame": mount.lidar_frame,
                "T_imu_lidar": mount.T_imu_lidar.to_dict(),
                "prior_T_base_imu": self.priors[mount.name].to_dict(),
                "translation_bound_m": 0.3,
            }
            for mount in self.mounts
        }
        return {
            "base": {"topic": BASE_TOPIC, "frame": BASE_FRAME},
            "sensors": sensors,
            "rest": asdict(RestConfig()),
            "gyro_bias": asdict(GyroBiasConfig()),
            "segments": asdict(SegmentsConfig()),
            "calibration": asdict(CalibrationConfig()),
        }


def simulate_drive(options: DriveOptions | None = None) -> SimulatedDrive:
    """Simulate a drive. Deterministic for given options (the seed drives every random draw)."""
    o = options or DriveOptions()
    if o.scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {o.scenario!r} (expected one of: {', '.join(SCENARIOS)})")
    if not 1 <= o.sensors <= len(o.mounts):
        raise ValueError(f"sensors must be between 1 and {len(o.mounts)}, got {o.sensors}")
    if o.noise_scale < 0:
        raise ValueError("noise_scale must be >= 0")
    mounts = o.mounts[: o.sensors]
    if o.time_offsets_s is not None and len(o.time_offsets_s) not in (1, len(mounts)):
        raise ValueError(f"give 1 or {len(mounts)} time offsets, got {len(o.time_offsets_s)}")

    trajectory = make_scenario(o.scenario, o.duration_s, seed=o.seed, dynamics=o.dynamics)
    rng = np.random.default_rng([o.seed, 7919])
    base = simulate_imu(trajectory, Transform.identity(), o.base_model.scaled(o.noise_scale), rng, o.t0_ns, BASE_FRAME)

    offsets: dict[str, float] = {}
    sensors: dict[str, SimulatedImu] = {}
    priors: dict[str, Transform] = {}
    for k, mount in enumerate(mounts):
        if o.time_offsets_s is None:
            offset = float(rng.uniform(-o.max_time_offset_s, o.max_time_offset_s))
        else:
            offset = float(o.time_offsets_s[k if len(o.time_offsets_s) > 1 else 0])
        offsets[mount.name] = offset
        model = replace(o.lidar_model.scaled(o.noise_scale), time_offset_s=offset)
        if o.lidar_rate_hz is not None:
            model = replace(model, rate_hz=o.lidar_rate_hz)
        sensors[mount.name] = simulate_imu(trajectory, mount.T_base_imu, model, rng, o.t0_ns, mount.imu_frame)
        priors[mount.name] = cad_prior(mount.T_base_imu, rng)
    return SimulatedDrive(o, trajectory, mounts, base, sensors, offsets, priors)
