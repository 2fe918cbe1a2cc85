"""Follow-mode latency: a five-IMU drive recorded in real time, followed as it is written.

The recorder (tests/recorder.py) writes one base IMU at 100 Hz and four lidar IMUs at 200 Hz
into an MCAP file at real time (64 KiB chunks, flushed). The follower (``api.follow``) runs
beside it. For each window, the latency is from the moment the recorder wrote the last message
the window needs (its end, plus the padding and the clock-offset margin the reduction needs, on
every topic: the method's filter padding and clock margin; the wait for stragglers counts as
latency) to the moment the updated estimate was ready. Windows reduced at the boot (the first
60 s of data, in one go) are shown apart. Prints a markdown table.

Run: ``python benchmarks/follow_latency.py [--minutes 5] [--factor 1]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))


def main() -> None:
    from recorder import Recorder

    from imucal_cli.api import follow
    from imucal_cli.core.streaming import PAD_S
    from imucal_cli.sim import DriveOptions, simulate_drive

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument(
        "--factor", type=float, default=1.0, help="times real time the recorder writes at"
    )
    args = parser.parse_args()
    drive = simulate_drive(
        DriveOptions(
            scenario="urban", duration_s=60 * args.minutes, seed=5, sensors=4, lidar_rate_hz=200.0
        )
    )
    config = drive.config()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "live.mcap"
        recorder = Recorder(path, drive.topics(), args.factor)
        recorder.start()
        recorder.started_writing.wait(30)
        start_wall = time.monotonic()
        updates: list[tuple[float, int]] = []
        run, _ = follow(
            path,
            config,
            on_window=lambda calibration, windows: updates.append((time.monotonic(), windows)),
        )
        recorder.join()
    # the recorder writes log time t at wall time start + (t - t0) / factor: a window k (grid
    # clock) is complete once every topic reached its end + PAD_S + max_offset
    t_ref = (run.t_ref_ns - run.t0_ns) * 1e-9
    window_s = config.segments.window_s
    margin = PAD_S + config.calibration.max_time_offset_s
    latencies = []
    seen = 0
    for wall, windows in updates:
        for k in range(seen, windows):
            grid_start = run.windows[next(iter(run.windows))][0].start_s  # the grid's origin
            needed = t_ref + grid_start + (k + 1) * window_s + margin
            ready = start_wall + needed / args.factor
            latencies.append(wall - ready)
        seen = windows
    lat = np.array(latencies)
    # windows reduced at the boot (60 s of data in one go) wait for it by design: shown apart
    boot_windows = updates[0][1] if updates else 0
    after = lat[boot_windows:]
    print(
        "| recording | windows | updates | latency median s (after boot) | latency worst s (after "
        "boot) | first estimate after s of log |"
    )
    print("|---|---|---|---|---|---|")
    first = (updates[0][0] - start_wall) * args.factor if updates else float("nan")
    print(
        f"| {args.minutes:g} min, 5 IMUs, {args.factor:g}x real time | {seen} | {len(updates)} | "
        f"{np.median(after):.3f} | {np.max(after):.3f} | {first:.1f} |"
    )


if __name__ == "__main__":
    main()
