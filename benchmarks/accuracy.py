"""Accuracy and honesty of imucal on simulated drives with ground truth; prints markdown tables.

Every case is a scenario (the motion) with an error class (what the sensors or the mount do
beyond the estimator's model, ``imucal simulate --errors``) or a mistake (:data:`MISTAKES`).
For every case and seed: simulate a drive with four lidars (the wheel: its two IMUs),
calibrate it, and compare each lidar's ``T_base_lidar`` with the truth
(rotation error: paper eq. 21; translation: the norm of the difference; per axis: the error
over the reported std, rotation about the base axes). Then:

- per case: statuses, errors, and the honesty figures: ``ok`` sensors with an axis beyond 4
  reported std (must be 0), the share of axes inside 3 reported std (goal: 95%), and the root
  mean square of error/std (at most 1.5; near 1 where the errors are drawn from the declared
  grades: the std neither too narrow nor needlessly wide);
- the clean scenarios against their accuracy targets, and their median std;
- the paper's figures beside ours (the lidar pair ``T_GT = T_BL1^-1 T_BL2``, eq. 20 and eq. 21);
- the tilting mount: the tilt estimated against the simulated one;
- units: detected, and the accuracy against the same drive in SI;
- every case read from each log container (MCAP, ROS 1, rosbag2 sqlite3 and mcap): the same
  windows and estimates from each (``--containers`` names fewer; ``memory``: no log at all);
- the everyday mistakes (:data:`MISTAKES`): a config or a log that puts the IMU's frame wrong,
  never ``ok``.

Run: ``python benchmarks/accuracy.py [--seeds 5] [--jobs 2] [--cases urban/none ...]
[--containers mcap rosbag1 ...]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from imucal_cli.api import calibrate, calibrate_streams
from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.documents import write_document
from imucal_cli.errors import ImucalError
from imucal_cli.sim import DriveOptions, simulate_drive, with_errors
from imucal_cli.sim.drive import ERROR_CLASSES, SimulatedDrive
from imucal_cli.sim.writers import TopicData, write_imu_log
from imucal_cli.types import Transform

#: (scenario, error class): the clean drives of the first round, then every new error class.
CASES = [
    ("aggressive", "none"),
    ("urban", "none"),
    ("parking", "none"),
    ("highway", "none"),
    ("aggressive", "mems"),
    ("urban", "mems"),
    ("urban", "misaligned"),
    ("urban", "tilting-mount"),
    ("highway", "clock-offsets"),
    ("urban", "prior-off"),
    ("urban", "accel-g"),
    ("urban", "gyro-dps"),
    ("aggressive", "ins-away"),
    ("aggressive", "clock-jitter"),
    ("urban", "consumer"),
    ("aggressive", "consumer"),
    ("urban", "industrial"),
    ("urban", "tactical"),
    ("urban", "navigation"),
    ("aggressive", "mems-base"),
    ("aggressive", "gyros-low"),
    ("urban", "yaw-missing"),
    ("urban", "frame-is-lidar"),
    ("urban", "tiny-quaternion"),
    ("wheel", "none"),
]
#: The log containers every case is read from (the first gives the accuracy rows); ``memory``
#: calibrates the simulated streams without writing a log.
CONTAINERS = ("mcap", "rosbag1", "rosbag2-sqlite3", "rosbag2-mcap")
TARGETS = {  # clean scenario: (max median rotation error deg, max median |dt| m)
    "aggressive": (0.05, 0.02),
    "urban": (0.1, 0.02),
    "parking": (0.2, 0.03),
}
PAPER = {  # Das & Boberg, real drives, the lidar pair: eq. 21 (deg), eq. 20 (m)
    "aggressive": ("Seq-1 (aggressive, 81 s)", 0.4577, 0.3387),
    "urban": ("Seq-2 (urban, 283 s)", 4.7938, 0.4431),
}
STATUSES = ("ok", "partial", "inconsistent", "unobservable", "refused")


# ------------------------------------------------------------------ everyday mistakes (issue 48)


def _yaw_missing(drive: SimulatedDrive) -> tuple[dict[str, Any], dict[str, TopicData], list]:
    """A config whose ``T_imu_lidar`` lacks the Ouster's 180 deg yaw, its prior made from the
    CAD lidar pose through it: the prior 180 deg about the IMU's z from the truth, and the
    lidar 180 deg from where the IMU's pose puts it."""
    config = drive.config_document()
    turn = Transform(Rotation.from_euler("z", 180.0, degrees=True), np.zeros(3))
    for sensor in config["sensors"].values():
        T_imu_lidar = Transform.from_dict(sensor["T_imu_lidar"])
        cad_lidar = Transform.from_dict(sensor["prior_T_base_imu"]) * T_imu_lidar
        wrong = T_imu_lidar * turn.inverse()
        sensor["T_imu_lidar"] = wrong.to_dict()
        sensor["prior_T_base_imu"] = (cad_lidar * wrong.inverse()).to_dict()
    return config, drive.topics(), []


