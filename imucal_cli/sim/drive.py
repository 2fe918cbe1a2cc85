"""A whole simulated drive: trajectory, rig, every IMU, and the truth and config documents."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any

import numpy as np

from imucal_cli.config import (
    CalibrationConfig,
    Config,
    GyroBiasConfig,
    RestConfig,
    SegmentsConfig,
    parse_config,
)
from imucal_cli.core.grades import GRADES
from imucal_cli.sim.imu import MEMS_LIDAR, TACTICAL_BASE, ImuErrorModel, ImuSampler, SimulatedImu
from imucal_cli.sim.rig import DEFAULT_MOUNTS, WHEEL_MOUNTS, LidarMount, cad_prior
from imucal_cli.sim.scenarios import SCENARIOS, VehicleDynamics, make_scenario
from imucal_cli.sim.trajectory import Trajectory
from imucal_cli.sim.writers import TopicData
from imucal_cli.types import GRAVITY_MPS2, DriveStreams, ImuStream, Transform, rotation_type

BASE_TOPIC = "/gnss/imu"
BASE_FRAME = "base_link"
#: The base IMU's own frame where the log carries /tf_static (its messages name it).
BASE_IMU_FRAME = "gnss_imu"
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
    clock_drifts_ppm: tuple[float, ...] | None = None  # per sensor (or one for all); None: 0
    #: Per sensor, the steps of its clock: (at s, by s) each (a clock re-synchronised).
    clock_steps: tuple[tuple[tuple[float, float], ...], ...] = ()
    #: Per sensor, where its mount moved (a knock): (at s, a turn about the base axes as a
    #: rotation vector (rad, 3), a shift in B (m, 3)) each; the truth is the last pose.
    knocks: tuple[tuple[tuple[float, tuple[float, ...], tuple[float, ...]], ...], ...] = ()
    base_model: ImuErrorModel = TACTICAL_BASE
    lidar_model: ImuErrorModel = MEMS_LIDAR
    lidar_rate_hz: float | None = None  # None: the model's rate
    mounts: tuple[LidarMount, ...] = field(default=DEFAULT_MOUNTS)
    dynamics: VehicleDynamics | None = None  # None: a bus/truck on its suspension
    t0_ns: int = DEFAULT_T0_NS
    #: The lidar mounts lean with the vehicle's specific force (roll per lateral, pitch per
    #: longitudinal; rad per m/s^2), like a truck cab on its own suspension.
    mount_tilt_rad_per_mps2: tuple[float, float] = (0.0, 0.0)
    #: Added to every CAD prior's translation (m): a prior further off than the search box.
    prior_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Units the base IMU's driver publishes (the lidar IMUs': ``lidar_model``).
    base_accel_units: str = "mps2"
    base_gyro_units: str = "radps"
    #: Where the base IMU sits in B (an INS is rarely at the rear-axle centre in B's axes).
    base_T_base_imu: Transform = field(default_factory=Transform.identity)
    errors: str = "none"  # the error class applied (:func:`with_errors`), for the truth file
    #: The grades (SPEC "IMU grades") each IMU's own errors are drawn from and the config
    #: declares; ``ideal``: none beyond the models' (and the error class's).
    lidar_grade: str = "ideal"
    base_grade: str = "ideal"
    #: The log carries /tf_static: Ouster-style frames per lidar (``<name>/os_sensor`` with
    #: the IMU's and the lidar's frames under it, at the CAD prior) and the base IMU's frame.
    tf_static: bool = False


#: Realistic MEMS errors of a lidar's IMU beyond noise and bias: 0.5% scale factors, 0.2 deg
#: non-orthogonality, 0.1 deg/s/g gyro g-sensitivity, a 20-60 Hz mount vibration.
MEMS_ERRORS = {
    "scale_factor_std": 0.005,
    "nonorthogonality_std_rad": np.radians(0.2),
    "g_sensitivity_std": np.radians(0.1) / GRAVITY_MPS2,
    "vibration_accel_mps2": 0.5,
    "vibration_gyro_radps": 0.01,
}

#: Error classes (``imucal simulate --errors``): what each changes in a drive's options.
#: Where the ``ins-away`` error class puts the base IMU in B.
INS_AWAY = Transform.from_rpy(np.radians([180.0, 0.0, 90.0]), np.array([1.4, 0.0, 0.75]))
ERROR_CLASSES: dict[str, dict[str, Any]] = {
    "none": {},
    "mems": {"lidar": MEMS_ERRORS},
    "misaligned": {"lidar": {"misalignment_std_rad": np.radians(0.2)}},
    "tilting-mount": {"drive": {"mount_tilt_rad_per_mps2": (np.radians(0.2), np.radians(0.2))}},
    "clock-offsets": {"drive": {"max_time_offset_s": 0.04}},
    "prior-off": {"drive": {"prior_offset_m": (0.5, 0.0, 0.0)}},
    "accel-g": {"lidar": {"accel_units": "g"}},
    "gyro-dps": {"lidar": {"gyro_units": "dps"}},
    # an INS upside down, yawed 90 deg, 1.4 m ahead and 0.75 m up (declared: base.T_base_imu)
    "ins-away": {"drive": {"base_T_base_imu": INS_AWAY}},
    # each IMU's errors drawn from the grade the config declares (SPEC "IMU grades")
    "consumer": {"drive": {"lidar_grade": "consumer", "base_grade": "tactical"}},
    "industrial": {"drive": {"lidar_grade": "industrial", "base_grade": "tactical"}},
    "tactical": {"drive": {"lidar_grade": "tactical", "base_grade": "tactical"}},
    "navigation": {"drive": {"lidar_grade": "navigation", "base_grade": "navigation"}},
    "mems-base": {
        "drive": {"lidar_grade": "consumer", "base_grade": "consumer", "base_model": MEMS_LIDAR}
    },
    # both gyros read 10% low (declared consumer and tactical: beyond either grade)
    "gyros-low": {
        "drive": {"lidar_grade": "consumer", "base_grade": "tactical"},
        "lidar": {"gyro_scale": -0.1},
        "base": {"gyro_scale": -0.1},
    },
    # clocks up to 40 ms off on 200 Hz lidar IMUs, 0.5 ms stamp jitter, 1% messages dropped
    "clock-jitter": {
        "drive": {"max_time_offset_s": 0.04, "lidar_rate_hz": 200.0},
        "lidar": {"jitter_s": 0.0005, "drop_fraction": 0.01},
    },
}


def with_errors(options: DriveOptions, error_class: str) -> DriveOptions:
    """``options`` with the error class ``error_class`` (:data:`ERROR_CLASSES`) applied."""
    if error_class not in ERROR_CLASSES:
        raise ValueError(
            f"unknown error class {error_class!r} (expected one of: {', '.join(ERROR_CLASSES)})"
        )
    change = ERROR_CLASSES[error_class]
    drive = {"base_model": options.base_model, **change.get("drive", {})}
    return replace(
        options,
        **{**drive, "base_model": replace(drive["base_model"], **change.get("base", {}))},
        lidar_model=replace(options.lidar_model, **change.get("lidar", {})),
        errors=error_class,
    )


def grade_errors(model: ImuErrorModel, grade: str) -> ImuErrorModel:
    """``model`` with its own errors drawn from ``grade``'s prior (:data:`GRADES`); the
    triads' misalignment to each other split between the two."""
    if grade == "ideal":
        return model
    g = GRADES[grade]
    return replace(
        model,
        scale_factor_std=g.scale,
        nonorthogonality_std_rad=g.nonorthogonality_rad,
        misalignment_std_rad=g.misalignment_rad / np.sqrt(2.0),
        g_sensitivity_std=g.g_sensitivity,
        housing_std_rad=g.housing_rad,
    )


