"""The ``imucal`` command line: parse arguments -> load config -> read log -> compute -> write.

Every :class:`ImucalError` becomes one line on stderr and exit code 2, with no traceback and no
partial output file. Heavy imports happen inside the commands so ``imucal --help`` is quick.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import typer

from imucal_cli import __version__
from imucal_cli.errors import ImucalError, InputError

P = ParamSpec("P")
R = TypeVar("R")

app = typer.Typer(
    name="imucal",
    help="Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

EXIT_OK, EXIT_CHECK_FAILED, EXIT_BAD_INPUT = 0, 1, 2

LOG_HELP = "Log: a .mcap file, a rosbag2 directory (sqlite3 or mcap storage) or a ROS 1 .bag."
PANEL_LOGS = "Logs"
PANEL_SIM = "Simulation"
PANEL_CONFIG = "Configuration"


class Scenario(StrEnum):
    aggressive = "aggressive"
    urban = "urban"
    highway = "highway"
    parking = "parking"


class LogFormat(StrEnum):
    mcap = "mcap"
    mcap_ros1 = "mcap-ros1"
    rosbag2_sqlite3 = "rosbag2-sqlite3"
    rosbag2_mcap = "rosbag2-mcap"
    rosbag1 = "rosbag1"


def _version(value: bool) -> None:
    if value:
        typer.echo(f"imucal {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
) -> None:
    """Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone."""


# --------------------------------------------------------------------------- output helpers


def handles_errors(command: Callable[P, R]) -> Callable[P, R]:
    """Turn :class:`ImucalError` into one line on stderr and exit 2 (no traceback)."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except ImucalError as exc:
            typer.echo(f"imucal: error: {exc}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt:
            typer.echo("imucal: interrupted", err=True)
            raise typer.Exit(130) from None

    return wrapper


def _stdout_console() -> Any:
    from rich.console import Console

    # Piped output is read by people too: do not squeeze tables into 80 columns.
    return Console(highlight=False, width=None if sys.stdout.isatty() else 160)


@contextmanager
def _progress(description: str) -> Iterator[Any]:
    """A spinner with a counter on stderr when it is a terminal; nothing otherwise."""
    if not sys.stderr.isatty():
        yield lambda count: None
        return
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TextColumn("{task.completed:>10,.0f} messages"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as progress:
        task = progress.add_task(description, total=None)
        yield lambda count: progress.update(task, completed=count)


def _emit(document: dict[str, Any], out: Path | None, as_json: bool, render: Any) -> None:
    """Write ``document`` to ``out`` (YAML/JSON by suffix), or print JSON, or render it."""
    from imucal_cli.io.reports import dumps, write_document

    if out is not None:
        write_document(out, document)
    elif as_json:
        typer.echo(dumps(document, as_json=True), nl=False)
    else:
        render(document)


def _check_output(out: Path | None) -> None:
    """Fail early (before any work) on an output path that cannot be written."""
    if out is None:
        return
    if out.suffix.lower() not in {".yaml", ".yml", ".json"}:
        raise InputError(f"{out}: output must end in .yaml, .yml or .json")
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")


# --------------------------------------------------------------------------- inspect


def _inspect_document(summary: Any) -> dict[str, Any]:
    return {
        "log": summary.path,
        "format": summary.format_name,
        "t0_ns": summary.t0_ns,
        "topics": {
            t.topic: {
                "type": t.msgtype,
                "count": t.count,
                "rate_hz": round(t.rate_hz, 6),
                "duration_s": round(t.duration_s, 6),
                "gaps": [[round(a, 6), round(b, 6)] for a, b in t.gaps],
                "backwards": t.backwards,
                "duplicates": t.duplicates,
                "time_source": t.time_source,
            }
            for t in summary.topics
        },
    }


def _render_inspect(document: dict[str, Any]) -> None:
    from rich.table import Table

    table = Table(title=f"{document['log']} ({document['format']}), t0_ns = {document['t0_ns']}")
    for column in ("topic", "type", "count", "rate Hz", "duration s", "gaps", "backwards", "duplicates"):
        left = column in ("topic", "type")
        table.add_column(column, justify="left" if left else "right", no_wrap=left)
    for topic, info in document["topics"].items():
        gaps = info["gaps"]
        gap_text = str(len(gaps)) if len(gaps) > 3 else ", ".join(f"{a:.2f}-{b:.2f}" for a, b in gaps) or "0"
        table.add_row(
            topic,
            info["type"],
            f"{info['count']:,}",
            f"{info['rate_hz']:.2f}",
            f"{info['duration_s']:.2f}",
            gap_text,
            str(info["backwards"]),
            str(info["duplicates"]),
        )
    _stdout_console().print(table)


@app.command(rich_help_panel=PANEL_LOGS)
@handles_errors
def inspect(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    out: Annotated[Path | None, typer.Option("-o", "--out", help="Write YAML (.yaml) or JSON (.json).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """Topics, message types, counts, rates, duration, gaps and time jumps of a log."""
    from imucal_cli.io.logs import summarize_log

    _check_output(out)
    summary = summarize_log(log)
    _emit(_inspect_document(summary), out, as_json, _render_inspect)


# --------------------------------------------------------------------------- config


@app.command("check-config", rich_help_panel=PANEL_CONFIG)
@handles_errors
def check_config(
    config: Annotated[Path, typer.Argument(help="Calibration config (YAML).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of YAML.")] = False,
) -> None:
    """Validate a config and print it with every default filled in."""
    from imucal_cli.config import load_config
    from imucal_cli.io.reports import dumps

    typer.echo(dumps(load_config(config).to_dict(), as_json=as_json), nl=False)


# --------------------------------------------------------------------------- simulate


def _stem(out: Path) -> Path:
    """OUT without ``.mcap``/``.bag``: the prefix of the truth and config files."""
    if out.suffix.lower() in {".mcap", ".bag"}:
        return out.with_suffix("")
    return out


def _infer_format(out: Path) -> str:
    suffix = out.suffix.lower()
    if suffix == ".mcap":
        return "mcap"
    if suffix == ".bag":
        return "rosbag1"
    return "rosbag2-sqlite3"


@app.command(rich_help_panel=PANEL_SIM)
@handles_errors
def simulate(
    out: Annotated[Path, typer.Argument(help="Log to write (.mcap, .bag, or a rosbag2 directory name).")],
    scenario: Annotated[Scenario, typer.Option(help="Kind of drive.")] = Scenario.urban,
    duration: Annotated[
        float | None, typer.Option(help="Seconds (default: aggressive 81, urban 283, highway/parking 120).", min=1.0)
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed: the same seed gives the same log.")] = 0,
    log_format: Annotated[
        LogFormat | None,
        typer.Option("--format", help="Log format (default: from OUT: .mcap -> mcap, .bag -> rosbag1, else rosbag2-sqlite3)."),
    ] = None,
    sensors: Annotated[int, typer.Option("--sensors", help="Number of lidars (1-4).", min=1, max=4)] = 2,
    noise_scale: Annotated[
        float, typer.Option(help="Multiplies every IMU error (0: ideal sensors, exact timing).", min=0.0)
    ] = 1.0,
    time_offset_s: Annotated[
        list[float] | None,
        typer.Option(
            "--time-offset-s",
            help="Clock offset of each lidar IMU (its stamp minus the base's), repeat per sensor; "
            "one value applies to all. Default: drawn in +-5 ms.",
        ),
    ] = None,
    lidar_rate_hz: Annotated[
        float | None, typer.Option(help="Rate of the lidar IMUs (default 100 Hz).", min=1.0)
    ] = None,
) -> None:
    """Simulate a drive: a log OUT with STEM.truth.yaml and STEM.config.yaml beside it."""
    from imucal_cli.io.reports import write_document
    from imucal_cli.io.writers import write_imu_log
    from imucal_cli.sim import DriveOptions, simulate_drive

    fmt = log_format.value if log_format is not None else _infer_format(out)
    suffix = out.suffix.lower()
    expected = {"mcap": ".mcap", "mcap-ros1": ".mcap", "rosbag1": ".bag"}.get(fmt)
    if expected is not None and suffix != expected:
        raise InputError(f"{out}: format {fmt} writes a {expected} file; name OUT with that suffix")
    if expected is None and suffix in {".mcap", ".bag"}:
        raise InputError(f"{out}: format {fmt} writes a rosbag2 directory; name OUT without {suffix}")
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")
    options = DriveOptions(
        scenario=scenario.value,
        duration_s=duration,
        seed=seed,
        sensors=sensors,
        noise_scale=noise_scale,
        time_offsets_s=tuple(time_offset_s) if time_offset_s else None,
        lidar_rate_hz=lidar_rate_hz,
    )
    try:
        drive = simulate_drive(options)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    stem = _stem(out)
    truth_path = stem.with_name(stem.name + ".truth.yaml")
    config_path = stem.with_name(stem.name + ".config.yaml")
    with _progress(f"writing {out}"):
        write_imu_log(out, fmt, drive.topics())
    write_document(truth_path, drive.truth_document())
    write_document(config_path, drive.config_document())
    counts = {topic: len(data.stream) for topic, data in drive.topics().items()}
    console = _stdout_console()
    console.print(f"[bold]{out}[/bold] ({fmt}, {scenario.value}, seed {seed}): " + ", ".join(
        f"{topic} {count:,}" for topic, count in counts.items()
    ))
    console.print(f"truth:  {truth_path}\nconfig: {config_path}")


# --------------------------------------------------------------------------- entry point


def main() -> None:
    """Console-script entry point (usage errors exit 2, as Typer does)."""
    app()


if __name__ == "__main__":
    main()