def _minimal(drive: SimulatedDrive) -> dict[str, Any]:
    """The config naming topics and frames only: the transforms come from /tf_static."""
    full = drive.config_document()
    return {
        "base": {k: full["base"][k] for k in ("topic", "frame", "grade")},
        "sensors": {
            name: {k: s[k] for k in ("imu_topic", "lidar_frame", "grade")}
            for name, s in full["sensors"].items()
        },
    }


def _frame_is_lidar(drive: SimulatedDrive) -> tuple[dict[str, Any], dict[str, TopicData], list]:
    """A Livox-style driver: the IMU's messages name the lidar's frame, so /tf_static gives
    ``T_imu_lidar = I`` (the Ouster's is 180 deg about z) and the prior is the lidar's pose."""
    topics = drive.topics()
    for mount in drive.mounts:
        data = topics[mount.imu_topic]
        stream = replace(data.stream, frame_id=mount.lidar_frame)
        topics[mount.imu_topic] = TopicData(stream, data.log_time_ns)
    return _minimal(drive), topics, drive.static_transforms()


class _RawTransform:
    """A /tf_static transform with any quaternion (what a log's author may write)."""

    def __init__(self, T: Transform, quaternion_xyzw: list[float]) -> None:
        self.translation, self.quaternion_xyzw = T.translation, np.asarray(quaternion_xyzw)


def _tiny_quaternion(drive: SimulatedDrive) -> tuple[dict[str, Any], dict[str, TopicData], list]:
    """/tf_static holding each IMU frame's rotation as (1e-8, 0, 0, 0): normalised, a 180 deg
    roll."""
    tree = [
        (parent, child, _RawTransform(T, [1e-8, 0.0, 0.0, 0.0]) if child.endswith("_imu") else T)
        for parent, child, T in drive.static_transforms()
    ]
    return _minimal(drive), drive.topics(), tree


#: Mistakes (the case's "errors"): the config, the topics and /tf_static a drive is read with.
MISTAKES: dict[str, Callable[[SimulatedDrive], tuple[dict[str, Any], dict[str, TopicData], list]]]
MISTAKES = {
    "yaw-missing": _yaw_missing,
    "frame-is-lidar": _frame_is_lidar,
    "tiny-quaternion": _tiny_quaternion,
}


@dataclass
class SensorRun:
    status: str
    rotation_error_deg: float
    translation_error_m: float
    normalized: np.ndarray | None  # (6,) error / std per axis (rotation about base axes, xyz)
    rotation_std_deg: float | None  # largest axis
    translation_std_m: float | None
    warnings: list[str]
    tilt_deg_per_mps2: list[float] | None
    true_tilt_deg_per_mps2: list[float]
    offset_error_ms: float = float("nan")  # the clock offset found less the simulated one
    statistical_t: np.ndarray | None = None  # (3,) lever-arm error / statistical std


@dataclass
class DriveRun:
    scenario: str
    errors: str
    seed: int
    sensors: list[SensorRun]
    pair_rotation_deg: float
    pair_eq20_m: float
    seconds: float
    same_in_containers: bool = True  # the same windows and estimates from every container


