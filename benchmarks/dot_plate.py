"""The quadrotor plate's four Xsens DOTs placed against each other; prints tables.

The rig ``quad_flight1_dot1_dot7`` (``../shared/realdata/multi_imu``) has no measured lever arm:
its truth file's translation is a placeholder. The dataset holds four DOTs on that plate, in
three flights of one day, so the estimates can be checked against what a rigid plate must satisfy
without knowing where the DOTs are:

- **Closure.** Every DOT calibrated against DOT1 and, again, against DOT2: the lever arm
  DOT2 -> DOTk measured directly must equal the one composed through DOT1,
  ``R_12^T (t_1k - t_12)``, within the two estimates' std.
- **Repeatability.** The same pair in two flights: within the combined statistical std.
- **Shape.** The four DOTs sit flat on one plate in two touching pairs either side of the
  camera gimbal (the dataset's photo, Fig. 7): the two shortest of the six distances near
  one DOT length or width (30-37 mm), the plane through them level with the DOTs' x-y plane.

The recordings are the dataset's own CSVs (SampleTimeFine in us, gyro in deg/s), converted
as the rig's log was: rows of all-zero motion dropped, the span every DOT covers, gyro to
rad/s. Each log is written as MCAP beside the others in a temporary folder and calibrated
with ``imucal_cli.calibrate`` and the rig's config (every DOT declared consumer grade), as a user
would.

Run: ``python benchmarks/dot_plate.py DATASET`` where DATASET is a checkout of
github.com/ansfl/Quadrotor-Dead-Reckoning-with-Multiple-Inertial-Sensors (CC BY 4.0,
Hurwitz & Klein, arXiv 2310.13452).
"""

from __future__ import annotations

import argparse
import copy
import tempfile
from itertools import combinations
from pathlib import Path

import numpy as np
from real_rigs import RIGS, header

from imucal_cli.api import calibrate
from imucal_cli.config import parse_config
from imucal_cli.documents import load_document
from imucal_cli.sim.writers import TopicData, write_imu_log
from imucal_cli.types import ImuStream

RIG = RIGS / "quad_flight1_dot1_dot7"
DOTS = ("DOT1", "DOT2", "DOT4", "DOT7")
EPOCH_NS = 1_700_000_000_000_000_000  # the rig log's origin


def read_dot(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SampleTimeFine (us, unwrapped), gyro (rad/s), accel (m/s^2) of one DOT's CSV."""
    table = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=range(10))
    keep = np.any(table[:, 4:10] != 0, axis=1)
    table = table[keep]
    t_us = np.unwrap(table[:, 0], period=2**32).astype(np.int64)
    return t_us, np.radians(table[:, 7:10]), table[:, 4:7]


def flight_files(dataset: Path) -> dict[str, dict[str, Path]]:
    """Per flight (the hour and minute its files start, HHMM), each DOT's CSV; only flights
    with all four DOTs."""
    raw = dataset / "StraightLine" / "RAW"
    flights: dict[str, dict[str, Path]] = {}
    for path in sorted(raw.glob("Xsens DOT*.csv")):
        dot, stamp = path.stem.split(" ")[1].split("_")[0], path.stem.split("_")[-1]
        flights.setdefault(stamp[:4], {})[dot] = path  # the DOTs start within a second
    return {k: v for k, v in flights.items() if set(v) == set(DOTS)}


def write_flight(files: dict[str, Path], base: str, out: Path) -> Path:
    """One MCAP: ``base`` on /base/imu, every other DOT on /<dot>/imu, over the common span."""
    data = {dot: read_dot(path) for dot, path in files.items()}
    start = max(int(t[0]) for t, _, _ in data.values())
    end = min(int(t[-1]) for t, _, _ in data.values())
    topics = {}
    for dot, (t_us, gyro, accel) in data.items():
        keep = (t_us >= start) & (t_us <= end)
        stream = ImuStream(EPOCH_NS + (t_us[keep] - start) * 1000, gyro[keep], accel[keep])
        topic = "/base/imu" if dot == base else f"/{dot.lower()}/imu"
        topics[topic] = TopicData(stream)
    return write_imu_log(out, "mcap", topics)


