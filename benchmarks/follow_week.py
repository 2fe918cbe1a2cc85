"""Memory of the follow mode fed a simulated week; prints a markdown table (docs/performance.md).

The follow loop's state (``pipeline._Follower``: the calibrator, the sink every message goes to
and the step the reader takes whenever it waits for the recording: the windows covered reduced,
every sensor solved and told) is fed in this process from memory, faster than real time: one
simulated hour of town driving (a base IMU and ``--sensors`` lidar IMUs at 100 Hz), its stamps
moved on by an hour each time, in 10 s batches, with the caught-up step every ``--update-s`` of
data. The table: the process's resident memory (VmRSS, now, not the peak)
after each of the hours listed, the windows it keeps per sensor, the CPU seconds per hour
fed since the previous row, and each sensor's status then (the same noise every hour: what
a real week would not repeat becomes significant as the hours add up).

Run: ``python benchmarks/follow_week.py [--hours 168] [--update-s 1800]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from imucal_cli.pipeline import _Follower
from imucal_cli.sim import DriveOptions, simulate_drive

HOUR_NS = 3_600_000_000_000


def rss_mb() -> float:
    """This process's resident memory now (MB)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=int, default=168)
    parser.add_argument("--sensors", type=int, default=2)
    parser.add_argument("--update-s", type=float, default=1800.0)
    args = parser.parse_args()
    drive = simulate_drive(
        DriveOptions(scenario="urban", duration_s=3600.0, seed=2, sensors=args.sensors)
    )
    streams = {"base": drive.streams().base, **drive.streams().sensors}
    state = _Follower(drive.config(), None, None, lambda: False, False)
    start = min(int(s.t_ns[0]) for s in streams.values())
    block, update = 10_000_000_000, int(args.update_s * 1e9)
    shown = {1, 2, 4, 8, 12, 24, 48, 72, 96, 120, 144, 168, args.hours}
    print(
        f"## Follow fed {args.hours} h ({args.sensors} lidar IMUs and the base at 100 Hz, "
        f"an update every {args.update_s:g} s of data)\n\nBefore feeding (the simulated hour "
        f"held in memory, modules loaded): {rss_mb():.0f} MB.\n"
    )
    print(
        "| hours fed | RSS MB | windows reduced | units kept per sensor | CPU s per hour "
        "| statuses |"
    )
    print("|---|---|---|---|---|---|")
    cpu, last_hour = time.process_time(), 0
    for hour in range(args.hours):
        shifted = {name: s.t_ns + hour * HOUR_NS for name, s in streams.items()}
        for edge in range(start + block, start + HOUR_NS + block, block):
            for name, stream in streams.items():
                t = shifted[name]
                a, b = np.searchsorted(t, [edge - block + hour * HOUR_NS, edge + hour * HOUR_NS])
                if b > a:
                    state.sink(name, t[a:b], stream.gyro[a:b], stream.accel[a:b])
            if (edge - start) % update == 0:
                state.caught_up()
        if hour + 1 in shown:
            now = time.process_time()
            units = max(len(w) for w in state.calibrator.windows.values())
            latest = state.latest
            statuses = ", ".join(e.status for e in latest.estimates.values()) if latest else "-"
            print(
                f"| {hour + 1} | {rss_mb():.0f} | {state.calibrator.reduced} | {units} "
                f"| {(now - cpu) / (hour + 1 - last_hour):.1f} | {statuses} |",
                flush=True,
            )
            cpu, last_hour = now, hour + 1


if __name__ == "__main__":
    main()
