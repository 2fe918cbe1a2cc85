"""Fleet runs: ``imucal batch`` over simulated logs with 1 and 2 local processes and on a
2-worker Dask LocalCluster (loopback); prints wall times and checks the results are identical
and the JUnit XML parses.

Run: ``python benchmarks/fleet.py [--logs 20] [--duration 300]``. Logs are cached in
``benchmarks/.cache/fleet``. Each run is the ``imucal`` command in a fresh process.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

HERE = Path(__file__).resolve().parent


def build(folder: Path, count: int, duration: float) -> list[Path]:
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    folder.mkdir(parents=True, exist_ok=True)
    logs = []
    for seed in range(1, count + 1):
        log = folder / f"town{seed:02d}.mcap"
        if not log.exists():
            drive = simulate_drive(
                DriveOptions(scenario="urban", duration_s=duration, seed=seed, sensors=4)
            )
            write_imu_log(log, "mcap", drive.topics())
            write_document(folder / f"town{seed:02d}.truth.yaml", drive.truth_document())
            write_document(folder / "config.yaml", drive.config_document())
        logs.append(log)
    return logs


def batch(
    folder: Path, logs: list[Path], out: Path, extra: list[str]
) -> tuple[float, list[dict[str, str]]]:
    shutil.rmtree(out, ignore_errors=True)
    command = [
        sys.executable,
        "-m",
        "imucal_cli.cli",
        "batch",
        *map(str, logs),
        "-c",
        str(folder / "config.yaml"),
        "--out-dir",
        str(out),
        "--truth-dir",
        str(folder),
        "--max-rotation-deg",
        "0.1",
        "--max-translation-m",
        "0.03",
        "--junit",
        str(out) + ".xml",
        *extra,
    ]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if result.returncode not in (0, 1):
        raise SystemExit(f"batch failed: {result.stderr[-2000:]}")
    ET.parse(str(out) + ".xml")  # valid XML or this raises
    with (out / "summary.csv").open() as handle:
        return wall, list(csv.DictReader(handle))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", type=int, default=20)
    parser.add_argument("--duration", type=float, default=300.0)
    args = parser.parse_args()
    folder = HERE / ".cache" / "fleet"
    logs = build(folder, args.logs, args.duration)
    work = HERE / ".cache" / "fleet-out"
    work.mkdir(exist_ok=True)
    t1, rows1 = batch(folder, logs, work / "jobs1", ["--jobs", "1"])
    t2, rows2 = batch(folder, logs, work / "jobs2", ["--jobs", "2"])
    from dask.distributed import LocalCluster

    runs = [("--jobs 1", t1, rows1, None), ("--jobs 2", t2, rows2, None)]
    import dask.config

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    # Dask's workers start with MALLOC_TRIM_THRESHOLD_=65536, which also fixes glibc's mmap
    # threshold at 128 kB: every medium numpy temporary becomes an mmap/munmap pair and its
    # pages fault in anew. imucal's tasks make many of them; this setting slows them by half.
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    tuned = {"distributed.nanny.pre-spawn-environ": environ}
    one_worker = None
    for label, settings, workers in (
        ("Dask LocalCluster, 2 workers (Dask defaults)", {}, 2),
        ("Dask LocalCluster, 1 worker (glibc malloc defaults)", tuned, 1),
        ("Dask LocalCluster, 2 workers (glibc malloc defaults)", tuned, 2),
    ):
        with (
            dask.config.set(settings),
            LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
            ) as cluster,
        ):
            wall, rows = batch(
                folder, logs, work / "dask", ["--scheduler", cluster.scheduler_address]
            )
        if workers == 1:
            one_worker = wall
        runs.append((label, wall, rows, one_worker if workers == 2 and settings else None))
    passed = sum(r["pass"] == "True" for r in rows1)
    print(
        f"## imucal batch: {len(logs)} simulated logs ({args.duration:.0f} s urban, 4 lidars "
        "each), 2-core machine\n"
    )
    print(
        "| run | wall s | x of --jobs 1 | x of the same scheduler with 1 worker | rows | passed | "
        "identical to --jobs 1 |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, wall, rows, single in runs:
        same = (
            f"{wall / t1:.2f}"
            if name == "--jobs 2"
            else ("-" if single is None else f"{wall / single:.2f}")
        )
        print(
            f"| {name} | {wall:.1f} | {wall / t1:.2f} | {same} | {len(rows)} | "
            f"{sum(r['pass'] == 'True' for r in rows)} | {'yes' if rows == rows1 else 'NO'} |"
        )
    print(
        f"\nJUnit XML parsed for every run; {passed} of {len(rows1)} sensor rows pass 0.1 deg / 3 "
        "cm against truth."
    )


if __name__ == "__main__":
    main()