def config_for(base: str):
    """The rig's config, with every DOT but ``base`` a sensor and all declared consumer."""
    document = load_document(RIG / "config.yaml")
    template = document["sensors"].pop("imu2")
    document["base"]["grade"] = "consumer"
    for dot in DOTS:
        if dot != base:
            sensor = copy.deepcopy(template)
            sensor["imu_topic"] = f"/{dot.lower()}/imu"
            sensor["grade"] = "consumer"
            document["sensors"][dot] = sensor
    return parse_config(document, str(RIG / "config.yaml"))


def fmt(values, scale: float = 1.0, digits: int = 1) -> str:
    return ", ".join(f"{scale * v:.{digits}f}" for v in values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    args = parser.parse_args()
    flights = flight_files(args.dataset)
    if not flights:
        raise SystemExit(f"no flight with all of {', '.join(DOTS)} under {args.dataset}")
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for flight, files in flights.items():
            for base in ("DOT1", "DOT2"):
                log = write_flight(files, base, Path(tmp) / f"{flight}_{base}.mcap")
                runs[flight, base] = calibrate(log, config_for(base))

    print("## Every DOT against DOT1 and against DOT2\n")
    header("flight", "base", "sensor", "status", "t mm", "total std mm", "stat std mm", "rpy deg")
    for (flight, base), run in runs.items():
        for name, estimate in sorted(run.estimates.items()):
            T = run.T_base_lidar(name)
            stat = np.sqrt(np.diag(estimate.statistical_covariance)[3:])
            total = run.document()["sensors"][name].get("translation_std_m") or [np.nan] * 3
            rpy = T.rotation.as_euler("xyz", degrees=True)
            print(
                f"| {flight} | {base} | {name} | {estimate.status} | {fmt(T.translation, 1e3)} "
                f"| {fmt(total, 1e3)} | {fmt(stat, 1e3)} | {fmt(rpy, 1, 2)} |"
            )

    print("\n## Closure: DOT2 -> DOTk measured, against composed through DOT1\n")
    header("flight", "DOTk", "direct mm", "composed mm", "difference mm", "over total std")
    for flight in flights:
        one, two = runs[flight, "DOT1"], runs[flight, "DOT2"]
        T12 = one.T_base_lidar("DOT2")
        for dot in ("DOT4", "DOT7"):
            T1k = one.T_base_lidar(dot)
            composed = T12.rotation.inv().apply(T1k.translation - T12.translation)
            direct = two.T_base_lidar(dot).translation
            var = sum(
                np.square(run.document()["sensors"][name]["translation_std_m"])
                for run, name in ((one, "DOT2"), (one, dot), (two, dot))
            )
            diff = direct - composed
            print(
                f"| {flight} | {dot} | {fmt(direct, 1e3)} | {fmt(composed, 1e3)} "
                f"| {fmt(diff, 1e3)} | {fmt(diff / np.sqrt(var), 1, 1)} |"
            )

    print("\n## Repeatability: one pair in two flights (base DOT1)\n")
    header("sensor", "flights", "difference mm", "over combined statistical std")
    for dot in ("DOT2", "DOT4", "DOT7"):
        for a, b in combinations(flights, 2):
            ea = runs[a, "DOT1"].estimates[dot]
            eb = runs[b, "DOT1"].estimates[dot]
            diff = (
                runs[a, "DOT1"].T_base_lidar(dot).translation
                - runs[b, "DOT1"].T_base_lidar(dot).translation
            )
            combined = np.sqrt(
                np.diag(ea.statistical_covariance)[3:] + np.diag(eb.statistical_covariance)[3:]
            )
            print(f"| {dot} | {a}, {b} | {fmt(diff, 1e3)} | {fmt(diff / combined, 1, 1)} |")

    print("\n## Shape: the four DOTs' centres in DOT1's frame (base DOT1)\n")
    header("flight", "distances mm, shortest first", "largest |z| mm")
    for flight in flights:
        run = runs[flight, "DOT1"]
        points = [np.zeros(3)] + [run.T_base_lidar(d).translation for d in DOTS[1:]]
        distances = sorted(np.linalg.norm(p - q) for p, q in combinations(points, 2))
        z = max(abs(p[2]) for p in points)
        print(f"| {flight} | {fmt(distances, 1e3, 0)} | {1e3 * z:.1f} |")


if __name__ == "__main__":
    main()