class BiasTrack:
    """Each IMU's true biases over the pieces of a drive, kept as figures (first, last, sum,
    count) as the pieces go by, not as samples."""

    def __init__(self, first: SimulatedDrive, later: Iterable[SimulatedDrive] = ()) -> None:
        self.figures: dict[str, dict[str, list[Any]]] = {}
        for piece in [first, *later]:
            self.add(piece)

    def add(self, piece: SimulatedDrive) -> None:
        for name, imu in [("", piece.base), *piece.sensors.items()]:  # ("": the base)
            for key, values in (
                ("gyro_bias_radps", imu.gyro_bias),
                ("accel_bias_mps2", imu.accel_bias),
            ):
                if not len(values):
                    continue
                kept = self.figures.setdefault(name, {}).get(key)
                total, count = values.sum(axis=0), len(values)
                if kept is not None:
                    total, count = kept[2] + total, kept[3] + count
                first = values[0] if kept is None else kept[0]
                self.figures[name][key] = [first, values[-1], total, count]

    def summary(self, name: str) -> dict[str, Any]:
        """An IMU's (``""``: the base's) biases: initial, final, mean."""
        return {
            key: {"initial": first.tolist(), "final": last.tolist(), "mean": (total / n).tolist()}
            for key, (first, last, total, n) in self.figures[name].items()
        }


