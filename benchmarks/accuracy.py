"""Accuracy and honesty of imucal on simulated drives with ground truth; prints markdown tables.

Every case is a scenario (the motion) with an error class (what the sensors or the mount do
beyond the estimator's model, ``imucal simulate --errors``). For every case and seed: simulate a
drive with four lidars, calibrate it, and compare each lidar's ``T_base_lidar`` with the truth
(rotation error: paper eq. 21; translation: the norm of the difference; per axis: the error
over the reported std, rotation about the base axes). Then:

- per case: statuses, errors, and the honesty figures: ``ok`` sensors with an axis beyond 4
  reported std (must be 0), the share of axes inside 3 reported std (goal: 95%), and the root
  mean square of error/std (at most 1.5; near 1 where the errors are drawn from the declared
  grades: the std neither too narrow nor needlessly wide);
- the clean scenarios against their accuracy targets, and their median std;
- the paper's figures beside ours (the lidar pair ``T_GT = T_BL1^-1 T_BL2``, eq. 20 and eq. 21);
- the tilting mount: the tilt estimated against the simulated one;
- units: detected, and the accuracy against the same drive in SI.

Run: ``python benchmarks/accuracy.py [--seeds 5] [--jobs 2] [--cases urban/none ...]``.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from imucal_cli.core.so3 import rotation_angle_deg
from imucal_cli.pipeline import run_calibrate
from imucal_cli.sim import DriveOptions, simulate_drive, with_errors

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
]
TARGETS = {  # clean scenario: (max median rotation error deg, max median |dt| m)
    "aggressive": (0.05, 0.02),
    "urban": (0.1, 0.02),
    "parking": (0.2, 0.03),
}
PAPER = {  # Das & Boberg, real drives, the lidar pair: eq. 21 (deg), eq. 20 (m)
    "aggressive": ("Seq-1 (aggressive, 81 s)", 0.4577, 0.3387),
    "urban": ("Seq-2 (urban, 283 s)", 4.7938, 0.4431),
}
STATUSES = ("ok", "partial", "inconsistent", "unobservable")


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


def run_one(scenario: str, errors: str, seed: int) -> DriveRun:
    drive = simulate_drive(
        with_errors(DriveOptions(scenario=scenario, seed=seed, sensors=4), errors)
    )
    streams, config = drive.streams(), drive.config()
    start = time.perf_counter()
    result = run_calibrate(streams, config)
    seconds = time.perf_counter() - start
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
    )


def _job(args: tuple) -> DriveRun:
    return run_one(*args)


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
    args = parser.parse_args()
    cases = [tuple(c.split("/")) for c in args.cases]
    seeds = list(range(1, args.seeds + 1))
    jobs = [(s, e, seed) for s, e in cases for seed in seeds]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(_job, jobs))
    by_case = {case: [r for r in runs if (r.scenario, r.errors) == case] for case in cases}

    print(f"## Accuracy and honesty: {len(seeds)} seeds x 4 lidars per case, T_base_lidar\n")
    print(
        "| scenario | errors | runs | "
        + "/".join(STATUSES)
        + " | median dR deg | max dR deg | median abs dt m | "
        "max abs dt m | ok beyond 4 std | axes inside 3 std | rms error/std | median std deg | "
        "median std m |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    total_ok_wrong, all_norm = 0, []
    for case in cases:
        rows = [s for d in by_case[case] for s in d.sensors]
        statuses = [r.status for r in rows]
        rot = np.array([r.rotation_error_deg for r in rows])
        trans = np.array([r.translation_error_m for r in rows])
        norm = np.array([r.normalized for r in rows if r.normalized is not None]).reshape(-1, 6)
        all_norm.append(norm)
        ok_wrong = sum(1 for r in rows if r.status == "ok" and np.any(np.abs(r.normalized) > 4))
        total_ok_wrong += ok_wrong
        inside = f"{(np.abs(norm) < 3).mean():.1%}" if norm.size else "-"
        rms = f"{np.sqrt(np.mean(norm**2)):.2f}" if norm.size else "-"
        print(
            f"| {case[0]} | {case[1]} | {len(rows)} | "
            f"{'/'.join(str(statuses.count(s)) for s in STATUSES)} | "
            f"{np.median(rot):.4f} | {rot.max():.4f} | {np.median(trans):.4f} | {trans.max():.4f} "
            f"| {ok_wrong} | {inside} | {rms} | "
            f"{_median([r.rotation_std_deg for r in rows])} | "
            f"{_median([r.translation_std_m for r in rows])} |"
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
