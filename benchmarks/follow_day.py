"""A day of following, honestly: what the status and std say as the hours add up; prints a
markdown table (docs/timeline.md).

One simulated drive of ``--hours`` of town driving (a base IMU and two lidar IMUs at 100 Hz,
their noise independent all along, unlike ``follow_week.py``'s repeated hour) is fed to the
follow mode's state (``pipeline._Follower``) in 10 s batches, with the caught-up step every
``--update-s`` of data. At each hour listed: each sensor's status, its largest std (rotation
deg, translation mm) and its error against the simulator's truth in std on each of its six
axes (rotation about the base axes, then translation), the largest of them in bold where the
status is ``ok`` and it is beyond 4. ``--clean`` takes the lidar IMUs' timestamp jitter,
dropped samples and quantisation and the base's float32 output out of the simulation;
``--no-walk`` every IMU's bias random walk (each keeps its turn-on bias), ``--still-base`` the
base IMU's alone (``--still-base gyro`` or ``accel``: that triad's alone); ``--keep-windows``
keeps every window its own unit of the fit, where the follow merges the older ones into
stretches past 400 (docs/method.md, step 3): slower, and memory that grows.

Run: ``python benchmarks/follow_day.py [--hours 24] [--seed 7] [--clean] [--no-walk]
[--still-base [gyro|accel]] [--keep-windows]``: about 6 GB of memory and 5 minutes for a day.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import numpy as np

from imucal_cli.core import streaming
from imucal_cli.pipeline import _Follower
from imucal_cli.sim import DriveOptions, simulate_drive

HOUR_NS = 3_600_000_000_000
SHOWN = (1, 2, 4, 8, 12, 16, 20, 24, 36, 48, 60, 72)


def options(
    hours: int, seed: int, clean: bool, no_walk: bool, still_base: str | None = None
) -> DriveOptions:
    drive = DriveOptions(scenario="urban", duration_s=hours * 3600.0, seed=seed, sensors=2)
    still = {"gyro_bias_random_walk": 0.0, "accel_bias_random_walk": 0.0}
    if no_walk or still_base:
        kept = {
            k: v
            for k, v in still.items()
            if no_walk or still_base == "both" or k.startswith(str(still_base))
        }
        drive = replace(drive, base_model=replace(drive.base_model, **kept))
    if no_walk:
        drive = replace(drive, lidar_model=replace(drive.lidar_model, **still))
    if not clean:
        return drive
    lidar = replace(drive.lidar_model, jitter_s=0.0, drop_fraction=0.0, gyro_lsb=0.0, accel_lsb=0.0)
    return replace(
        drive, lidar_model=lidar, base_model=replace(drive.base_model, float32_output=False)
    )


def rows(hour: int, drive: Any, result: Any) -> list[str]:
    """The table's rows of one hour: a sensor each."""
    out = []
    for mount in drive.mounts:
        estimate = result.estimates[mount.name]
        T = result.T_base_lidar(mount.name)
        rotation = (mount.T_base_lidar.rotation * T.rotation.inv()).as_rotvec()
        translation = T.translation - mount.T_base_lidar.translation
        cov = estimate.lidar_covariance(mount.T_imu_lidar)
        if cov is None:
            out.append(f"| {hour} | {mount.name} | {estimate.status} | - | - | - |")
            continue
        std = np.sqrt(np.diag(cov))
        normalized = np.concatenate([rotation, translation]) / std
        worst = float(np.abs(normalized).max())
        said = f"{worst:.2f}"
        if estimate.status == "ok" and worst > 4.0:
            said = f"**{said}**"
        axes = ", ".join(f"{v:+.2f}" for v in normalized)
        std_r, std_t = np.degrees(std[:3]).max(), 1000 * std[3:].max()
        out.append(
            f"| {hour} | {mount.name} | {estimate.status} | {std_r:.4f} / {std_t:.3f} "
            f"| {axes} | {said} |"
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=int, default=24)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--update-s", type=float, default=1800.0)
    parser.add_argument("--clean", action="store_true")
    parser.add_argument("--no-walk", action="store_true")
    parser.add_argument("--still-base", nargs="?", const="both", choices=["both", "gyro", "accel"])
    parser.add_argument("--keep-windows", action="store_true")
    args = parser.parse_args()
    if args.keep_windows:  # every window its own unit: nothing merged into stretches
        streaming.MAX_UNITS = streaming.FULL_WINDOWS = 1 << 30
    drive = simulate_drive(
        options(args.hours, args.seed, args.clean, args.no_walk, args.still_base)
    )
    streams = {"base": drive.streams().base, **drive.streams().sensors}
    state = _Follower(drive.config(), None, None, lambda: False, False)
    start = min(int(s.t_ns[0]) for s in streams.values())
    block, update = 10_000_000_000, int(args.update_s * 1e9)
    clean = ", no jitter, drops or quantisation" if args.clean else ""
    clean += ", biases that do not wander" if args.no_walk else ""
    if args.still_base and not args.no_walk:
        which = {"both": "biases", "gyro": "gyro's bias", "accel": "accelerometer's bias"}
        clean += f", a base whose {which[args.still_base]} does not wander"
    clean += ", every window kept" if args.keep_windows else ""
    print(
        f"## A day of following: {args.hours} h of town driving, seed {args.seed}{clean}\n\n"
        "| hours fed | sensor | status | largest std deg / mm | error / std (rx, ry, rz, tx, "
        "ty, tz) | largest |\n|---|---|---|---|---|---|"
    )
    for edge in range(start + block, start + args.hours * HOUR_NS + block, block):
        for name, stream in streams.items():
            a, b = np.searchsorted(stream.t_ns, [edge - block, edge])
            if b > a:
                state.sink(name, stream.t_ns[a:b], stream.gyro[a:b], stream.accel[a:b])
        if (edge - start) % update == 0:
            state.caught_up()
            hour = (edge - start) / HOUR_NS
            if hour in SHOWN and state.latest is not None:
                print("\n".join(rows(int(hour), drive, state.latest)), flush=True)


if __name__ == "__main__":
    main()
