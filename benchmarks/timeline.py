"""Calibration through time on simulated drives with ground truth; prints markdown tables.

Clocks that drift: every lidar IMU's clock drifts from the base's by a rate drawn from +-5 to
+-150 ppm (either sign) with an offset at the start drawn within +-50 ms, on urban, aggressive
and highway drives of four lidars, several seeds; in every other drive one lidar's clock also
steps (re-synchronised) by +-5 to +-30 ms at a random time between 30% and 80% of the drive.
In two drives of three, one or two lidars' mounts are knocked once or twice (0.3-3 deg,
5-30 mm, at random times). Per scenario:

- statuses; ``ok`` sensors with an axis of ``T_base_lidar`` beyond 4 reported std (must be 0);
  the share of axes inside 3 std (goal: at least 95%);
- the drift: how many sensors report one, how many of those lie within 3 of their std, the
  largest error over std; the offset at t0 likewise;
- the knocks: found (the time within two windows), their sizes (the turn's angle and the
  lidar's shift) within 3 std of the poses either side, and moves said where there was none;
- the steps: found (within two windows of the truth, the size within 3 std), missed, and
  steps said where there was none;
- the timeline (epochs of 60 s): each epoch wholly between knocks against the pose then, every
  axis over the epoch's std;
- the same drives with the drift not estimated (``max_clock_drift_ppm: 0``): what a single
  offset makes of them.

Run: ``python benchmarks/timeline.py [--seeds 5] [--jobs 2] [--scenarios urban ...]``;
``--figure docs/report_timeline.png`` draws docs/timeline.md's figure instead.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from imucal_cli.api import calibrate_streams
from imucal_cli.sim import DriveOptions, simulate_drive

SCENARIOS = ("urban", "aggressive", "highway")
DRIFT_PPM = (5.0, 150.0)
OFFSET_S = 0.05
#: The timeline's epoch in these drives (the default, 300 s, is longer than most of them).
EPOCH_S = 60.0


STEP_S = (0.005, 0.030)
#: How close (s) a step's time must be to the truth's: two windows.
STEP_TIME_S = 20.0


def drifts(seed: int) -> tuple[float, ...]:
    """Four drifts (ppm), each of a random sign and size."""
    rng = np.random.default_rng(1000 + seed)
    return tuple(float(v) for v in rng.choice([-1, 1], 4) * rng.uniform(*DRIFT_PPM, 4))


def steps(seed: int, duration_s: float) -> tuple[tuple[tuple[float, float], ...], ...]:
    """In every other drive, one lidar's clock steps once."""
    rng = np.random.default_rng(2000 + seed)
    out: list[tuple[tuple[float, float], ...]] = [(), (), (), ()]
    if seed % 2:
        size = float(rng.choice([-1, 1]) * rng.uniform(*STEP_S))
        out[int(rng.integers(4))] = ((float(rng.uniform(0.3, 0.8) * duration_s), size),)
    return tuple(out)


KNOCK_DEG = (0.3, 3.0)
KNOCK_M = (0.005, 0.030)


def knocks(seed: int, duration_s: float) -> tuple[tuple[Any, ...], ...]:
    """In two drives of three, one or two lidars' mounts knocked once or twice each (a turn
    of 0.3-3 deg about a random axis, a shift of 5-30 mm in a random direction) at random
    times between 15% and 85% of the drive, at least 30 s apart."""
    rng = np.random.default_rng(3000 + seed)
    out: list[tuple[Any, ...]] = [(), (), (), ()]
    if seed % 3 == 0:
        return tuple(out)
    for sensor in rng.choice(4, int(rng.integers(1, 3)), replace=False):
        times: list[float] = []
        while len(times) < int(rng.integers(1, 3)):
            at = float(rng.uniform(0.15, 0.85) * duration_s)
            if all(abs(at - t) >= 30.0 for t in times):
                times.append(at)
        out[int(sensor)] = tuple(
            (
                at,
                tuple(np.radians(rng.uniform(*KNOCK_DEG)) * _unit(rng)),
                tuple(rng.uniform(*KNOCK_M) * _unit(rng)),
            )
            for at in sorted(times)
        )
    return tuple(out)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def run_case(args: tuple[str, int, bool]) -> list[dict[str, Any]]:
    """One drive calibrated: a row per lidar."""
    from imucal_cli.sim.scenarios import SCENARIOS as DURATIONS

    scenario, seed, follow = args
    options = DriveOptions(
        scenario=scenario,
        seed=seed,
        sensors=4,
        max_time_offset_s=OFFSET_S,
        clock_drifts_ppm=drifts(seed),
        clock_steps=steps(seed, DURATIONS[scenario]),
        knocks=knocks(seed, DURATIONS[scenario]),
    )
    drive = simulate_drive(options)

    def no_drift(document: dict[str, Any]) -> None:
        document["calibration"]["max_clock_drift_ppm"] = 0

    def epochs(document: dict[str, Any]) -> None:
        document["calibration"]["epoch_s"] = EPOCH_S

    cal = calibrate_streams(drive.streams(), drive.config(epochs if follow else no_drift))
    truth = drive.truth_document()["sensors"]
    rows = []
    for name, s in cal.document()["sensors"].items():
        mount = next(m for m in drive.mounts if m.name == name)
        T = cal.T_base_lidar(name)
        rotation = (mount.T_base_lidar.rotation * T.rotation.inv()).as_rotvec()
        error = np.concatenate([rotation, T.translation - mount.T_base_lidar.translation])
        covariance = cal.estimates[name].lidar_covariance(mount.T_imu_lidar)
        std = None if covariance is None else np.sqrt(np.diag(covariance))
        drift, drift_std = s["clock_drift_ppm"], s["clock_drift_std_ppm"]
        offset_error = s["time_offset_s"] - truth[name]["time_offset_s"]
        said = [w for w in s["warnings"] if w.startswith("clock stepped by")]
        found = [(float(w.split(" at ")[1].split(" s")[0]), w) for w in said]
        true_steps = truth[name]["clock_steps"]
        rows.append(
            {
                "scenario": scenario,
                "status": s["status"],
                "ratios": None if std is None else np.abs(error) / std,
                "drift_ratio": None
                if drift is None
                else abs(drift - truth[name]["clock_drift_ppm"]) / drift_std,
                "offset_ratio": abs(offset_error) / s["time_offset_std_s"]
                if s["time_offset_std_s"]
                else None,
                "rotation_deg": float(np.degrees(np.linalg.norm(error[:3]))),
                "translation_mm": float(1000 * np.linalg.norm(error[3:])),
                "steps": len(true_steps),
                "found": sum(
                    any(abs(at - true_at) <= STEP_TIME_S for at, _ in found)
                    for true_at, _ in true_steps
                ),
                "false_steps": max(0, len(found) - len(true_steps)),
                **_moves(cal, name, s, truth[name], mount),
                **_epochs(s, truth[name], mount),
            }
        )
    return rows


