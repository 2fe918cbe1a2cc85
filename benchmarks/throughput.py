"""Throughput and memory on long logs; prints a markdown table.

Builds (once, cached in ``benchmarks/.cache``) logs of a rig with one base IMU at 100 Hz and four
lidar IMUs at 200 Hz (900 messages/s) driving in town, in MCAP (zstd chunks), rosbag2 sqlite3
and ROS 1 (lz4 chunks), and measures per format and length, side by side in one run:

- floor: read the container and decompress it, decoding nothing (MCAP and ROS 1: every chunk;
  sqlite3: SQLite's fetch of every row's timestamp and blob); for sqlite3 also the time to read
  the file's bytes, printed below the table (the fast path reads the pages itself);
- decode: ``read_imu`` with the fast path, all IMU topics to arrays (messages/s, x floor);
- naive: the generic path (container reader + rosbags' per-message deserialiser);
- calibrate: ``imucal calibrate`` end to end in a fresh process, wall time, peak RSS and the
  largest error of ``T_base_lidar`` over the four lidars against the simulator's truth. Peak
  RSS is the highest sum of the resident sizes of the process and its children (the log reader
  and the math worker) at one instant, sampled every 10 ms; "sum of peaks" adds each process's
  own peak (``VmHWM``) instead, an upper bound that counts pages shared after the fork twice and
  adds peaks that never meet (the reader's, while reading; the solve's, after it). Its CPU
  seconds (user + system) are given per process: the main one, the log reader and the math
  worker (sampled from ``/proc`` every 10 ms); wall time is at least their sum over the two
  cores.

Below the table: per format measured at several lengths, ``calibrate``'s scaling (wall time
and peak RSS against the shorter log's, and the wall time each added hour of log costs: linear
in length means the same cost per added hour, while the plain ratio of wall times also carries
the fixed start-up, imports and forks, which a longer log spreads thinner); then each figure
of issue 4's "must show" from this run against its bound. "Wall time linear in length" is
checked both ways: the 4 h log against 4 times the 1 h log (which counts the start-up four
times, so a log four times longer comes out faster than proportional), and against the
straight line through the 15 min and 1 h logs (start-up plus a cost per hour) carried on to
4 h, where 15 min was measured.

Floor and decode are run ``--repeat`` times (default 5) and calibrate ``--calibrate-repeat``
times (default 5), taking turns (floor, decode, calibrate, floor, ...); the fastest run of each
is reported (the machine's run-to-run spread is tens of per cent and its speed drifts over
minutes; the minimum is the least disturbed), with the largest peak RSS of the calibrate runs.
The naive path, minutes long, runs once, after them.

Run: ``python benchmarks/throughput.py [--lengths 15m 1h 4h] [--formats mcap rosbag2-sqlite3
rosbag1] [--naive-max-minutes 60] [--repeat 5] [--calibrate-repeat 5]``.
"""

from __future__ import annotations

import argparse
import shlex
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


def build(length: str, fmt: str) -> tuple[Path, Path]:
    """The cached log and its config (made with the simulator's writer)."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import write_imu_log
    from imucal_cli.sim import DriveOptions, simulate_drive

    CACHE.mkdir(exist_ok=True)
    stem = CACHE / f"town_{length}_{fmt}"
    log = stem.with_name(stem.name + SUFFIX[fmt])
    config = stem.with_name(stem.name + ".config.yaml")
    if log.exists() and config.exists():
        return log, config
    start = time.perf_counter()
    drive = simulate_drive(
        DriveOptions(scenario="urban", duration_s=LENGTHS[length], seed=1, sensors=4, lidar_rate_hz=200.0)
    )
    write_imu_log(log, fmt, drive.topics())
    write_document(config, drive.config_document())
    write_document(stem.with_name(stem.name + ".truth.yaml"), drive.truth_document())
    print(f"built {log.name} in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return log, config


def floor(log: Path, fmt: str) -> float:
    """Seconds to read and decompress the storage, decoding nothing."""
    from imucal_cli.io.fastimu import McapChunks, Ros1Bag

    start = time.perf_counter()
    if fmt == "mcap":
        with log.open("rb") as handle:
            chunks = McapChunks(handle)
            assert chunks.summary is not None
            for ci in chunks.summary.chunk_indexes:
                chunks.read_chunk(ci)
    elif fmt == "rosbag2-sqlite3":
        for db in sorted(log.glob("*.db3")):
            connection = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            cursor = connection.execute("SELECT timestamp, data FROM messages")
            while cursor.fetchmany(65536):
                pass
            connection.close()
    else:
        import lz4.frame

        with log.open("rb") as handle:
            bag = Ros1Bag(handle)
            from imucal_cli.io.fastimu import _ros1_header

            for pos in bag.chunk_positions:
                handle.seek(pos)
                head = handle.read(4096)
                fields, p = _ros1_header(head, 0)
                (size,) = np.frombuffer(head[p : p + 4], "<u4")
                handle.seek(pos + p + 4)
                data = handle.read(int(size))
                if fields["compression"] == b"lz4":
                    lz4.frame.decompress(data)
    return time.perf_counter() - start


def file_read(log: Path) -> float:
    """Seconds to read the storage files' bytes (sqlite3 pages are not compressed)."""
    start = time.perf_counter()
    for db in sorted(log.glob("*.db3")):
        with db.open("rb", buffering=0) as handle:
            while handle.read(8 << 20):
                pass
    return time.perf_counter() - start