@dataclass(frozen=True)
class SimulatedDrive:
    options: DriveOptions
    trajectory: Trajectory
    mounts: tuple[LidarMount, ...]
    base: SimulatedImu
    sensors: dict[str, SimulatedImu]
    time_offsets_s: dict[str, float]
    priors: dict[str, Transform]
    #: Per sensor whose mount moved: its T_base_lidar before each move (the first: at the start).
    befores: dict[str, list[Transform]] = field(default_factory=dict)

    def streams(self) -> DriveStreams:
        """What the drive's log holds, as :func:`imucal_cli.api.calibrate_streams` takes it."""
        return DriveStreams(
            base=self.base.stream,
            sensors={m.name: self.sensors[m.name].stream for m in self.mounts},
            t0_ns=int(self.base.stream.t_ns[0]),
        )

    def config(self, changes: Callable[[dict[str, Any]], None] | None = None) -> Config:
        """The drive's calibration config (:meth:`config_document`), ``changes`` made to its
        document first."""
        document = self.config_document()
        if changes is not None:
            changes(document)
        return parse_config(document, "sim.config.yaml")

    def topics(self) -> dict[str, TopicData]:
        """The IMU topics to write, with their log (receive) times."""
        out = {BASE_TOPIC: TopicData(self.base.stream, self.base.log_time_ns)}
        for mount in self.mounts:
            imu = self.sensors[mount.name]
            out[mount.imu_topic] = TopicData(imu.stream, imu.log_time_ns)
        return out

    def static_transforms(self) -> list[tuple[str, str, Transform]]:
        """What the drive's /tf_static holds (``options.tf_static``; else nothing): the base
        IMU's frame in B, and per lidar an Ouster-style tree, ``<name>/os_sensor`` at the CAD
        prior with the IMU's frame and the lidar's under it (the supplier's transforms)."""
        if not self.options.tf_static:
            return []
        out = [(BASE_FRAME, BASE_IMU_FRAME, self.options.base_T_base_imu)]
        for mount in self.mounts:
            T_sensor_imu = mount.T_imu_lidar.inverse()  # the sensor frame is the lidar's
            sensor = f"{mount.name}/os_sensor"
            out += [
                (BASE_FRAME, sensor, self.priors[mount.name] * T_sensor_imu.inverse()),
                (sensor, mount.imu_frame, T_sensor_imu),
                (sensor, mount.lidar_frame, Transform.identity()),
            ]
        return out

    def urdf(self) -> str:
        """The tree of :meth:`static_transforms` as a URDF (fixed joints, ROS RPY)."""
        from imucal_cli.names import quoteattr

        transforms = self.static_transforms()
        links = dict.fromkeys(f for parent, child, _ in transforms for f in (parent, child))
        lines = ['<robot name="simulated_vehicle">']
        lines += [f"  <link name={quoteattr(link)}/>" for link in links]
        for k, (parent, child, T) in enumerate(transforms):
            xyz = " ".join(f"{v:.17g}" for v in T.translation)
            rpy = " ".join(f"{v:.17g}" for v in T.rpy_rad)
            lines += [
                f'  <joint name="joint_{k}" type="fixed">',
                f"    <parent link={quoteattr(parent)}/><child link={quoteattr(child)}/>",
                f'    <origin xyz="{xyz}" rpy="{rpy}"/>',
                "  </joint>",
            ]
        return "\n".join([*lines, "</robot>", ""])

    def _moved(self, k: int, name: str) -> list[dict[str, Any]]:
        """Sensor ``k``'s knocks in the truth: when, and its pose before."""
        knocks = sorted(self.options.knocks[k]) if k < len(self.options.knocks) else []
        befores = self.befores.get(name, [])
        return [
            {"at_s": float(at_s), "before": {"T_base_lidar": before.to_dict()}}
            for (at_s, _, _), before in zip(knocks, befores, strict=False)
        ]

    def truth_document(self, later: Sequence[SimulatedDrive] | BiasTrack = ()) -> dict[str, Any]:
        """The SPEC truth file, plus ``T_base_imu``, time offsets and the true biases (with
        ``later``, the pieces that follow this one: :func:`drive_pieces`; or their
        :class:`BiasTrack`)."""
        tracks = later if isinstance(later, BiasTrack) else BiasTrack(self, later)

        sensors: dict[str, Any] = {}
        drifts = self.options.clock_drifts_ppm or (0.0,)
        for k, mount in enumerate(self.mounts):
            sensors[mount.name] = {
                "imu_topic": mount.imu_topic,
                "T_base_lidar": mount.T_base_lidar.to_dict(),
                "T_base_imu": mount.T_base_imu.to_dict(),
                "T_imu_lidar": mount.T_imu_lidar.to_dict(),
                "time_offset_s": self.time_offsets_s[mount.name],
                "clock_drift_ppm": float(drifts[k % len(drifts)]),
                "clock_steps": [list(step) for step in self.options.clock_steps[k]]
                if k < len(self.options.clock_steps)
                else [],
                "moved": [
                    {"at_s": float(at_s), "before": {"T_base_lidar": before.to_dict()}}
                    for (at_s, _, _), before in zip(
                        sorted(self.options.knocks[k]),
                        self.befores.get(mount.name, []),
                        strict=False,
                    )
                ]
                if k < len(self.options.knocks)
                else [],
                **tracks.summary(mount.name),
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
            "errors": o.errors,
            "mount_tilt_deg_per_mps2": np.degrees(o.mount_tilt_rad_per_mps2).tolist(),
            "t0_ns": o.t0_ns,
            "base": {"topic": BASE_TOPIC, "frame": BASE_FRAME, **tracks.summary("")},
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
                "grade": self.options.lidar_grade,
                # on a wheel a steady centripetal 20-80 m/s^2 defeats the unit detection
                **({"accel_units": "mps2"} if self.options.scenario == "wheel" else {}),
            }
            for mount in self.mounts
        }
        # the grades the IMUs' errors were drawn from (ideal: exactly in their housings)
        base: dict[str, Any] = {
            "topic": BASE_TOPIC,
            "frame": BASE_FRAME,
            "grade": self.options.base_grade,
        }
        if not np.allclose(self.options.base_T_base_imu.as_matrix(), np.eye(4), atol=0.0):
            base["T_base_imu"] = self.options.base_T_base_imu.to_dict()
        return {
            "base": base,
            "sensors": sensors,
            "rest": asdict(RestConfig()),
            "gyro_bias": asdict(GyroBiasConfig()),
            "segments": asdict(SegmentsConfig()),
            "calibration": asdict(CalibrationConfig()),
        }


