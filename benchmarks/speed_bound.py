"""What bounds ``calibrate``'s time on the 1 h MCAP of :mod:`throughput`, in units of its floor.

Prints, per round, each figure as a multiple of that round's floor (read and decompress,
decoding nothing):

- ``imports``: a fresh process importing what ``imucal calibrate`` imports;
- ``imports + read``: what a calibration whose math took no time at all would take (the
  imports, then :class:`~imucal_cli.reading.ImuBatches` over every IMU topic);
- ``one process``: imports, read, windows and solve in one fresh process (``calibrate``
  without its document);
- ``two halves``: the log split in time between two processes on the machine's two cores,
  each importing, reading and reducing the windows of half an hour (a half-hour drive of the
  same rig), plus the solve timed in ``one process``, halved as if the sensors were split
  between the processes too. This is the best a time-split design could do; merging the
  halves' moments and read counters is not counted.

Run: ``python benchmarks/speed_bound.py [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from throughput import CACHE, floor  # noqa: E402

STAGES = """
import os, sys, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as imucal's entry point sets it
start = time.perf_counter()
import imucal_cli.cli
from imucal_cli.pipeline import estimate, stream_log
from imucal_cli.config import load_config
from imucal_cli.reading import ImuBatches
imported = time.perf_counter()
config = load_config(sys.argv[2])
if sys.argv[3] == "read":
    for _ in ImuBatches(sys.argv[1], config.imu_names()):
        pass
    print(imported - start, time.perf_counter() - imported, 0.0)
    raise SystemExit
streamed = stream_log(sys.argv[1], config)
for name in streamed.calibrator.sensors:
    streamed.calibrator.window_infos(name)
reduced = time.perf_counter()
if sys.argv[3] == "solve":
    estimate(streamed)
print(imported - start, reduced - imported, time.perf_counter() - reduced)
"""


def half_hour() -> tuple[Path, Path]:
    """A half-hour drive of the throughput benchmark's rig (cached)."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    log, config = CACHE / "town_30m_mcap.mcap", CACHE / "town_30m_mcap.config.yaml"
    if not (log.exists() and config.exists()):
        CACHE.mkdir(exist_ok=True)
        drive = simulate_drive(
            DriveOptions(
                scenario="urban", duration_s=1800.0, seed=1, sensors=4, lidar_rate_hz=200.0
            )
        )
        write_imu_log(log, "mcap", drive.topics())
        write_document(config, drive.config_document())
    return log, config


def stages(log: Path, config: Path, what: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", STAGES, str(log), str(config), what],
        stdout=subprocess.PIPE,
        text=True,
    )


def seconds(process: subprocess.Popen[str]) -> list[float]:
    out, _ = process.communicate()
    if process.returncode != 0:
        raise RuntimeError(f"stage run exited {process.returncode}")
    return [float(v) for v in out.split()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    log, config = CACHE / "town_1h_mcap.mcap", CACHE / "town_1h_mcap.config.yaml"
    if not log.exists():
        raise SystemExit(f"{log}: run benchmarks/throughput.py --lengths 1h --formats mcap first")
    half_log, half_config = half_hour()
    rows = []
    for _ in range(args.repeat):
        t_floor = floor(log, "mcap")
        imports, read, _ = seconds(stages(log, config, "read"))
        start = time.perf_counter()
        _, _, solve = seconds(stages(log, config, "solve"))
        one = time.perf_counter() - start
        start = time.perf_counter()
        halves = [stages(half_log, half_config, "reduce") for _ in range(2)]
        for process in halves:
            seconds(process)
        two = time.perf_counter() - start + solve / 2
        rows.append((t_floor, imports, imports + read, one, two))
    print(
        "| round | floor s | imports / floor | imports + read / floor | one process / floor | two "
        "halves / floor |"
    )
    print("|---|---|---|---|---|---|")
    for k, (t_floor, imports, math_free, one, two) in enumerate(rows, start=1):
        print(
            f"| {k} | {t_floor:.2f} | {imports / t_floor:.1f} | {math_free / t_floor:.1f} | "
            f"{one / t_floor:.1f} | {two / t_floor:.1f} |"
        )
    ratios = np.array([[r[2] / r[0], r[3] / r[0], r[4] / r[0]] for r in rows])
    print()
    print("| design | median / floor | bound |")
    print("|---|---|---|")
    for name, column in (
        ("math free (imports + read)", 0),
        ("one process (today)", 1),
        ("two halves in time, solve split", 2),
    ):
        print(f"| {name} | {np.median(ratios[:, column]):.1f} | <= 4 |")


if __name__ == "__main__":
    main()