def decode(log: Path, topics: list[str], fast: bool) -> tuple[float, int]:
    from imucal_cli.io.logs import read_imu

    start = time.perf_counter()
    reads = read_imu(log, topics, fast=fast)
    return time.perf_counter() - start, sum(r.stats.messages for r in reads.values())


CHILD = """
import os, resource, sys, threading, time
peaks = {}  # per child process: the highest VmHWM (its own peak RSS, kB) seen
together = [0]  # the highest sum of VmRSS of this process and its children at one instant (kB)
cpu = {}  # per child process, in the order they appeared: its CPU seconds (user + system) so far
def status(pid, key):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(key):
            return int(line.split()[1])
    return 0
def cpu_s(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
def watch():
    me = os.getpid()
    while True:
        try:
            kids = [int(k) for k in open(f"/proc/{me}/task/{me}/children").read().split()]
        except OSError:
            kids = []
        now = status(me, "VmRSS:")
        for kid in kids:
            try:
                peaks[kid] = max(peaks.get(kid, 0), status(kid, "VmHWM:"))
                now += status(kid, "VmRSS:")
                cpu[kid] = cpu_s(kid)
            except OSError:
                pass
        together[0] = max(together[0], now)
        time.sleep(0.01)
threading.Thread(target=watch, daemon=True).start()
from imucal_cli import launch
launch.begin(sys.argv[1:])  # as the imucal command starts: the log's reader first
from imucal_cli.cli import app
try:
    app(sys.argv[1:])
except SystemExit as exc:
    if exc.code:
        raise
own = resource.getrusage(resource.RUSAGE_SELF)
summed = own.ru_maxrss + sum(peaks.values())
children = list(cpu.values()) + [0.0, 0.0]  # the log reader forked first, then the math worker
with open(sys.argv[-1] + ".rss", "w") as stats:
    print(max(together[0], own.ru_maxrss), summed, own.ru_utime + own.ru_stime, children[0], sum(children[1:]), file=stats)
from imucal_cli.cli import _end
_end(0)  # as the imucal command ends
"""


def errors(config: Path) -> tuple[float, float]:
    """Largest rotation (deg, paper eq. 21) and translation (m) error of ``T_base_lidar`` over
    the sensors of the last ``calibrate`` run, against the simulator's truth beside ``config``."""
    import json

    import yaml
    from scipy.spatial.transform import Rotation

    from imucal_cli.core.so3 import rotation_angle_deg

    estimate = json.loads((CACHE / "estimate.json").read_text())["sensors"]
    truth = yaml.safe_load(config.with_name(config.name.replace(".config.yaml", ".truth.yaml")).read_text())["sensors"]
    worst_r = worst_t = 0.0
    for name, sensor in estimate.items():
        est, ref = sensor["T_base_lidar"], truth[name]["T_base_lidar"]
        worst_r = max(worst_r, rotation_angle_deg(Rotation.from_quat(ref["rotation"]), Rotation.from_quat(est["rotation"])))
        worst_t = max(worst_t, float(np.linalg.norm(np.subtract(est["translation"], ref["translation"]))))
    return worst_r, worst_t