def simulate_drive(options: DriveOptions | None = None) -> SimulatedDrive:
    """Simulate a drive. Deterministic for given options (the seed drives every random draw).
    A drive longer than :data:`PIECE_S` is made piece by piece (:func:`drive_pieces`) and
    joined."""
    pieces = list(drive_pieces(options))
    if len(pieces) == 1:
        return pieces[0]
    first = pieces[0]

    def joined(imus: list[SimulatedImu]) -> SimulatedImu:
        def cat(get: Callable[[SimulatedImu], np.ndarray]) -> np.ndarray:
            return np.concatenate([get(i) for i in imus])

        return replace(
            imus[0],
            stream=ImuStream(
                cat(lambda i: i.stream.t_ns),
                cat(lambda i: i.stream.gyro),
                cat(lambda i: i.stream.accel),
                imus[0].stream.frame_id,
            ),
            log_time_ns=cat(lambda i: i.log_time_ns),
            true_time_s=cat(lambda i: i.true_time_s),
            gyro_bias=cat(lambda i: i.gyro_bias),
            accel_bias=cat(lambda i: i.accel_bias),
        )

    base = joined([p.base for p in pieces])
    sensors = {name: joined([p.sensors[name] for p in pieces]) for name in first.sensors}
    return replace(first, base=base, sensors=sensors)


#: The span of a drive made at once (s): a longer one is made, and written, piece by piece, in
#: memory that does not grow with its length (4 h at once: 2.5 GB).
PIECE_S = 600.0


def _checked(o: DriveOptions) -> DriveOptions:
    """The options, checked; a wheel's mounts where the vehicle's were left."""
    if o.scenario not in SCENARIOS:
        raise ValueError(
            f"unknown scenario {o.scenario!r} (expected one of: {', '.join(SCENARIOS)})"
        )
    if not 1 <= o.sensors <= len(o.mounts):
        raise ValueError(f"sensors must be between 1 and {len(o.mounts)}, got {o.sensors}")
    if o.noise_scale < 0:
        raise ValueError("noise_scale must be >= 0")
    if o.scenario == "wheel" and o.mounts == DEFAULT_MOUNTS:
        o = replace(o, mounts=WHEEL_MOUNTS)  # (a vehicle's lidars would spin off a wheel)
    n = min(o.sensors, len(o.mounts))
    if o.time_offsets_s is not None and len(o.time_offsets_s) not in (1, n):
        raise ValueError(f"give 1 or {n} time offsets, got {len(o.time_offsets_s)}")
    return o


