"""Peak memory of every command on a day-long log against an hour's; prints a markdown table
(docs/performance.md).

The log is the rig of ``throughput.py`` (a base IMU at 100 Hz, four lidar IMUs at 200 Hz: 900
messages a second) driving one simulated hour in town, repeated ``--hours`` times end to end
(stamps and log times moved on by an hour each time: 78 million messages, 4 GB for a day).
Each command runs in a fresh process on the one-hour log and on the ``--hours`` log; its peak
RSS is ``ru_maxrss`` of that process, reaped by a small launcher (a process started from this
one would count this one's memory). The hour repeated is the same noise each hour: the statuses
of the long log say nothing (24 hours of identical residuals look like a model error).

Run: ``python benchmarks/daylong.py [--hours 24]`` (cached in ``benchmarks/.cache``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache"
MEASURE = """
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, code)
"""


def build(hours: int) -> tuple[Path, Path]:
    from mcap.writer import CompressionType, Writer

    from imucal_cli.documents import write_document
    from imucal_cli.io.imu_msg import IMU_MSGTYPE
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.serialize import serialize_cdr
    from imucal_cli.sim.writers import _merged, _msgdef

    CACHE.mkdir(exist_ok=True)
    log, config = (
        CACHE / f"town_{hours}h_repeated.mcap",
        CACHE / f"town_{hours}h_repeated.config.yaml",
    )
    if log.exists() and config.exists():
        return log, config
    start = time.perf_counter()
    drive = simulate_drive(
        DriveOptions(scenario="urban", duration_s=3600.0, seed=1, sensors=4, lidar_rate_hz=200.0)
    )
    topics = drive.topics()
    # CDR: header.stamp.sec is bytes 4-8 of each message
    blobs = {topic: serialize_cdr(data.stream) for topic, data in topics.items()}
    order = list(_merged(topics))
    msgdef, _ = _msgdef(False)
    partial = log.with_suffix(".partial")
    with partial.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        writer.start(profile="ros2", library="imucal benchmark")
        schema = writer.register_schema(name=IMU_MSGTYPE, encoding="ros2msg", data=msgdef.encode())
        channels = {
            t: writer.register_channel(topic=t, message_encoding="cdr", schema_id=schema)
            for t in topics
        }
        sequence = dict.fromkeys(topics, 0)
        for hour in range(hours):
            shifted = {}
            for topic, data in blobs.items():
                moved = data.copy()
                sec = moved[:, 4:8].copy().view("<i4")
                moved[:, 4:8] = (sec + 3600 * hour).view(np.uint8)
                shifted[topic] = moved
            for log_ns, topic, i in order:
                t = log_ns + hour * 3_600_000_000_000
                writer.add_message(
                    channel_id=channels[topic],
                    log_time=t,
                    data=shifted[topic][i].tobytes(),
                    publish_time=t,
                    sequence=sequence[topic],
                )
                sequence[topic] += 1
            print(
                f"hour {hour + 1} of {hours} written ({time.perf_counter() - start:.0f} s)",
                file=sys.stderr,
            )
        writer.finish()
    partial.rename(log)
    write_document(config, drive.config_document())
    return log, config


def _measure(command: str, log: Path, config: Path) -> tuple[float, float, int]:
    """Wall time (s), peak RSS (MB) and exit code of one command in a fresh process."""
    argv = [sys.executable, "-m", "imucal_cli.cli", command, str(log)] + (
        [] if command == "inspect" else ["-c", str(config)]
    )
    wall, rss_kb, code = subprocess.run(
        [sys.executable, "-c", MEASURE, *argv], capture_output=True, text=True, check=True
    ).stdout.split()
    return float(wall), int(rss_kb) / 1024, int(code)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=int, default=24)
    args = parser.parse_args()
    hour, day = build(1), build(args.hours)
    size = day[0].stat().st_size / 1e6
    print(
        f"## Day-long log: {args.hours} h, {size:,.0f} MB, {args.hours * 3_237_168:,} messages "
        "(about), against its first hour\n"
    )
    print(
        f"| command | 1 h wall s | 1 h peak RSS MB | {args.hours} h wall s "
        f"| {args.hours} h peak RSS MB | peak ratio | exit |"
    )
    print("|---|---|---|---|---|---|---|")
    for command in ("inspect", "biases", "segments", "calibrate"):
        wall_1, rss_1, code_1 = _measure(command, *hour)
        wall_n, rss_n, code_n = _measure(command, *day)
        print(
            f"| {command} | {wall_1:.1f} | {rss_1:.0f} | {wall_n:.1f} | {rss_n:.0f} "
            f"| {rss_n / rss_1:.2f} | {code_1}, {code_n} |"
        )
        sys.stdout.flush()


if __name__ == "__main__":
    main()
