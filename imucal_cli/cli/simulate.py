"""``simulate``: a drive with its truth and config, for trying the tool and for tests."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from imucal_cli.cli import options, render
from imucal_cli.cli.app import PANEL_SIM, command
from imucal_cli.io.formats import FORMATS

SCENARIOS = ("aggressive", "urban", "highway", "parking", "stationary")  # (not sim's: scipy)
Scenario = StrEnum("Scenario", {name: name for name in SCENARIOS})  # type: ignore[misc]
LogFormat = StrEnum("LogFormat", {name: name for name in FORMATS})  # type: ignore[misc]

Out = Annotated[
    Path,
    typer.Argument(
        help="Log to write (.mcap, .bag, or a rosbag2 directory name).",
        callback=options.output_path,
    ),
]
Duration = Annotated[
    float | None,
    typer.Option(help="Seconds (default: aggressive 81, urban 283, highway/parking 120).", min=1.0),
]
Format = Annotated[
    LogFormat | None,
    typer.Option(
        "--format",
        help="Log format (default: from OUT: .mcap -> mcap, .bag -> rosbag1, else "
        "rosbag2-sqlite3).",
    ),
]
TimeOffsets = Annotated[
    list[float] | None,
    typer.Option(
        "--time-offset-s",
        help="Clock offset of each lidar IMU (its stamp minus the base's), repeat per sensor; "
        "one value applies to all. Default: drawn in +-5 ms.",
    ),
]
Errors = Annotated[
    str,
    typer.Option(
        "--errors",
        help="Sensor or mount errors beyond the estimator's model: none, mems (scale factors, "
        "non-orthogonality, g-sensitivity, vibration), misaligned (gyro and accelerometer "
        "triads apart), tilting-mount, clock-offsets (+-40 ms), prior-off (0.5 m), accel-g, "
        "gyro-dps, ins-away (the base IMU turned and 1.6 m away, declared), clock-jitter "
        "(+-40 ms, 0.5 ms jitter, 1% drops, 200 Hz); consumer, industrial, tactical, "
        "navigation, mems-base (errors drawn from those grades), gyros-low (both gyros 10% low).",
    ),
]
LidarGrade = Annotated[
    str | None,
    typer.Option(
        help="Draw each lidar IMU's own errors from this grade (consumer, industrial, tactical, "
        "navigation, ideal) and declare it in the config (default: ideal, or the error class's).",
    ),
]
BaseGrade = Annotated[
    str | None,
    typer.Option(help="The same for the base IMU (default: ideal, or the error class's)."),
]
TfStatic = Annotated[
    bool,
    options.flag(
        "--tf-static",
        help="Write /tf_static: per lidar <name>/os_sensor at the CAD prior with the IMU's and "
        "the lidar's frames under it, and the base IMU's frame gnss_imu in base_link.",
    ),
]
Force = Annotated[
    bool,
    options.flag(
        "--force",
        help="Replace an existing OUT if it is a log (and the truth and config beside it).",
    ),
]


@command(PANEL_SIM)
def simulate(
    out: Out,
    scenario: Annotated[Scenario, typer.Option(help="Kind of drive.")] = Scenario["urban"],
    duration: Duration = None,
    seed: Annotated[int, typer.Option(help="Random seed: the same seed gives the same log.")] = 0,
    log_format: Format = None,
    sensors: Annotated[
        int, typer.Option("--sensors", help="Number of lidars (1-4).", min=1, max=4)
    ] = 2,
    noise_scale: Annotated[
        float,
        typer.Option(help="Multiplies every IMU error (0: ideal sensors, exact timing).", min=0.0),
    ] = 1.0,
    time_offset_s: TimeOffsets = None,
    lidar_rate_hz: Annotated[
        float | None, typer.Option(help="Rate of the lidar IMUs (default 100 Hz).", min=1.0)
    ] = None,
    errors: Errors = "none",
    lidar_grade: LidarGrade = None,
    base_grade: BaseGrade = None,
    tf_static: TfStatic = False,
    force: Force = False,
) -> None:
    """Simulate a drive: a log OUT with STEM.truth.yaml and STEM.config.yaml beside it."""
    from rich.text import Text

    from imucal_cli.sim import DriveOptions
    from imucal_cli.sim.files import simulate_files
    from imucal_cli.sim.writers import format_for

    fmt = format_for(out, log_format.value if log_format is not None else None)
    drive = DriveOptions(
        scenario=scenario.value,
        duration_s=duration,
        seed=seed,
        sensors=sensors,
        noise_scale=noise_scale,
        time_offsets_s=tuple(time_offset_s) if time_offset_s else None,
        lidar_rate_hz=lidar_rate_hz,
    )
    with render.progress(f"writing {out.name}") as progress:
        written = simulate_files(
            out, fmt, drive, errors, (lidar_grade, base_grade), tf_static, force, progress
        )
    counts = ", ".join(f"{topic} {count:,}" for topic, count in written.counts.items())
    shown = render.console()
    shown.print(
        Text.assemble((str(out), "bold"), f" ({fmt}, {scenario.value}, seed {seed}): {counts}")
    )
    shown.print(f"truth:  {written.truth}\nconfig: {written.config}")