def calibrate(log: Path, config: Path) -> tuple[float, float, float, tuple[float, float, float]]:
    """Wall seconds, peak RSS together and the sum of the processes' peaks (MB) of ``imucal
    calibrate`` in a fresh process (see the module's docstring), and the CPU seconds of its
    main process, its log reader and its math worker.

    It is started through a shell that does not ``exec`` it, so it is not forked from this
    (large) process: Linux keeps a process's pre-``exec`` peak.
    """
    out = CACHE / "estimate.json"
    command = " ".join(
        shlex.quote(part)
        for part in [sys.executable, "-c", CHILD, "calibrate", str(log), "-c", str(config), "-o", str(out)]
    )
    start = time.perf_counter()
    subprocess.run(["/bin/sh", "-c", f"{command}; true"], check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    together_kb, summed_kb, *cpu = (float(v) for v in Path(str(out) + ".rss").read_text().split())
    return wall, together_kb / 1024.0, summed_kb / 1024.0, (cpu[0], cpu[1], cpu[2])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", nargs="+", default=["15m", "1h", "4h"], choices=list(LENGTHS))
    parser.add_argument("--formats", nargs="+", default=list(SUFFIX), choices=list(SUFFIX))
    parser.add_argument("--four-hour-formats", nargs="+", default=["mcap"], choices=list(SUFFIX))
    parser.add_argument("--naive-max-minutes", type=float, default=60.0)
    parser.add_argument("--repeat", type=int, default=5, help="runs of floor and decode (the fastest is reported)")
    parser.add_argument("--calibrate-repeat", type=int, default=5, help="runs of calibrate, taking turns with floor and decode (the fastest time and the largest peak RSS are reported)")
    args = parser.parse_args()
    from imucal_cli.parallel import reuse_freed_memory

    reuse_freed_memory()  # floor and decode run here with the allocator set as `imucal` sets it
    from imucal_cli.config import load_config

    rows = []
    fetches = []
    for length in args.lengths:
        for fmt in args.formats:
            if length == "4h" and fmt not in args.four_hour_formats:
                continue
            log, config_path = build(length, fmt)
            config = load_config(config_path)
            topics = [config.base.topic] + [s.imu_topic for s in config.sensors]
            # floor, decode and calibrate take turns, so that all three see the machine in the
            # same moods (its speed drifts by tens of per cent over minutes)
            floors, fast_runs, runs = [], [], []
            for turn in range(max(args.repeat, args.calibrate_repeat)):
                if turn < args.repeat:
                    floors.append(floor(log, fmt))
                    fast_runs.append(decode(log, topics, fast=True))
                if turn < args.calibrate_repeat:
                    runs.append(calibrate(log, config_path))
            t_floor = min(floors)
            t_fast, count = min(fast_runs)
            t_naive = None
            if LENGTHS[length] / 60.0 <= args.naive_max_minutes:
                t_naive, _ = decode(log, topics, fast=False)
            fastest = min(runs, key=lambda run: run[0])
            wall, cpu = fastest[0], fastest[3]
            rss, summed = max(run[1] for run in runs), max(run[2] for run in runs)  # the worst
            worst_r, worst_t = errors(config_path)
            size = sum(p.stat().st_size for p in ([log] if log.is_file() else log.iterdir()))
            if fmt == "rosbag2-sqlite3":
                fetches.append((length, min(file_read(log) for _ in range(args.repeat)), t_fast))
            rows.append((length, fmt, count, size, t_floor, t_fast, t_naive, wall, cpu, rss, summed, worst_r, worst_t))
            print(f"measured {length} {fmt}", file=sys.stderr)

    print("| length | format | messages | size MB | floor s | decode s | decode / floor | decode msg/s | naive s | naive / decode | calibrate s | calibrate / floor | calibrate CPU s (main + reader + math) | peak RSS MB | sum of peaks MB | max dR deg | max abs dt m |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for length, fmt, count, size, t_floor, t_fast, t_naive, wall, cpu, rss, summed, worst_r, worst_t in rows:
        naive = f"{t_naive:.1f} | {t_naive / t_fast:.0f}x" if t_naive is not None else "- | -"
        print(
            f"| {length} | {fmt} | {count:,} | {size / 1e6:.0f} | {t_floor:.2f} | {t_fast:.2f} | {t_fast / t_floor:.2f} | "
            f"{count / t_fast / 1e6:.2f} M | {naive} | {wall:.1f} | {wall / t_floor:.1f} | "
            f"{sum(cpu):.1f} ({cpu[0]:.1f} + {cpu[1]:.1f} + {cpu[2]:.1f}) | {rss:.0f} | {summed:.0f} | {worst_r:.4f} | {worst_t:.4f} |"
        )

    for length, t_read, t_fast in fetches:
        print(f"\n{length} rosbag2-sqlite3: reading the file's bytes {t_read:.2f} s; decode / that = {t_fast / t_read:.1f}")

    measured = {(row[0], row[1]): row for row in rows}
    print_scaling(measured)
    print_checks(measured)


def print_scaling(measured: dict[tuple[str, str], tuple]) -> None:
    """Per format measured at several lengths, for each two consecutive lengths:
    ``calibrate``'s wall time and peak RSS of the longer log against the shorter's, and the
    wall time each hour added between them costs (linear in length: the same cost per added
    hour whatever the length; the ratio of wall times also carries the fixed start-up, which a
    longer log spreads thinner)."""
    lines = []
    for fmt in SUFFIX:
        lengths = [length for length in LENGTHS if (length, fmt) in measured]
        for shorter, longer in zip(lengths, lengths[1:]):
            short, long_ = measured[(shorter, fmt)], measured[(longer, fmt)]
            hours_s, hours_l = LENGTHS[shorter] / 3600.0, LENGTHS[longer] / 3600.0
            scale = hours_l / hours_s
            per_hour_l = (long_[7] - short[7]) / (hours_l - hours_s)
            per_hour_s = short[7] / hours_s
            lines.append(
                f"| {fmt} | {shorter} -> {longer} | {short[7]:.2f} -> {long_[7]:.2f} | {long_[7] / (scale * short[7]):.2f} | "
                f"{per_hour_s:.2f} | {per_hour_l:.2f} | {short[9]:.0f} -> {long_[9]:.0f} | {long_[9] / short[9]:.2f} |"
            )
    if lines:
        print("\n| format | lengths | calibrate s | longer / (scale x shorter) | s per hour, shorter (incl. start-up) | s per hour added | peak RSS MB | RSS longer / shorter |")
        print("|---|---|---|---|---|---|---|---|")
        print("\n".join(lines))


def print_checks(measured: dict[tuple[str, str], tuple]) -> None:
    """The figures of issue 4's "must show", each against its bound, from this run."""
    checks = []
    for (length, fmt), row in measured.items():
        t_floor, t_fast, t_naive = row[4], row[5], row[6]
        bound = 1.5 if fmt == "mcap" else 3.0
        checks.append((f"{length} {fmt} decode / floor", t_fast / t_floor, f"<= {bound}", t_fast / t_floor <= bound))
        if t_naive is not None:
            checks.append((f"{length} {fmt} naive / decode", t_naive / t_fast, ">= 10", t_naive / t_fast >= 10.0))
    if ("1h", "mcap") in measured:
        row = measured[("1h", "mcap")]
        checks.append(("1h mcap calibrate / floor", row[7] / row[4], "<= 3", row[7] / row[4] <= 3.0))
        checks.append(("1h mcap calibrate peak RSS MB", row[9], "<= 1000", row[9] <= 1000.0))
    hours = {length: seconds / 3600.0 for length, seconds in LENGTHS.items()}
    for fmt in SUFFIX:
        if ("1h", fmt) in measured and ("4h", fmt) in measured:
            one, four = measured[("1h", fmt)], measured[("4h", fmt)]
            rss = four[9] / one[9]
            checks.append((f"4h / 1h {fmt} peak RSS", rss, "within 20%", abs(rss - 1.0) <= 0.2))
            wall = four[7] / (hours["4h"] / hours["1h"] * one[7])
            checks.append((f"4h / (4 x 1h) {fmt} calibrate wall (start-up counted 4 times)", wall, "within 20%", abs(wall - 1.0) <= 0.2))
            if ("15m", fmt) in measured:  # the line through 15 min and 1 h, carried on to 4 h
                quarter = measured[("15m", fmt)]
                line = one[7] + (hours["4h"] - hours["1h"]) * (one[7] - quarter[7]) / (hours["1h"] - hours["15m"])
                checks.append((f"4h {fmt} calibrate wall / the line through 15m and 1h", four[7] / line, "within 20%", abs(four[7] / line - 1.0) <= 0.2))
    if checks:
        print("\n| must show (issue 4) | measured | bound | met |")
        print("|---|---|---|---|")
        for name, value, bound, met in checks:
            shown = f"{value:.0f}" if name.endswith("MB") else f"{value:.2f}"
            print(f"| {name} | {shown} | {bound} | {'yes' if met else 'NO'} |")


if __name__ == "__main__":
    main()