def drive_pieces(options: DriveOptions | None = None) -> Iterator[SimulatedDrive]:
    """The drive as consecutive pieces of :data:`PIECE_S` (one piece where it is no longer):
    each a :class:`SimulatedDrive` of the same trajectory, mounts, offsets and priors, with the
    IMUs' samples of its span, their bias walks carried on. The first piece draws what
    :func:`simulate_drive` of it alone would."""
    o = _checked(options or DriveOptions())
    mounts = list(o.mounts[: o.sensors])
    befores: dict[str, list[Transform]] = {}

    trajectory = make_scenario(o.scenario, o.duration_s, seed=o.seed, dynamics=o.dynamics)
    edges = [*np.arange(trajectory.t_start_s, trajectory.t_end_s, PIECE_S)[1:].tolist()]
    spans = list(zip([trajectory.t_start_s, *edges], [*edges, trajectory.t_end_s], strict=True))
    rng = np.random.default_rng([o.seed, 7919])
    base_model = replace(
        grade_errors(o.base_model, o.base_grade).scaled(o.noise_scale),
        accel_units=o.base_accel_units,
        gyro_units=o.base_gyro_units,
    )
    base_frame = BASE_IMU_FRAME if o.tf_static else BASE_FRAME
    base = ImuSampler(trajectory, o.base_T_base_imu, base_model, rng, o.t0_ns, base_frame)
    base_piece = base.sample(*spans[0])

    offsets: dict[str, float] = {}
    samplers: dict[str, ImuSampler] = {}
    firsts: dict[str, SimulatedImu] = {}
    priors: dict[str, Transform] = {}
    for k, mount in enumerate(mounts):
        if o.time_offsets_s is None:
            offset = float(rng.uniform(-o.max_time_offset_s, o.max_time_offset_s))
        else:
            offset = float(o.time_offsets_s[k if len(o.time_offsets_s) > 1 else 0])
        offsets[mount.name] = offset
        model = _lidar_model(o, k, offset)
        moves = knocked(mount.T_base_imu, o.knocks[k] if k < len(o.knocks) else ())
        samplers[mount.name] = ImuSampler(
            trajectory,
            mount.T_base_imu,
            model,
            rng,
            o.t0_ns,
            mount.imu_frame,
            o.mount_tilt_rad_per_mps2,
            moves,
        )
        firsts[mount.name] = samplers[mount.name].sample(*spans[0])
        prior = cad_prior(mount.T_base_imu, rng)
        if moves:  # the truth: the pose it has now
            befores[mount.name] = [mount.T_base_lidar, *(p * mount.T_imu_lidar for _, p in moves)]
            mounts[k] = replace(mount, T_base_lidar=moves[-1][1] * mount.T_imu_lidar)
        priors[mount.name] = Transform(
            prior.rotation, prior.translation + np.asarray(o.prior_offset_m)
        )
    final = tuple(mounts)
    yield SimulatedDrive(o, trajectory, final, base_piece, firsts, offsets, priors, befores)
    for span in spans[1:]:
        piece = {name: sampler.sample(*span) for name, sampler in samplers.items()}
        base_span = base.sample(*span)
        yield SimulatedDrive(o, trajectory, final, base_span, piece, offsets, priors, befores)


def _lidar_model(o: DriveOptions, k: int, offset: float) -> ImuErrorModel:
    """Lidar ``k``'s IMU: the options' model and grade, its clock's offset, drift and steps."""
    drift = 0.0 if not o.clock_drifts_ppm else o.clock_drifts_ppm[k % len(o.clock_drifts_ppm)]
    model = replace(
        grade_errors(o.lidar_model, o.lidar_grade).scaled(o.noise_scale),
        time_offset_s=offset,
        clock_drift_ppm=drift,
        clock_steps=o.clock_steps[k] if k < len(o.clock_steps) else (),
    )
    return model if o.lidar_rate_hz is None else replace(model, rate_hz=o.lidar_rate_hz)


def knocked(
    T_base_imu: Transform, knocks: tuple[tuple[float, tuple[float, ...], tuple[float, ...]], ...]
) -> tuple[tuple[float, Transform], ...]:
    """The poses an IMU's mount has from each knock on: each turns it about the base axes by
    a rotation vector and shifts it, from the pose before."""
    poses, pose = [], T_base_imu
    for at_s, turn, shift in sorted(knocks):
        rotation = rotation_type().from_rotvec(np.asarray(turn, dtype=float)) * pose.rotation
        pose = Transform(rotation, pose.translation + np.asarray(shift, dtype=float))
        poses.append((float(at_s), pose))
    return tuple(poses)
