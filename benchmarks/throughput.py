"""Throughput and memory on long logs; prints markdown tables (docs/performance.md).

Builds (once, cached in ``benchmarks/.cache``) logs of a rig with one base IMU at 100 Hz and
four lidar IMUs at 200 Hz (900 messages/s) driving in town, and measures per format and length:

- floor: read the container and decompress it, decoding nothing (MCAP and ROS 1: every chunk;
  rosbag2 sqlite3: SQLite's fetch of every row);
- read: :class:`~imucal_cli.reading.ImuBatches` over every IMU topic (decode and screening);
- each command (``calibrate``, ``inspect``, ``biases``, ``segments``) end to end in a fresh
  process: wall time and peak RSS (``ru_maxrss`` of the process);
- the largest error of ``T_base_lidar`` over the four lidars against the simulator's truth.

The package's bytecode is compiled first (:func:`compile_package`), as ``pip install`` does: an
environment with ``PYTHONDONTWRITEBYTECODE`` set (this workplace's) would otherwise have every
command compile imucal's modules again, 0.1 s a run that no installed copy pays.

Each figure is the least of ``--repeat`` rounds, each round running every case in turn (the
machine's run-to-run spread is tens of per cent; the minimum is the least disturbed); peak RSS
is the largest.

Run: ``python benchmarks/throughput.py [--lengths 15m 1h 4h] [--formats mcap rosbag1
rosbag2-sqlite3] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache"
LENGTHS = {"15m": 900.0, "1h": 3600.0, "4h": 14400.0}
SUFFIX = {"mcap": ".mcap", "rosbag2-sqlite3": "", "rosbag1": ".bag"}
COMMANDS = ("calibrate", "inspect", "biases", "segments")
MEASURE = """
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode
used = resource.getrusage(resource.RUSAGE_CHILDREN)
print(time.perf_counter() - start, used.ru_utime + used.ru_stime, used.ru_maxrss, code)
"""


def build(length: str, fmt: str) -> tuple[Path, Path]:
    """The cached log and its config (made with the simulator's writer)."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    CACHE.mkdir(exist_ok=True)
    stem = CACHE / f"town_{length}_{fmt}"
    log, config = (
        stem.with_name(stem.name + SUFFIX[fmt]),
        stem.with_name(stem.name + ".config.yaml"),
    )
    if log.exists() and config.exists():
        return log, config
    start = time.perf_counter()
    drive = simulate_drive(
        DriveOptions(
            scenario="urban", duration_s=LENGTHS[length], seed=1, sensors=4, lidar_rate_hz=200.0
        )
    )
    write_imu_log(log, fmt, drive.topics())
    write_document(config, drive.config_document())
    write_document(stem.with_name(stem.name + ".truth.yaml"), drive.truth_document())
    print(f"built {log.name} in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return log, config


def compile_package() -> None:
    """Write the bytecode of every module of imucal (``__pycache__``, as an install does)."""
    import compileall

    import imucal_cli

    if not compileall.compile_dir(Path(imucal_cli.__file__).parent, quiet=1):
        raise RuntimeError("imucal's modules did not compile")


def floor(log: Path, fmt: str) -> tuple[float, float]:
    """Wall and CPU seconds to read and decompress the storage, decoding nothing."""
    start, cpu = time.perf_counter(), time.process_time()
    if fmt == "mcap":
        from mcap.records import Chunk
        from mcap.stream_reader import StreamReader

        from imucal_cli.io.base import decompress
        from imucal_cli.io.mcap_log import McapLog

        with McapLog(log) as reader, log.open("rb") as handle:
            indexes = list(reader._chunks)  # (the summary's chunk indexes, as held)
            assert indexes, f"{log}: no chunk index: the floor would read nothing"
            for index in indexes:
                handle.seek(index.chunk_start_offset)
                chunk = next(iter(StreamReader(handle, skip_magic=True, emit_chunks=True).records))
                assert isinstance(chunk, Chunk)
                decompress(
                    chunk.compression,
                    chunk.data,
                    chunk.uncompressed_size,
                    out=np.empty(chunk.uncompressed_size, dtype=np.uint8),
                )
    elif fmt == "rosbag1":
        from imucal_cli.io.base import decompress
        from imucal_cli.io.rosbag1 import _U32, Ros1Log

        with Ros1Log(log) as reader:
            for chunk_pos, _ in reader.chunks:
                fields, begin, length, _ = reader._header(chunk_pos)
                decompress(
                    fields["compression"].decode("latin-1"),
                    reader._read(chunk_pos + begin, length),
                    _U32.unpack(fields["size"])[0],
                )
    else:
        for db in sorted(log.glob("*.db3")):
            connection = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            cursor = connection.execute("SELECT timestamp, data FROM messages")
            while cursor.fetchmany(65536):
                pass
            connection.close()
    return time.perf_counter() - start, time.process_time() - cpu


def read(log: Path, config: Path) -> tuple[float, float, int]:
    from imucal_cli.config import load_config
    from imucal_cli.reading import ImuBatches

    cfg = load_config(config)
    start, cpu = time.perf_counter(), time.process_time()
    count = sum(
        len(batch[1])
        for batch in ImuBatches(log, [cfg.base.topic, *(s.imu_topic for s in cfg.sensors)])
    )
    return time.perf_counter() - start, time.process_time() - cpu, count


def command(name: str, log: Path, config: Path, out: Path) -> tuple[float, float, float]:
    """Wall seconds, CPU seconds (user + system of every process it ran) and peak RSS (MB) of
    ``imucal NAME`` in a fresh process."""
    args = [str(Path(sys.executable).with_name("imucal")), name, str(log)]
    if name != "inspect":
        args += ["-c", str(config)]
    args += ["-o", str(out)]
    printed = subprocess.run(
        [sys.executable, "-c", MEASURE, *args], capture_output=True, text=True, check=True
    ).stdout.split()
    if printed[3] != "0":
        raise RuntimeError(f"imucal {name} {log} exited {printed[3]}")
    return float(printed[0]), float(printed[1]), float(printed[2]) / 1024


def errors(estimate: Path, truth: Path) -> tuple[float, float]:
    from imucal_cli.api import load_transforms
    from imucal_cli.outputs import transform_errors

    est, tru = load_transforms(estimate), load_transforms(truth)
    found = [transform_errors(est[n], tru[n]) for n in tru]
    return max(e["rotation_error_deg"] for e in found), max(e["translation_error_m"] for e in found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", nargs="+", default=["15m", "1h", "4h"], choices=list(LENGTHS))
    parser.add_argument(
        "--formats", nargs="+", default=["mcap", "rosbag1", "rosbag2-sqlite3"], choices=list(SUFFIX)
    )
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    # the scaling is measured on MCAP; every round runs every case once, so that the machine's
    # drift (tens of per cent over minutes) falls on all lengths alike
    cases = {
        (length, fmt): build(length, fmt)
        for length in args.lengths
        for fmt in args.formats
        if length != "4h" or fmt == "mcap"
    }
    compile_package()
    runs: dict[tuple[str, str], dict[str, list[tuple[float, ...]]]] = {case: {} for case in cases}
    errors_of = {}
    for _ in range(args.repeat):
        for case, (log, config) in cases.items():
            fmt = case[1]
            runs[case].setdefault("floor", []).append((*floor(log, fmt), 0.0))
            runs[case].setdefault("read", []).append(read(log, config))
            for name in COMMANDS:
                runs[case].setdefault(name, []).append(
                    command(name, log, config, CACHE / f"out_{name}.yaml")
                )
            truth = config.with_name(config.name.replace(".config.yaml", ".truth.yaml"))
            errors_of[case] = errors(CACHE / "out_calibrate.yaml", truth)
    print(
        "| length | format | messages | size MB | what | wall s | CPU s | wall / floor "
        "| CPU / floor | peak RSS MB |"
    )
    print("|---" * 10 + "|")
    for (length, fmt), (log, _) in cases.items():
        own = runs[(length, fmt)]
        size = log.stat().st_size if log.is_file() else sum(p.stat().st_size for p in log.iterdir())
        wall0, cpu0 = min(r[0] for r in own["floor"]), min(r[1] for r in own["floor"])
        count = int(own["read"][0][2])
        for what in ("floor", "read", *COMMANDS):
            wall, cpu = min(r[0] for r in own[what]), min(r[1] for r in own[what])
            rss = f"{max(r[2] for r in own[what]):.0f}" if what in COMMANDS else ""
            print(
                f"| {length} | {fmt} | {count:,} | {size / 1e6:.0f} | {what} | {wall:.2f} | "
                f"{cpu:.2f} | {wall / wall0:.1f} | {cpu / cpu0:.1f} | {rss} |"
            )
    print()
    print("| case | max dR deg | max abs dt m |")
    print("|---|---|---|")
    for (length, fmt), (dr, dt) in errors_of.items():
        print(f"| {length} {fmt} | {dr:.4f} | {dt:.4f} |")
    checks = []
    if ("1h", "mcap") in runs:
        own = runs[("1h", "mcap")]

        def rounds(a: str, b: str, k: int) -> float:
            """``a / b`` (figure ``k``: 0 wall, 1 CPU) from each round's own pair, measured
            seconds apart and so less moved by the machine's drift: their median."""
            return float(np.median([x[k] / y[k] for x, y in zip(own[a], own[b], strict=True)]))

        checks.append(
            ("1h mcap calibrate CPU / floor CPU", rounds("calibrate", "floor", 1), "<= 5")
        )
        checks.append(
            ("1h mcap calibrate wall / floor wall", rounds("calibrate", "floor", 0), "<= 4")
        )
        checks.append(
            ("1h mcap calibrate peak RSS MB", max(r[2] for r in own["calibrate"]), "<= 1000")
        )
        for name in COMMANDS[1:]:
            for k, what in ((1, "CPU"), (0, "wall")):
                checks.append(
                    (f"1h mcap {name} / calibrate, {what}", rounds(name, "calibrate", k), "<= 1")
                )
    if ("1h", "mcap") in runs and ("4h", "mcap") in runs:
        one = min(r[1] for r in runs[("1h", "mcap")]["calibrate"])
        four = min(r[1] for r in runs[("4h", "mcap")]["calibrate"])
        checks.append(("4h mcap calibrate CPU / (4 x 1h)", four / (4 * one), "<= 1.1"))
    print()
    print("| check (median of the rounds' ratios) | measured | bound | met |")
    print("|---|---|---|---|")
    for name, value, bound in checks:
        met = eval(f"{value} {bound}")
        print(f"| {name} | {value:.2f} | {bound} | {'yes' if met else 'NO'} |")


if __name__ == "__main__":
    main()