def _read(
    drive: SimulatedDrive, errors: str, container: str, folder: Path
) -> tuple[Any, float, str | None]:
    """The drive calibrated as read from ``container`` (``memory``: its streams): the result,
    the seconds the calibration took, and why it was refused (an input error), else None."""
    config, topics, tree = (
        MISTAKES[errors](drive)
        if errors in MISTAKES
        else (drive.config_document(), drive.topics(), [])
    )
    start = time.perf_counter()
    if container == "memory" and not tree:
        from imucal_cli.config import parse_config

        result = calibrate_streams(drive.streams(), parse_config(config, "sim.config.yaml"))
        return result, time.perf_counter() - start, None
    fmt = "mcap" if container == "memory" else container  # (a tree needs a log)
    log = write_imu_log(folder / f"drive-{container}", fmt, topics, tf_static=tree)
    write_document(folder / "config.yaml", config)
    start = time.perf_counter()
    try:
        result = calibrate(log, folder / "config.yaml")
    except ImucalError as exc:
        return None, time.perf_counter() - start, str(exc)
    return result, time.perf_counter() - start, None


def _same(a: Any, b: Any) -> bool:
    """Whether two results hold the same windows, statuses and estimates."""
    if a is None or b is None:
        return a is b
    return all(
        a.estimates[n].status == b.estimates[n].status
        and [w.selected for w in a.estimates[n].windows]
        == [w.selected for w in b.estimates[n].windows]
        and np.allclose(a.T_base_lidar(n).as_matrix(), b.T_base_lidar(n).as_matrix(), atol=1e-9)
        for n in a.estimates
    )


def run_one(
    scenario: str, errors: str, seed: int, containers: tuple[str, ...] = CONTAINERS
) -> DriveRun:
    options = DriveOptions(scenario=scenario, seed=seed, sensors=2 if scenario == "wheel" else 4)
    if errors in ERROR_CLASSES:
        options = with_errors(options, errors)
    elif errors in MISTAKES:
        options = replace(options, tf_static=True)
    drive = simulate_drive(options)
    with tempfile.TemporaryDirectory() as folder:
        reads = [_read(drive, errors, c, Path(folder)) for c in containers]
    result, seconds, refused = reads[0]
    same = all(_same(result, other) for other, _, _ in reads[1:])
    if result is None:
        return DriveRun(
            scenario,
            errors,
            seed,
            [_refused(refused)] * len(drive.mounts),
            float("nan"),
            float("nan"),
            seconds,
            same,
        )
    sensors = []
    estimates = {}
    true_tilt = np.degrees(drive.options.mount_tilt_rad_per_mps2).tolist()
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        T = result.T_base_lidar(mount.name)
        estimates[mount.name] = T
        rotation_error = (mount.T_base_lidar.rotation * T.rotation.inv()).as_rotvec()
        translation_error = T.translation - mount.T_base_lidar.translation
        cov = estimate.lidar_covariance(mount.T_imu_lidar)
        normalized = std_r = std_t = None
        if cov is not None:
            std = np.sqrt(np.diag(cov))
            normalized = np.concatenate([rotation_error, translation_error]) / std
            std_r, std_t = float(np.degrees(std[:3]).max()), float(std[3:].max())
        rigid = getattr(estimate, "checks", {}).get("rigid_mount", {})
        statistical_t = None
        if estimate.statistical_covariance is not None:
            lever_arm = estimate.T_base_imu.translation - mount.T_base_imu.translation
            statistical_t = lever_arm / np.sqrt(np.diag(estimate.statistical_covariance)[3:])
        sensors.append(
            SensorRun(
                estimate.status,
                rotation_angle_deg(T.rotation, mount.T_base_lidar.rotation),
                float(np.linalg.norm(translation_error)),
                normalized,
                std_r,
                std_t,
                list(getattr(estimate, "warnings", [])),
                rigid.get("tilt_deg_per_mps2"),
                true_tilt,
                1e3 * (estimate.time_offset_s - drive.time_offsets_s[mount.name]),
                statistical_t,
            )
        )
    a, b = drive.mounts[0], drive.mounts[1]
    pair_est = estimates[a.name].inverse() * estimates[b.name]
    pair_true = a.T_base_lidar.inverse() * b.T_base_lidar
    return DriveRun(
        scenario,
        errors,
        seed,
        sensors,
        rotation_angle_deg(pair_est.rotation, pair_true.rotation),
        float(np.linalg.norm(pair_est.translation - pair_true.translation)) / 3.0,
        seconds,
        same,
    )


def _refused(why: str | None) -> SensorRun:
    """A sensor of a drive the tool refused to calibrate (exit 2): no estimate."""
    return SensorRun("refused", float("nan"), float("nan"), None, None, None, [why or ""], None, [])


def _job(args: tuple) -> DriveRun:
    return run_one(*args)