def _moves(cal: Any, name: str, s: dict[str, Any], truth: dict[str, Any], mount: Any) -> dict:
    """The knocks found (the time within two windows) and their sizes against the truth's,
    over the std of the poses either side; the moves said where there was no knock."""
    from imucal_cli.core.so3 import rotation_angle_deg
    from imucal_cli.types import Transform

    true = truth["moved"]
    poses = [Transform.from_dict(m["before"]["T_base_lidar"], "t", "t") for m in true]
    poses.append(mount.T_base_lidar)
    said = s["moved"]
    after_std = (max(s["rotation_std_deg"] or [np.inf]), max(s["translation_std_m"] or [np.inf]))
    found, size_ratios = 0, []
    for k, knock in enumerate(true):
        near = [m for m in said if abs(m["at_s"] - knock["at_s"]) <= STEP_TIME_S]
        if not near:
            continue
        found += 1
        m = near[0]
        angle = rotation_angle_deg(poses[k].rotation, poses[k + 1].rotation)
        shift = float(np.linalg.norm(poses[k + 1].translation - poses[k].translation))
        std_r = np.hypot(max(m["before"]["rotation_std_deg"]), after_std[0])
        std_t = np.hypot(max(m["before"]["translation_std_m"]), after_std[1])
        size_ratios += [
            abs(m["rotation_deg"] - angle) / std_r,
            abs(m["translation_m"] - shift) / std_t,
        ]
    return {
        "knocks": len(true),
        "knocks_found": found,
        "size_ratios": size_ratios,
        "false_moves": max(0, len(said) - found),
        "knocked_log": bool(true),
    }


def _epochs(s: dict[str, Any], truth: dict[str, Any], mount: Any) -> dict[str, Any]:
    """Each epoch of the timeline wholly between two knocks against the pose then: the error
    of every axis (rotation about the base axes, translation) over the epoch's std."""
    from imucal_cli.types import Transform

    knocks = [m["at_s"] for m in truth["moved"]]
    poses = [Transform.from_dict(m["before"]["T_base_lidar"], "t", "t") for m in truth["moved"]]
    poses.append(mount.T_base_lidar)
    ratios = []
    for epoch in s["timeline"]:
        if any(epoch["start_s"] - 5.0 < at < epoch["end_s"] + 5.0 for at in knocks):
            continue  # (it holds two poses, or the knock's window)
        then = poses[sum(at <= epoch["start_s"] for at in knocks)]
        pose = Transform.from_dict(
            {"translation": epoch["translation"], "rpy_deg": epoch["rpy_deg"]}, "t", "t"
        )
        rotation = np.degrees((then.rotation * pose.rotation.inv()).as_rotvec())
        std = np.array([*epoch["rotation_std_deg"], *epoch["translation_std_m"]])
        error = np.abs(np.concatenate([rotation, pose.translation - then.translation]))
        ratios.append(error / std)
    return {"epoch_ratios": ratios}


