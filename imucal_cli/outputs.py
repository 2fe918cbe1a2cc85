"""The SPEC's output documents (``inspect``, ``biases``, ``segments``, ``calibrate``,
``evaluate``), built from a run's results as plain dicts; :mod:`imucal_cli.documents` writes
them."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from itertools import combinations
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from imucal_cli.core.grades import GRADES
from imucal_cli.core.segments import WindowInfo, window_counts
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.core.status import move_sentence
from imucal_cli.documents import to_plain
from imucal_cli.frames import config_sources
from imucal_cli.version import version

if TYPE_CHECKING:
    from imucal_cli.config import Config
    from imucal_cli.core.biases import BiasReport
    from imucal_cli.inspection import LogSummary
    from imucal_cli.io.base import Loss
    from imucal_cli.types import Transform


class Calibration(Protocol):
    """What the documents take of a :class:`imucal_cli.calibration.Calibration`."""

    @property
    def config(self) -> Config: ...
    @property
    def estimates(self) -> dict[str, Any]: ...
    @property
    def windows(self) -> Mapping[str, Sequence[Any]]: ...
    @property
    def t0_ns(self) -> int: ...
    @property
    def t_ref_ns(self) -> int: ...
    @property
    def time_offsets_s(self) -> Mapping[str, float]: ...
    @property
    def rates_hz(self) -> Mapping[str, float]: ...
    @property
    def noise_density(self) -> Mapping[str, tuple[float, float]]: ...

    def T_base_lidar(self, name: str) -> Transform: ...
    def missing(self, name: str) -> list[str]: ...


def inspect_document(summary: LogSummary) -> dict[str, Any]:
    """``losses`` as calibrate's: only what was lost (a note on how the log was read, such as
    a summary-less MCAP read record by record, is said on stderr, not listed as a loss)."""
    document: dict[str, Any] = {
        "log": summary.path,
        "format": summary.format_name,
        "t0_ns": summary.t0_ns,
        "topics": {
            t.topic: {
                "type": t.msgtype,
                "count": t.count,
                "rate_hz": round(t.rate_hz, 6),
                "duration_s": round(t.duration_s, 6),
                "gaps": [[round(a, 6), round(b, 6)] for a, b in t.gaps],
                "backwards": t.backwards,
                "duplicates": t.duplicates,
                "time_source": t.time_source,
            }
            for t in summary.topics
        },
    }
    if losses := losses_document(summary.losses):
        document["losses"] = losses
    return document


def biases_document(
    config: Config,
    reports: Mapping[str, BiasReport],
    losses: Sequence[Loss] = (),
    counts: Mapping[str, Mapping[str, int]] | None = None,
) -> dict[str, Any]:
    """The SPEC's biases document; ``losses`` and ``counts`` (per topic, what reading counted)
    as calibrate's take them, each IMU's reading warnings among its own."""
    counts = counts or {}
    t0_ns = min(r.first_ns for r in reports.values())
    topics = {"base": config.base.topic} | {s.name: s.imu_topic for s in config.sensors}
    imus: dict[str, Any] = {}
    for name, report in reports.items():
        offset = (report.first_ns - t0_ns) * 1e-9
        imus[name] = {
            "topic": topics[name],
            "rest_periods": [[offset + r.start_s, offset + r.end_s] for r in report.rest_periods],
            # at one rest pose only the bias along gravity separates from the tilt: this vector
            # is that component (the full one, relative to the base, is calibrate's)
            "accel_bias_mps2": report.accel_bias,
            "accel_bias_along_gravity_mps2": report.rest_periods[-1].accel_bias_along_gravity
            if report.rest_periods
            else None,
            "accel_bias_resolved": (
                "along gravity only (the full vector: imucal calibrate, accel_bias_mps2)"
            ),
            "accel_noise_std_mps2": report.accel_noise_std,
            "gyro_bias_radps": {
                "initial": report.gyro_bias_initial,
                "final": report.gyro_bias_final,
                "track_std": report.gyro_bias_track_std,
                "final_std": report.gyro_bias_final_std,
            },
            "warnings": [
                *report.warnings,
                *read_warnings(topics[name], counts.get(topics[name], {})),
            ],
        }
    return to_plain(
        {
            "imucal_version": version(),
            "t0_ns": t0_ns,
            "imus": imus,
            "lost_s": lost_seconds(losses),
            "losses": losses_document(losses),
            "dropped": dropped_document(counts),
        }
    )


#: Windows made into a document's rows at a time, as ``segments`` writes them.
ROWS_CHUNK = 1000


def segments_document(calibration: Calibration, streamed: bool = False) -> dict[str, Any]:
    """The SPEC's segments document; ``streamed``: each sensor's windows a
    :class:`~imucal_cli.documents.Rows` made as it is written (a day's windows are never a
    document in memory)."""
    from imucal_cli.documents import Rows

    config = calibration.config
    offset = (calibration.t_ref_ns - calibration.t0_ns) * 1e-9
    sensors: dict[str, Any] = {}
    for sensor in config.sensors:
        windows = calibration.windows[sensor.name]
        used, total = window_counts(windows)

        def chunks(windows: Sequence[WindowInfo] = windows) -> Iterator[list[dict[str, Any]]]:
            for a in range(0, len(windows), ROWS_CHUNK):
                end = min(a + ROWS_CHUNK, len(windows))
                yield [_window_row(offset, windows[k]) for k in range(a, end)]

        sensors[sensor.name] = {
            "total": total,
            "selected": used,
            "time_offset_s": calibration.time_offsets_s.get(sensor.name, 0.0),
            "windows": Rows(len(windows), chunks) if streamed else list(Rows(len(windows), chunks)),
        }
    return to_plain(
        {
            "imucal_version": version(),
            "t0_ns": calibration.t0_ns,
            "window_s": config.segments.window_s,
            "max_rotation_std_deg": config.segments.max_rotation_std_deg,
            "sensors": sensors,
        }
    )


def _window_row(offset: float, w: WindowInfo) -> dict[str, Any]:
    return to_plain(
        {
            "start_s": offset + w.start_s,
            "end_s": offset + w.end_s,
            "min_singular_value": w.min_singular_value,
            "rotation_std_deg": w.rotation_std_deg if np.isfinite(w.rotation_std_deg) else None,
            "selected": w.selected,
            "translation_observable": w.translation_observable,
            "translation_std_m": [v if np.isfinite(v) else None for v in w.translation_std_m],
            **({} if w.valid else {"gap": True}),
        }
    )


def _std_list(values: np.ndarray | None) -> list[float] | None:
    return None if values is None else [float(v) for v in values]


def _rate(result: Calibration, name: str) -> float | None:
    rate = result.rates_hz.get(name)
    return None if rate is None else round(float(rate), 6)


def lost_seconds(losses: Sequence[Loss]) -> float | None:
    """Seconds of log time the read lost: 0 without a loss, None where a loss's span is not
    known (a log cut off mid-write: its end is not recorded anywhere)."""
    spans = [(x.start_ns, x.end_ns) for x in losses if x.lost]
    if any(a is None or b is None for a, b in spans):
        return None
    return float(sum((b - a) * 1e-9 for a, b in spans if a is not None and b is not None))


def losses_document(losses: Sequence[Loss]) -> list[dict[str, Any]]:
    return [
        {
            "reason": x.describe(),
            "offset": x.offset,
            "bytes": x.nbytes,
            "start_ns": x.start_ns,
            "end_ns": x.end_ns,
            "messages": x.messages,
        }
        for x in losses
        if x.lost
    ]


#: Smallest random walk written (Kalibr refuses zero): 1e-9 per sqrt(s).
MIN_RANDOM_WALK = 1e-9


def _base_source(config: Config) -> str:
    """Where ``base.T_base_imu`` came from (SPEC ``priors``): config, tf_static, urdf."""
    sources = {p.get("base.T_base_imu", "config") for p in config.priors.values()}
    return sources.pop() if len(sources) == 1 else "config"


def imu_noise(result: Calibration, name: str) -> dict[str, float | None]:
    """An IMU's noise in Kalibr's terms: white-noise densities measured above the motion, and
    the gyro and accelerometer bias random walks measured from the knots of the relative biases
    the fit estimated (sensor minus base, a knot a window or a merged stretch's ends, each step
    over its own time: for each IMU an upper bound, and the sensor's own); the base's walks are
    its grade's (:data:`GRADES`), or for ``ideal`` the smallest of its sensors' (the tightest
    upper bound the log gives)."""
    gyro, accel = result.noise_density.get(name, (None, None))
    walks: dict[str, list[float]] = {"gyro": [], "accel": []}
    for sensor, est in result.estimates.items():
        if name != "base" and sensor != name:
            continue
        gaps_s = np.diff(est.bias_knots_s)[:, None]
        for key, knots in (("gyro", est.gyro_bias_knots), ("accel", est.accel_bias_knots)):
            if len(knots) > 2:
                walks[key].append(float(np.sqrt(np.mean(np.diff(knots, axis=0) ** 2 / gaps_s))))
    walk_g, walk_a = (min(w) if w else None for w in (walks["gyro"], walks["accel"]))
    grade_walks = GRADES[result.config.base.grade].random_walks
    if name == "base" and grade_walks is not None:  # (the drive measures the sensors' alone)
        walk_g, walk_a = grade_walks
    return {
        "gyroscope_noise_density": gyro,
        "accelerometer_noise_density": accel,
        "gyroscope_random_walk": None if walk_g is None else max(walk_g, MIN_RANDOM_WALK),
        "accelerometer_random_walk": None if walk_a is None else max(walk_a, MIN_RANDOM_WALK),
    }


#: What reading drops from a topic (:class:`~imucal_cli.reading.ReadStats`), and how a warning says
#: it.
DROPPED = {
    "decode_errors": "not decodable",
    "non_finite": "not finite",
    "implausible": "beyond any IMU's range",
    "saturated": "clipped at the sensor's range",
    "stamp_outliers": "with a damaged stamp",
    "duplicates": "with a duplicate stamp",
}


def dropped_document(counts: Mapping[str, Mapping[str, int]]) -> dict[str, dict[str, int]]:
    """Per topic that dropped any, the samples reading dropped, by reason."""
    out = {
        topic: {k: int(c.get(k, 0)) for k in DROPPED if c.get(k, 0)} for topic, c in counts.items()
    }
    return {topic: d for topic, d in out.items() if d}


def read_warnings(topic: str, counts: Mapping[str, int]) -> list[str]:
    """What reading dropped from ``topic`` or found wrong with its clock, as warnings."""
    dropped = {k: int(counts.get(k, 0)) for k in DROPPED if counts.get(k, 0)}
    out = []
    if dropped:
        total, messages = sum(dropped.values()), max(int(counts.get("messages", 0)), 1)
        out.append(
            f"{topic}: {total:,} of {messages:,} messages dropped ({100 * total / messages:.1f}%: "
            + ", ".join(f"{n:,} {DROPPED[k]}" for k, n in dropped.items())
            + "); windows with a gap there are not used"
        )
    if counts.get("clock_jumps"):
        out.append(
            f"{topic}: its stamps jump by a minute or more {counts['clock_jumps']} times; the "
            "windows across a jump are not used"
        )
    return out


def calibration_document(
    result: Calibration,
    log: str,
    losses: Sequence[Loss] = (),
    counts: Mapping[str, Mapping[str, int]] | None = None,
) -> dict[str, Any]:
    """The SPEC's calibrate document; ``losses`` (what reading the log could not read) go in
    as ``losses`` and ``lost_s`` (None: a span not known), undecodable messages counted in
    ``lost_s`` at their topic's rate; ``counts`` (per topic, what reading counted) as
    ``dropped`` and as each sensor's warnings (the base's in every sensor's)."""
    config = result.config
    counts = counts or {}
    lost_s = lost_seconds(losses)
    for topic, name in [
        (config.base.topic, "base"),
        *((s.imu_topic, s.name) for s in config.sensors),
    ]:
        undecodable, rate = counts.get(topic, {}).get("decode_errors", 0), _rate(result, name)
        if undecodable and lost_s is not None:
            lost_s = None if rate is None else lost_s + undecodable / rate
    names = sorted(s.name for s in config.sensors)
    pairs = {
        f"{a}/{b}": (result.T_base_lidar(a).inverse() * result.T_base_lidar(b)).to_dict()
        for a, b in combinations(names, 2)
    }
    return to_plain(
        {  # plain types: yaml.safe_dump and json.dumps take it as it is
            "imucal_version": version(),
            "log": log,
            "base_frame": config.base.frame,
            "base_topic": config.base.topic,
            "base_imu_rate_hz": _rate(result, "base"),
            "base_imu_noise": imu_noise(result, "base"),
            "base": {
                "topic": config.base.topic,
                "T_base_imu": config.base.T_base_imu.to_dict(),
                "grade": config.base.grade,
                "source": _base_source(config),
            },
            "sensors": {s.name: _sensor_document(result, s, counts) for s in config.sensors},
            "pairs": pairs,
            "lost_s": lost_s,
            "losses": losses_document(losses),
            "dropped": dropped_document(counts),
        }
    )


MOVE_KEYS = ("at_s", "at_std_s", "rotation_deg", "translation_m")


def follow_line(result: Calibration, windows: int) -> dict[str, Any]:
    """A line of ``calibrate --follow --json`` after ``windows`` windows: per sensor its
    status, ``T_base_lidar``, the statistical std ``stop:`` tests, the total std, the windows
    used and the axes still missing."""
    sensors = {}
    for name, e in result.estimates.items():
        T = result.T_base_lidar(name)
        sensors[name] = {
            "status": e.status,
            "T_base_lidar": {"translation": T.translation, "rpy_deg": np.degrees(T.rpy_rad)},
            "statistical_std": _statistical_std(e),
            "rotation_std_deg": _std_list(e.rotation_std_deg),
            "translation_std_m": _std_list(e.translation_std_m),
            "windows": "{}/{}".format(*window_counts(e.windows)),
            "missing": result.missing(name),
        }
    return {"windows": windows, "sensors": sensors}


def _moved(result: Calibration, sensor: Any) -> list[dict[str, Any]]:
    """Where the sensor's mount moved (SPEC ``moved``): when (s since t0), how far its lidar
    turned and shifted, and its pose before."""
    T_imu_lidar = sensor.T_imu_lidar
    offset = (result.t_ref_ns - result.t0_ns) * 1e-9
    out = []
    for move in result.estimates[sensor.name].moves:
        before = move.T_base_imu_before * T_imu_lidar
        after = move.T_base_imu_after * T_imu_lidar
        out.append(
            {
                "at_s": move.at_s + offset,
                "at_std_s": move.at_std_s,
                "rotation_deg": rotation_angle_deg(before.rotation, after.rotation),
                "translation_m": float(np.linalg.norm(after.translation - before.translation)),
                "before": {
                    "T_base_lidar": before.to_dict(),
                    "rotation_std_deg": [float(v) for v in move.rotation_std_deg],
                    "translation_std_m": [float(v) for v in move.translation_std_m],
                },
            }
        )
    return out


def _timeline(result: Calibration, sensor: Any) -> list[dict[str, Any]]:
    """The sensor estimated alone per epoch (SPEC ``timeline``): the span of the epoch's windows
    (s since t0), the lidar's pose (``T_base_lidar``) with its std, and the clock offset over
    the epoch."""
    offset = (result.t_ref_ns - result.t0_ns) * 1e-9
    out = []
    for epoch in result.estimates[sensor.name].timeline:
        lidar = epoch.T_base_imu * sensor.T_imu_lidar
        pose = lidar.to_dict()
        out.append(
            {
                "start_s": epoch.start_s + offset,
                "end_s": epoch.end_s + offset,
                "windows": epoch.windows,
                "rpy_deg": pose["rpy_deg"],
                "translation": pose["translation"],
                "rotation_std_deg": [float(v) for v in epoch.rotation_std_deg],
                "translation_std_m": [float(v) for v in epoch.translation_std_m],
                "time_offset_s": epoch.time_offset_s,
            }
        )
    return out


def _sensor_document(
    result: Calibration, sensor: Any, counts: Mapping[str, Mapping[str, int]]
) -> dict[str, Any]:
    """One sensor's part of the calibrate document."""
    config, est = result.config, result.estimates[sensor.name]
    base_warnings = [
        f"base: {w}" for w in read_warnings(config.base.topic, counts.get(config.base.topic, {}))
    ]
    moved = _moved(result, sensor)
    return {
        "status": est.status,
        "warnings": [  # what reading dropped first: it is the cause of what the fit says
            *base_warnings,
            *read_warnings(sensor.imu_topic, counts.get(sensor.imu_topic, {})),
            *(move_sentence(*(m[k] for k in MOVE_KEYS)) for m in moved),
            *est.warnings,
        ],
        "notes": list(est.notes),
        "imu_topic": sensor.imu_topic,
        "lidar_frame": sensor.lidar_frame,
        # where each transform came from (SPEC): config (or its default), tf_static
        "priors": dict(config.priors.get(sensor.name) or config_sources()),
        "imu_rate_hz": _rate(result, sensor.name),
        "imu_noise": imu_noise(result, sensor.name),
        "T_base_imu": est.T_base_imu.to_dict(),
        "T_base_lidar": result.T_base_lidar(sensor.name).to_dict(),
        "rotation_std_deg": _std_list(est.rotation_std_deg),
        "translation_std_m": _std_list(est.translation_std_m),
        "statistical_std": _statistical_std(est),
        "covariance": _covariance(est.covariance),
        "translation_observable": [bool(v) for v in est.translation_observable],
        # at t0 (the grid's origin is t_ref): the drift carries the offset there
        "time_offset_s": est.time_offset_s
        + (est.clock_drift or 0.0) * (result.t0_ns - result.t_ref_ns) * 1e-9,
        "time_offset_std_s": est.time_offset_std_s,
        "time_offset_observable": bool(est.time_offset_observable),
        "clock_drift_ppm": None if est.clock_drift is None else 1e6 * est.clock_drift,
        "clock_drift_std_ppm": None if est.clock_drift_std is None else 1e6 * est.clock_drift_std,
        "moved": moved,
        "timeline": _timeline(result, sensor),
        "checks": to_plain(est.checks),
        "accel_intrinsics": to_plain(est.accel_intrinsics) if est.accel_intrinsics else None,
        "gyro_intrinsics": to_plain(est.gyro_intrinsics) if est.gyro_intrinsics else None,
        "gyro_bias_radps": est.gyro_bias,
        "accel_bias_mps2": est.accel_bias,
        "segments": dict(zip(("selected", "total"), window_counts(est.windows), strict=True)),
        "residual_rms": {"gyro_radps": est.residual_rms_gyro, "accel_mps2": est.residual_rms_accel},
    }


def _statistical_std(est: Any) -> dict[str, list[float] | None] | None:
    """The std of what more driving shrinks (``stop:`` tests it), or None without a fit."""
    if est.statistical_covariance is None:
        return None
    return {
        "rotation_deg": _std_list(est.statistical_rotation_std_deg),
        "translation_m": _std_list(est.statistical_translation_std_m),
    }


def _covariance(cov: np.ndarray | None) -> dict[str, Any] | None:
    if cov is None:
        return None
    return {
        "of": "T_base_imu",
        "order": ["rx", "ry", "rz", "tx", "ty", "tz"],
        "rotation_axes": "base",
        "units": ["rad", "rad", "rad", "m", "m", "m"],
        "matrix": [[float(v) for v in row] for row in cov],
    }


def transform_errors(estimate: Transform, truth: Transform) -> dict[str, Any]:
    """Rotation error (paper eq. 21), translation error norm and eq. 20 (norm / 3)."""
    delta = estimate.translation - truth.translation
    norm = float(np.linalg.norm(delta))
    return {
        "rotation_error_deg": rotation_angle_deg(estimate.rotation, truth.rotation),
        "translation_error_m": norm,
        "translation_error_eq20_m": norm / 3.0,
        "translation_error_xyz_m": [float(v) for v in delta],
    }


#: Each threshold of ``evaluate`` and the error it bounds (the clock offset's by its size).
THRESHOLDS = (
    ("max_rotation_deg", "rotation_error_deg"),
    ("max_translation_m", "translation_error_m"),
    ("max_time_offset_s", "time_offset_error_s"),
)


def over_thresholds(row: Mapping[str, Any], limits: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The (threshold, error) pairs of an evaluate row whose error exceeds its threshold."""
    return [
        (limit, error)
        for limit, error in THRESHOLDS
        if limits.get(limit) is not None
        and row.get(error) is not None
        and abs(row[error]) > limits[limit]
    ]


def evaluate_document(
    estimates: Mapping[str, Transform],
    truths: Mapping[str, Transform],
    max_rotation_deg: float | None,
    max_translation_m: float | None,
    allow_missing: bool = False,
    offsets: tuple[Mapping[str, float], Mapping[str, float]] = ({}, {}),
    max_time_offset_s: float | None = None,
) -> dict[str, Any]:
    """Every sensor present in both, and every pair ``T_a_b = T_base_a^-1 T_base_b``. A sensor
    in one file and not the other fails the evaluation unless ``allow_missing``. ``offsets``:
    each side's clock offsets (s), compared where both have the sensor's."""
    names = sorted(set(estimates) & set(truths))
    missing = {
        "estimate_only": sorted(set(estimates) - set(truths)),
        "truth_only": sorted(set(truths) - set(estimates)),
    }
    sensors = {}
    for n in names:
        both = n in offsets[0] and n in offsets[1]
        sensors[n] = transform_errors(estimates[n], truths[n]) | {
            "time_offset_error_s": offsets[0][n] - offsets[1][n] if both else None
        }
    pairs = {}
    for a, b in combinations(names, 2):
        errors = transform_errors(
            estimates[a].inverse() * estimates[b], truths[a].inverse() * truths[b]
        )
        del errors["translation_error_xyz_m"]
        pairs[f"{a}/{b}"] = errors
    thresholds = {
        "max_rotation_deg": max_rotation_deg,
        "max_translation_m": max_translation_m,
        "max_time_offset_s": max_time_offset_s,
    }
    rows = list(sensors.values()) + list(pairs.values())
    passed = bool(names) and (
        allow_missing or not (missing["estimate_only"] or missing["truth_only"])
    )
    passed &= not any(over_thresholds(row, thresholds) for row in rows)
    return to_plain(
        {
            "sensors": sensors,
            "pairs": pairs,
            "thresholds": thresholds,
            "missing": missing,
            "pass": passed,
        }
    )