def _ok_wrong(row: SensorRun) -> bool:
    """An ``ok`` wrong by more than 4 std on any axis."""
    return row.status == "ok" and np.any(np.abs(row.normalized) > 4)


def _median(values: list[float | None]) -> str:
    kept = [v for v in values if v is not None]
    return f"{np.median(kept):.4f}" if kept else "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--cases", nargs="+", default=[f"{s}/{e}" for s, e in CASES], help="scenario/errors"
    )
    parser.add_argument(
        "--containers",
        nargs="+",
        default=list(CONTAINERS),
        help="log containers to read each drive from (memory: none)",
    )
    args = parser.parse_args()
    cases = [tuple(c.split("/")) for c in args.cases]
    seeds = list(range(1, args.seeds + 1))
    jobs = [(s, e, seed, tuple(args.containers)) for s, e in cases for seed in seeds]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(_job, jobs))
    by_case = {case: [r for r in runs if (r.scenario, r.errors) == case] for case in cases}

    print(f"## Accuracy and honesty: {len(seeds)} seeds x 4 lidars per case, T_base_lidar\n")
    print(f"Each drive read from: {', '.join(args.containers)}.\n")
    print(
        "| scenario | errors | runs | "
        + "/".join(STATUSES)
        + " | median dR deg | max dR deg | median abs dt m | "
        "max abs dt m | ok beyond 4 std | axes inside 3 std | rms error/std | median std deg | "
        "median std m | same in every container |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    total_ok_wrong, all_norm = 0, []
    for case in cases:
        rows = [s for d in by_case[case] for s in d.sensors]
        statuses = [r.status for r in rows]
        rot = np.array([r.rotation_error_deg for r in rows])
        trans = np.array([r.translation_error_m for r in rows])
        norm = np.array([r.normalized for r in rows if r.normalized is not None]).reshape(-1, 6)
        if case[1] not in MISTAKES:  # (wrong on purpose: their figure is never ok)
            all_norm.append(norm)
        ok_wrong = sum(map(_ok_wrong, rows))
        if case[1] in MISTAKES:  # a frame put wrong: never ok, whatever its std
            ok_wrong = statuses.count("ok")
        total_ok_wrong += ok_wrong
        inside = f"{(np.abs(norm) < 3).mean():.1%}" if norm.size else "-"
        rms = f"{np.sqrt(np.mean(norm**2)):.2f}" if norm.size else "-"
        same = sum(d.same_in_containers for d in by_case[case])
        figures = (
            [f"{f(v):.4f}" for v in (rot, trans) for f in (np.nanmedian, np.nanmax)]
            if np.isfinite(rot).any()
            else ["-"] * 4
        )
        print(
            f"| {case[0]} | {case[1]} | {len(rows)} | "
            f"{'/'.join(str(statuses.count(s)) for s in STATUSES)} | "
            f"{figures[0]} | {figures[1]} | {figures[2]} | {figures[3]} | {ok_wrong} | {inside} | "
            f"{rms} | "
            f"{_median([r.rotation_std_deg for r in rows])} | "
            f"{_median([r.translation_std_m for r in rows])} | {same}/{len(by_case[case])} |"
        )
    norm = np.concatenate(all_norm)
    n_runs = sum(len(d.sensors) for d in runs)
    print(
        f"\n**All cases: {n_runs} sensor runs; `ok` with an axis beyond 4 std: {total_ok_wrong} "
        "(must be 0); "
        f"axes inside 3 std: {(np.abs(norm) < 3).mean():.1%} of {norm.size} (goal >= 95%); "
        f"inside 1 std: {(np.abs(norm) < 1).mean():.1%} (Gaussian: 68%).**\n"
    )

    print("## Clean scenarios against their targets (median over sensors and seeds)\n")
    print("| scenario | median dR deg | median abs dt m | target | met | share ok |")
    print("|---|---|---|---|---|---|")
    for scenario, (target_rot, target_trans) in TARGETS.items():
        if (scenario, "none") not in by_case:
            continue
        rows = [s for d in by_case[(scenario, "none")] for s in d.sensors]
        rot = np.median([r.rotation_error_deg for r in rows])
        trans = np.median([r.translation_error_m for r in rows])
        met = "yes" if rot <= target_rot and trans <= target_trans else "NO"
        ok = sum(r.status == "ok" for r in rows) / len(rows)
        print(
            f"| {scenario} | {rot:.4f} | {trans:.4f} | <= {target_rot} deg, <= "
            f"{target_trans * 100:g} cm | {met} | {ok:.0%} |"
        )

    print("\n## Against the paper (lidar pair T_GT = T_BL1^-1 T_BL2; paper: real drives)\n")
    print(
        "| drive | paper dR deg (eq. 21) | paper dt m (eq. 20) | imucal median dR deg | imucal "
        "median dt m (eq. 20) |"
    )
    print("|---|---|---|---|---|")
    for scenario, (name, paper_rot, paper_trans) in PAPER.items():
        drive_runs = by_case.get((scenario, "none"))
        if drive_runs:
            rot = float(np.median([d.pair_rotation_deg for d in drive_runs]))
            trans = float(np.median([d.pair_eq20_m for d in drive_runs]))
            print(f"| {name} | {paper_rot} | {paper_trans} | {rot:.4f} | {trans:.5f} |")

    tilting = [
        s for (sc, e), d in by_case.items() if e == "tilting-mount" for r in d for s in r.sensors
    ]
    if tilting:
        print("\n## Tilting mount: estimated tilt against the simulated one (deg per m/s^2)\n")
        print(
            "| runs | not ok | simulated roll, pitch | median estimate roll, pitch | max relative "
            "error | within 30% |"
        )
        print("|---|---|---|---|---|---|")
        truth = np.array(tilting[0].true_tilt_deg_per_mps2)
        est = np.array(
            [
                r.tilt_deg_per_mps2 if r.tilt_deg_per_mps2 is not None else [np.nan, np.nan]
                for r in tilting
            ]
        )
        rel = np.abs(est - truth) / np.abs(truth)
        print(
            f"| {len(tilting)} | {sum(r.status != 'ok' for r in tilting)} | "
            f"{truth.round(3).tolist()} | "
            f"{np.nanmedian(est, axis=0).round(3).tolist()} | {np.nanmax(rel):.1%} | "
            f"{int(np.sum(np.all(rel <= 0.3, axis=1)))}/{len(tilting)} |"
        )

    units = [c for c in cases if c[1] in ("accel-g", "gyro-dps") and (c[0], "none") in by_case]
    if units:
        print("\n## Units: detected and calibrated as well as the SI twin (same seeds)\n")
        print(
            "| case | runs | warned of the units | median dR deg (SI twin) | median abs dt m (SI "
            "twin) | statuses equal |"
        )
        print("|---|---|---|---|---|---|")
        for case in units:
            rows = [s for d in by_case[case] for s in d.sensors]
            twin = [s for d in by_case[(case[0], "none")] for s in d.sensors]
            warned = sum(any("publishes" in w for w in r.warnings) for r in rows)
            same = sum(a.status == b.status for a, b in zip(rows, twin, strict=True))
            print(
                f"| {case[0]}/{case[1]} | {len(rows)} | {warned} | "
                f"{np.median([r.rotation_error_deg for r in rows]):.4f} "
                f"({np.median([r.rotation_error_deg for r in twin]):.4f}) | "
                f"{np.median([r.translation_error_m for r in rows]):.4f} "
                f"({np.median([r.translation_error_m for r in twin]):.4f}) | {same}/{len(rows)} |"
            )
    clocks = [c for c in cases if c[1] in ("clock-offsets", "clock-jitter")]
    if clocks:
        print("\n## Clock offsets: found, and the lever arm against its statistical std\n")
        print(
            "| case | runs | largest offset error ms | median offset error ms | lever-arm axes "
            "within 3 statistical std |"
        )
        print("|---|---|---|---|---|")
        for case in clocks:
            rows = [s for d in by_case[case] for s in d.sensors]
            offsets = np.abs([r.offset_error_ms for r in rows])
            lever = np.abs([r.statistical_t for r in rows if r.statistical_t is not None])
            print(
                f"| {case[0]}/{case[1]} | {len(rows)} | {offsets.max():.3f} | "
                f"{np.median(offsets):.3f} | {(lever <= 3).mean():.1%} of {lever.size} |"
            )
    print(
        f"\n({len(jobs)} drives in {time.perf_counter() - started:.0f} s with {args.jobs} "
        "processes.)"
    )


if __name__ == "__main__":
    main()