def epoch_table(rows: list[dict[str, Any]]) -> None:
    print(f"\n### the timeline (epoch_s {EPOCH_S:g}; epochs wholly between knocks)\n")
    print("| scenario | epochs | axes within 3 std | epochs with an axis beyond 4 std |")
    print("|---|---|---|---|")
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        ratios = [e for r in rows if r["scenario"] == scenario for e in r["epoch_ratios"]]
        values = np.concatenate(ratios) if ratios else np.zeros(0)
        print(
            f"| {scenario} | {len(ratios)} | {100 * np.mean(values <= 3):.1f}% "
            f"| {sum(bool(np.any(e > 4)) for e in ratios)} |"
        )


def knock_table(rows: list[dict[str, Any]]) -> None:
    print("\n### mounts knocked\n")
    print(
        "| scenario | knocks | found (time within 2 windows) | sizes within 3 std | worst size "
        "err/std | moves said where none (lidars) | lidars without a knock |"
    )
    print("|---|---|---|---|---|---|---|")
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        mine = [r for r in rows if r["scenario"] == scenario]
        ratios = [v for r in mine for v in r["size_ratios"]]
        print(
            f"| {scenario} | {sum(r['knocks'] for r in mine)} "
            f"| {sum(r['knocks_found'] for r in mine)} "
            f"| {sum(v <= 3 for v in ratios)} / {len(ratios)} "
            f"| {max(ratios, default=float('nan')):.2f} | {sum(r['false_moves'] for r in mine)} "
            f"| {sum(not r['knocks'] for r in mine)} |"
        )


def table(rows: list[dict[str, Any]], title: str) -> None:
    print(f"\n### {title}\n")
    print(
        "| scenario | sensors | ok / partial / inconsistent / unobservable | ok beyond 4 std "
        "| axes within 3 std | median rot err deg | median trans err mm | drift reported "
        "| drift within 3 std | worst drift err/std | offset within 3 std | steps found "
        "| steps said where none |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        mine = [r for r in rows if r["scenario"] == scenario]
        counts = [
            sum(r["status"] == s for r in mine)
            for s in ("ok", "partial", "inconsistent", "unobservable")
        ]
        ok = [r for r in mine if r["status"] == "ok" and r["ratios"] is not None]
        beyond = sum(bool(np.any(r["ratios"] > 4)) for r in ok)
        ratios = np.concatenate([r["ratios"] for r in mine if r["ratios"] is not None] or [[]])
        within = 100 * np.mean(ratios <= 3) if len(ratios) else float("nan")
        drift = [r["drift_ratio"] for r in mine if r["drift_ratio"] is not None]
        offsets = [r["offset_ratio"] for r in mine if r["offset_ratio"] is not None]
        print(
            f"| {scenario} | {len(mine)} | {' / '.join(map(str, counts))} | {beyond} "
            f"| {within:.1f}% | {np.median([r['rotation_deg'] for r in mine]):.4f} "
            f"| {np.median([r['translation_mm'] for r in mine]):.2f} | {len(drift)} "
            f"| {sum(d <= 3 for d in drift)} | {max(drift, default=float('nan')):.2f} "
            f"| {sum(o <= 3 for o in offsets)} / {len(offsets)} "
            f"| {sum(r['found'] for r in mine)} / {sum(r['steps'] for r in mine)} "
            f"| {sum(r['false_steps'] for r in mine)} |"
        )


def figure(path: str) -> None:
    """The report's timeline figure (docs/timeline.md) of a 900 s town drive of two lidars, the
    first knocked at 450 s by 1.3 deg and 11 mm."""
    from pathlib import Path

    from imucal_cli.report import pyplot, timeline_figure

    knock = ((450.0, (0.02, 0.01, 0.0), (0.01, 0.0, 0.005)),)
    options = DriveOptions(scenario="urban", seed=3, sensors=2, duration_s=900.0, knocks=(knock,))
    drive = simulate_drive(options)
    cal = calibrate_streams(drive.streams(), drive.config())
    timeline_figure(pyplot(), cal.document()["sensors"], Path(path))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--figure", help="only draw docs/timeline.md's figure into this PNG")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--scenarios", nargs="*", default=list(SCENARIOS))
    args = parser.parse_args()
    if args.figure:
        figure(args.figure)
        return
    start = time.perf_counter()
    cases = [(s, seed, True) for s in args.scenarios for seed in range(args.seeds)]
    single = [(s, seed, False) for s, seed, _ in cases]
    with ProcessPoolExecutor(args.jobs) as pool:
        followed = [row for rows in pool.map(run_case, cases) for row in rows]
        one_offset = [row for rows in pool.map(run_case, single) for row in rows]
    print(
        f"Clocks drifting +-{DRIFT_PPM[0]:g}-{DRIFT_PPM[1]:g} ppm from offsets within "
        f"+-{1000 * OFFSET_S:g} ms; {args.seeds} seeds, four lidars a drive "
        f"({time.perf_counter() - start:.0f} s)."
    )
    table(followed, "drift followed (the default, max_clock_drift_ppm: 200)")
    knock_table(followed)
    epoch_table(followed)
    table(one_offset, "one offset for the log (max_clock_drift_ppm: 0)")


if __name__ == "__main__":
    main()
