"""The ``imucal`` command line: parse arguments -> load config -> read log -> compute -> write.

Every :class:`ImucalError` becomes one line on stderr and exit code 2, with no traceback and no
partial output file. Heavy imports happen inside the commands so ``imucal --help`` is quick.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import typer

from imucal_cli.errors import ImucalError, InputError, Terminated
from imucal_cli.names import printable
from imucal_cli.version import version

P = ParamSpec("P")
R = TypeVar("R")


def _flag(option: Any) -> Any:
    """The help option shown as the flag it is: no ``<bool>`` (Typer 0.29 gives its own
    ``--help`` a type; this program's flags have ``metavar=""``)."""
    if option is not None:
        option.metavar = ""
    return option


class _Command(typer.core.TyperCommand):
    def get_help_option(self, ctx: Any) -> Any:
        return _flag(super().get_help_option(ctx))


class _Group(typer.core.TyperGroup):
    def get_help_option(self, ctx: Any) -> Any:
        return _flag(super().get_help_option(ctx))


app = typer.Typer(
    cls=_Group,
    name="imucal",
    help="Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

EXIT_OK, EXIT_CHECK_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143

LOG_HELP = "Log: a .mcap file, a rosbag2 directory (sqlite3 or mcap storage) or a ROS 1 .bag."
PANEL_LOGS = "Logs"
PANEL_SIM = "Simulation"
PANEL_CONFIG = "Configuration"


class Scenario(StrEnum):
    aggressive = "aggressive"
    urban = "urban"
    highway = "highway"
    parking = "parking"
    stationary = "stationary"


class LogFormat(StrEnum):
    mcap = "mcap"
    mcap_ros1 = "mcap-ros1"
    rosbag2_sqlite3 = "rosbag2-sqlite3"
    rosbag2_mcap = "rosbag2-mcap"
    rosbag1 = "rosbag1"


def _version(value: bool) -> None:
    if value:
        typer.echo(f"imucal {version()}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", metavar="", callback=_version, is_eager=True, help="Print the version."
        ),
    ] = False,
) -> None:
    """Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone."""


# --------------------------------------------------------------------------- output helpers


def _err(text: str) -> None:
    """One line on stderr, control characters shown as escapes: what a log or config names
    (topics, frames, paths) can never move the cursor, retitle the terminal or fake a line."""
    typer.echo(printable(text), err=True)


class _Process:
    """What :func:`main` made of this process."""

    #: A SIGTERM came (:func:`_terminate`).
    terminated = False


def handles_errors(command: Callable[P, R]) -> Callable[P, R]:
    """Turn :class:`ImucalError` into one line on stderr and exit 2 (no traceback)."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except ImucalError as exc:
            _err(f"imucal: error: {exc}")
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt as exc:
            raise _interrupted(exc) from None

    return wrapper


def _interrupted(exc: BaseException | None = None) -> typer.Exit:
    """The exit of a Ctrl-C (130) or a SIGTERM (143, :class:`Terminated`), said on stderr."""
    if isinstance(exc, Terminated) or (exc is None and _Process.terminated):
        _err("imucal: terminated")
        return typer.Exit(EXIT_TERMINATED)
    _err("imucal: interrupted")
    return typer.Exit(EXIT_INTERRUPTED)


def _terminate(number: int, frame: Any) -> None:
    """SIGTERM's handler: raise :class:`Terminated` where the command runs."""
    _Process.terminated = True
    raise Terminated


def _default_sigterm() -> None:
    """In a forked child (a reading child, a batch worker): SIGTERM ends it at once, as before;
    its parent ends it in turn when the command is ended."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _stdout_console() -> Any:
    from rich.console import Console

    # Piped output is read by people too: do not squeeze tables into 80 columns. No markup:
    # what is printed holds the user's names and paths (``lidar[front]``), to be shown as they
    # are; colours are given as styles.
    return Console(highlight=False, markup=False, width=None if sys.stdout.isatty() else 160)


@contextmanager
def _progress(description: str, unit: str = "messages") -> Iterator[Any]:
    """A bar with the total and the time left on stderr when it is a terminal (a counter while
    the total is not known); nothing otherwise. The callback takes ``(count, total)``."""
    if not sys.stderr.isatty():
        yield lambda count=None, total=None: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    progress = Progress(
        TextColumn("{task.description}", markup=False),  # a path, as it is
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn(unit),
        TimeElapsedColumn(),
        TextColumn("left"),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
    )
    task = progress.add_task(printable(description), total=None)
    progress.start()

    def update(count: int | None = None, total: int | None = None) -> None:
        progress.update(task, completed=count, total=total or None)

    try:
        yield update
    finally:
        progress.stop()


def _print_table(
    title: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[Any]],
    right: Iterable[str] = (),
    no_wrap: Iterable[str] = (),
) -> Any:
    """A rich table on stdout, the ``right`` columns right-justified (numbers); returns the
    console (for what follows the table)."""
    from rich.table import Table

    table = Table(title=printable(title))
    right, no_wrap = set(right), set(no_wrap)
    for column in columns:
        table.add_column(
            column, justify="right" if column in right else "left", no_wrap=column in no_wrap
        )
    for row in rows:
        table.add_row(*(printable(cell) if isinstance(cell, str) else cell for cell in row))
    console = _stdout_console()
    console.print(table)
    return console


def _emit(document: dict[str, Any], out: Path | None, as_json: bool, render: Any) -> None:
    """Write ``document`` to ``out`` (YAML/JSON by suffix), or print JSON, or render it."""
    from imucal_cli.documents import dumps, write_document

    if out is not None:
        write_document(out, document)
    elif as_json:
        typer.echo(dumps(document, as_json=True), nl=False)
    else:
        render(document)


def _check_output(out: Path | None, *inputs: Path | None, junit: Path | None = None) -> None:
    """Fail early (before any work) on an output path that cannot be written or that would
    replace one of the run's ``inputs`` (:func:`~imucal_cli.paths.check_outputs`)."""
    from imucal_cli.paths import check_outputs

    if out is not None and out.suffix.lower() not in {".yaml", ".yml", ".json"}:
        raise InputError(f"{out}: output must end in .yaml, .yml or .json")
    for path in (out, junit):
        if path is not None and not path.parent.is_dir():
            raise InputError(f"{path}: output folder {path.parent} does not exist")
        if path is not None and not os.access(path.parent, os.W_OK):
            raise InputError(f"{path}: output folder {path.parent} is not writable")
    check_outputs({"-o": out, "--junit": junit}, inputs)


# --------------------------------------------------------------------------- inspect


def _render_inspect(document: dict[str, Any]) -> None:
    def gaps(info: dict[str, Any]) -> str:
        return (
            str(len(info["gaps"]))
            if len(info["gaps"]) > 3
            else ", ".join(f"{a:.2f}-{b:.2f}" for a, b in info["gaps"]) or "0"
        )

    _print_table(
        f"{document['log']} ({document['format']}), t0_ns = {document['t0_ns']}",
        columns := (
            "topic",
            "type",
            "count",
            "rate Hz",
            "duration s",
            "gaps",
            "backwards",
            "duplicates",
        ),
        (
            (
                topic,
                i["type"],
                f"{i['count']:,}",
                f"{i['rate_hz']:.2f}",
                f"{i['duration_s']:.2f}",
                gaps(i),
                str(i["backwards"]),
                str(i["duplicates"]),
            )
            for topic, i in document["topics"].items()
        ),
        right=columns[2:],
        no_wrap=columns[:2],
    )


@app.command(cls=_Command, rich_help_panel=PANEL_LOGS)
@handles_errors
def inspect(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    out: Annotated[
        Path | None, typer.Option("-o", "--out", help="Write YAML (.yaml) or JSON (.json).")
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", metavar="", help="Print JSON instead of a table.")
    ] = False,
) -> None:
    """Topics, message types, counts, rates, duration, gaps and time jumps of a log."""
    from imucal_cli.inspection import summarize_log
    from imucal_cli.outputs import inspect_document

    _check_output(out, log)
    with _progress(f"reading {log}") as progress:
        summary = summarize_log(log, progress)
    _note_losses(log, summary.losses)
    _emit(inspect_document(summary), out, as_json, _render_inspect)


# --------------------------------------------------------------------------- config


#: The most lines ``init`` says of each kind (names left out, placeholders) before a count.
INIT_LINES = 20


@app.command("init", cls=_Command, rich_help_panel=PANEL_CONFIG)
@handles_errors
def init(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    out: Annotated[
        Path | None, typer.Option("-o", "--out", help="Write the config here (.yaml).")
    ] = None,
    base: Annotated[
        str | None,
        typer.Option("--base", help="The base IMU's topic (default: found from /tf_static)."),
    ] = None,
    frame: Annotated[str, typer.Option("--frame", help="The base frame B.")] = "base_link",
    urdf: UrdfOption = None,
    force: Annotated[
        bool, typer.Option("--force", metavar="", help="Replace the config OUT if it exists.")
    ] = False,
) -> None:
    """Write a starting config from a log: its IMU topics, the base, the transforms in its
    /tf_static, a commented placeholder for each one it lacks."""
    from imucal_cli.init import find, render
    from imucal_cli.version import version

    if out is not None and out.suffix.lower() not in {".yaml", ".yml"}:
        raise InputError(f"{out}: the config is YAML: name it .yaml")
    _check_output(out, log, urdf)
    if out is not None and out.exists() and not force:
        raise InputError(f"{out}: exists (a config of yours?): name a new one, or give --force")
    found = find(log, base, frame, urdf)
    text = render(found, log, version())
    if out is None:
        typer.echo(text, nl=False)
    else:
        from imucal_cli.documents import write_text_atomic

        write_text_atomic(out, text)
        _err(f"imucal: config: {out} (base {found.base_topic}, {len(found.sensors)} sensors)")
    missing = [
        f"{name}: {key} is not in the log ({found.looked.get((name, key), '')}): fill its "
        "placeholder"
        for name, key in found.missing
    ]
    for lines, what in ((found.skipped, "names left out"), (missing, "placeholders")):
        for line in lines[:INIT_LINES]:  # (a log of 60,000 IMU channels: a bounded say)
            _err(f"imucal: {line}")
        if len(lines) > INIT_LINES:
            _err(f"imucal: ... and {len(lines) - INIT_LINES:,} more {what}")


@app.command("check-config", cls=_Command, rich_help_panel=PANEL_CONFIG)
@handles_errors
def check_config(
    config: Annotated[Path, typer.Argument(help="Calibration config (YAML).")],
    as_json: Annotated[
        bool, typer.Option("--json", metavar="", help="Print JSON instead of YAML.")
    ] = False,
    log: Annotated[
        Path | None,
        typer.Option(
            "--log", help="Take the transforms the config leaves out from this log's /tf_static."
        ),
    ] = None,
    urdf: UrdfOption = None,
) -> None:
    """Validate a config and print it with every default filled in."""
    from imucal_cli.config import load_config
    from imucal_cli.documents import dumps

    if urdf is not None and log is None:
        raise InputError("--urdf goes with --log (the IMUs' frames are in the log)")
    typer.echo(dumps(load_config(config, log, urdf).to_dict(), as_json=as_json), nl=False)


# --------------------------------------------------------------------------- calibration commands

PANEL_CAL = "Calibration"
ConfigOption = Annotated[Path, typer.Option("-c", "--config", help="Calibration config (YAML).")]
UrdfOption = Annotated[
    Path | None,
    typer.Option(
        "--urdf",
        help="A URDF whose joints stand in for transforms the config leaves out (beside the "
        "log's /tf_static; default: the log's /robot_description).",
    ),
]
OutOption = Annotated[
    Path | None, typer.Option("-o", "--out", help="Write YAML (.yaml) or JSON (.json).")
]
JsonOption = Annotated[
    bool, typer.Option("--json", metavar="", help="Print JSON instead of a summary.")
]


def _note_read(log: Path, topic: str, counts: dict[str, int]) -> None:
    """One line on stderr when reading a topic sorted, replaced or dropped anything."""
    changed = {k: v for k, v in counts.items() if k != "messages" and v}
    if changed:
        details = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in changed.items())
        _err(f"imucal: note: {log} [{topic}]: {counts['messages']} messages; {details}")


def _note_losses(log: Path, losses: list[Any]) -> None:
    """One line on stderr per part of the log that could not be read (at most five, then a
    count); ``losses`` are :class:`~imucal_cli.io.base.Loss` es or a document's ``losses``."""
    for loss in losses[:5]:
        if isinstance(loss, dict):  # (a document lists only what was lost)
            _err(f"imucal: warning: {log}: {loss['reason']}")
        else:  # a note says how the log was read, nothing lost
            _err(f"imucal: {'warning' if loss.lost else 'note'}: {log}: {loss.describe()}")
    if len(losses) > 5:
        _err(f"imucal: warning: {log}: {len(losses) - 5} more damaged parts not read")


def _stream_log(log: Path, config_path: Path, urdf: Path | None = None) -> tuple[Any, Any]:
    """Load the config and stream the log's IMU messages through a calibrator (windows reduced
    beside the reading, nothing solved yet); say on stderr what reading found. Returns the
    config and the :class:`~imucal_cli.api.StreamedLog`."""
    from imucal_cli.api import stream_log
    from imucal_cli.config import load_config

    config = load_config(config_path, log, urdf)  # what it leaves out: /tf_static, URDF
    with _progress(f"reading {log}") as progress:
        streamed = stream_log(log, config, progress=progress)
    _note_losses(log, streamed.losses)
    for topic, stats in streamed.stats.items():
        _note_read(log, topic, stats.to_dict() | {"duplicates": streamed.duplicates[topic]})
    return config, streamed


def _fmt(values: Any, digits: int) -> str:
    if values is None:
        return "-"
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"


@app.command(cls=_Command, rich_help_panel=PANEL_CAL)
@handles_errors
def biases(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    config: ConfigOption,
    out: OutOption = None,
    as_json: JsonOption = False,
    urdf: UrdfOption = None,
) -> None:
    """Per IMU: rest periods, accelerometer bias and noise, gyro bias track summary."""
    _check_output(out, log, config, urdf)
    from imucal_cli.api import stream_biases
    from imucal_cli.config import load_config

    cfg = load_config(config, log, urdf)
    with _progress(f"reading {log}") as progress:
        document = stream_biases(log, cfg, progress)
    _note_losses(log, document["losses"])

    def render(doc: dict[str, Any]) -> None:
        console = _print_table(
            f"IMU biases: {log}",
            (
                "IMU",
                "rests",
                "rest s",
                "accel bias along g m/s^2",
                "gyro bias rad/s (final)",
                "final std rad/s",
            ),
            (
                (
                    name,
                    str(len(imu["rest_periods"])),
                    f"{sum(b - a for a, b in imu['rest_periods']):.1f}",
                    "n/a"
                    if imu["accel_bias_along_gravity_mps2"] is None
                    else f"{imu['accel_bias_along_gravity_mps2']:.4f}",
                    _fmt(imu["gyro_bias_radps"]["final"], 5),
                    _fmt(imu["gyro_bias_radps"]["final_std"], 5),
                )
                for name, imu in doc["imus"].items()
            ),
        )
        console.print(
            "accel bias: at rest only its component along gravity is seen; the full vector, "
            "relative to the "
            "base IMU, is calibrate's accel_bias_mps2"
        )
        for name, imu in doc["imus"].items():
            for warning in imu["warnings"]:
                console.print(printable(f"{name}: {warning}"), style="yellow")

    _emit(document, out, as_json, render)
    if out is not None or as_json:  # (the summary says them otherwise: as calibrate does)
        for name, imu in document["imus"].items():
            for warning in imu["warnings"]:
                _err(f"imucal: {name}: {warning}")


@app.command(cls=_Command, rich_help_panel=PANEL_CAL)
@handles_errors
def segments(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    config: ConfigOption,
    out: OutOption = None,
    as_json: JsonOption = False,
    urdf: UrdfOption = None,
) -> None:
    """Per sensor: each window's Fisher-information min singular value, rotation std, selected
    or not."""
    _check_output(out, log, config, urdf)
    cfg, streamed = _stream_log(log, config, urdf)
    from imucal_cli.outputs import segments_document

    calibrator, t0_ns = streamed.calibrator, streamed.t0_ns
    document = segments_document(t0_ns, cfg, calibrator)

    def render(doc: dict[str, Any]) -> None:
        for name, sensor in doc["sensors"].items():
            _print_table(
                f"{name}: {sensor['selected']} of {sensor['total']} windows selected (rotation std "
                f"< {doc['max_rotation_std_deg']:g} deg)",
                columns := (
                    "start s",
                    "end s",
                    "min singular value 1/rad^2",
                    "rotation std deg",
                    "selected",
                    "translation observable x y z",
                ),
                (
                    (
                        f"{w['start_s']:.1f}",
                        f"{w['end_s']:.1f}",
                        f"{w['min_singular_value']:.4g}",
                        "inf" if w["rotation_std_deg"] is None else f"{w['rotation_std_deg']:.4f}",
                        "yes"
                        if w["selected"]
                        else ("no: gap in the data" if w.get("gap") else "no: too little motion"),
                        " ".join("y" if v else "n" for v in w["translation_observable"]),
                    )
                    for w in sensor["windows"]
                ),
                right=columns,
            )

    _emit(document, out, as_json, render)


@app.command(cls=_Command, rich_help_panel=PANEL_CAL)
@handles_errors
def calibrate(
    log: Annotated[Path, typer.Argument(help=LOG_HELP)],
    config: ConfigOption,
    out: OutOption = None,
    as_json: JsonOption = False,
    require_observable: Annotated[
        bool,
        typer.Option(
            "--require-observable",
            metavar="",
            help="Exit 1 unless every sensor is fully observable (status ok).",
        ),
    ] = False,
    report: Annotated[
        Path | None,
        typer.Option(
            "--report",
            help="Also write figures (PNG) and report.html into this folder "
            "(needs imucal\\[report]).",
        ),
    ] = None,
    follow: Annotated[
        bool,
        typer.Option(
            "--follow",
            metavar="",
            help="Read a log still being written; update the estimate as each window completes.",
        ),
    ] = False,
    until_converged: Annotated[
        bool,
        typer.Option(
            "--until-converged",
            metavar="",
            help="With --follow: exit 0 once every sensor meets the config's stop: targets.",
        ),
    ] = False,
    timeout: Annotated[
        float | None,
        typer.Option(
            "--timeout",
            min=0.0,
            help="With --follow: stop after this many seconds (exit 1 with --until-converged).",
        ),
    ] = None,
    quiet: Annotated[
        bool,
        typer.Option(
            "--quiet",
            "-q",
            metavar="",
            help="With -o or --json: print no status lines on stderr.",
        ),
    ] = False,
    urdf: UrdfOption = None,
) -> None:
    """The extrinsics of every sensor and every lidar pair."""
    _check_output(out, log, config, urdf)
    if not follow and (until_converged or timeout is not None):
        raise InputError("--until-converged and --timeout go with --follow")
    if report is not None:
        if not report.parent.is_dir():
            raise InputError(f"{report}: report folder's parent {report.parent} does not exist")
        if report.exists() and not report.is_dir():
            raise InputError(f"{report}: exists and is not a folder")
        from imucal_cli.paths import check_outputs
        from imucal_cli.report import FIGURES

        check_outputs(
            {
                "--report": out,
                **{f"--report ({name})": report / name for name in ("report.html", *FIGURES)},
            },
            [log, config],
        )
        from imucal_cli.report import pyplot

        pyplot()  # fail before the work when matplotlib is missing
    if follow:
        _follow(log, config, out, as_json, until_converged, timeout, report, urdf)
        return
    _cfg, streamed = _stream_log(log, config, urdf)
    from imucal_cli.api import estimate
    from imucal_cli.outputs import calibration_document

    with _progress("calibrating"):
        result = estimate(streamed)
    document = calibration_document(result, str(log), streamed.losses, streamed.counts())

    def render(doc: dict[str, Any]) -> None:
        from rich.text import Text

        def row(name: str, s: dict[str, Any]) -> tuple[Any, ...]:
            std_t = (
                None
                if s["translation_std_m"] is None
                else [v * 1000 for v in s["translation_std_m"]]
            )
            return (
                name,
                Text(
                    s["status"], style={"ok": "green", "partial": "yellow"}.get(s["status"], "red")
                ),
                _fmt(s["T_base_lidar"]["translation"], 4),
                _fmt(s["T_base_lidar"]["rpy_deg"], 3),
                _fmt(std_t, 2),
                _fmt(s["rotation_std_deg"], 4),
                f"{s['time_offset_s'] * 1000:.2f}" if s["time_offset_observable"] else "not shown",
                f"{s['segments']['selected']}/{s['segments']['total']}",
            )

        console = _print_table(
            f"T_{doc['base_frame']}_lidar from {log}",
            (
                "sensor",
                "status",
                "xyz m",
                "rpy deg",
                "std xyz mm",
                "std rpy deg",
                "time offset ms",
                "windows",
            ),
            (row(name, s) for name, s in doc["sensors"].items()),
        )
        for name, s in doc["sensors"].items():
            for warning in s["warnings"]:
                console.print(Text(printable(f"{name}: {warning}"), style="yellow"))
        for pair, T in doc["pairs"].items():
            console.print(
                f"{pair}: xyz {_fmt(T['translation'], 4)} m, rpy {_fmt(T['rpy_deg'], 3)} deg"
            )

    if report is not None:
        from imucal_cli.report import write_report

        with _progress("drawing the report", "figures") as progress:
            written = write_report(report, log, result, streamed, document, progress)
        _err(f"imucal: report: {written[-1]}")
    _emit(document, out, as_json, render)
    if (out is not None or as_json) and not quiet:
        _status_lines(document)
    if require_observable and not result.all_ok:
        weak = [n for n, e in result.estimates.items() if e.status != "ok"]
        _err(f"imucal: not fully observable: {', '.join(weak)}")
        raise typer.Exit(EXIT_CHECK_FAILED)


def _status_lines(document: dict[str, Any]) -> None:
    """Where the readable summary is not printed (``-o``, ``--json``): each sensor's status
    with its worst std, then each of its warnings, one line each on stderr, so that a terminal
    or a job's log shows what is wrong without opening the output."""
    for name, sensor in document["sensors"].items():
        line = f"imucal: {name}: {sensor['status']}"
        if sensor["rotation_std_deg"] is not None:
            line += f", std {max(sensor['rotation_std_deg']):.3g} deg"
        if sensor["translation_std_m"] is not None:
            line += f" and {1000 * max(sensor['translation_std_m']):.3g} mm (worst axis)"
        _err(f"{line}, {sensor['segments']['selected']}/{sensor['segments']['total']} windows")
        for warning in sensor["warnings"]:
            _err(f"imucal: {name}: {warning}")


def _follow_table(log: Path, windows: int, result: Any, sensors: dict[str, Any]) -> Any:
    """The live table of follow mode: per sensor its status, std per axis, windows used and
    what it still lacks."""
    from rich.table import Table

    table = Table(title=f"following {log}: {windows} windows")
    for column in ("sensor", "status", "std rpy deg", "std xyz mm", "windows used", "missing"):
        table.add_column(column)
    for name, s in sensors.items():
        est = result.estimates[name]
        std_t = (
            None if s["translation_std_m"] is None else [1000 * v for v in s["translation_std_m"]]
        )
        table.add_row(
            name,
            s["status"],
            _fmt(s["rotation_std_deg"], 4),
            _fmt(std_t, 2),
            f"{sum(w.selected for w in est.windows)}/{len(est.windows)}",
            "; ".join(m.split(":")[0] for m in s["missing"]) or "-",
        )
    return table


def _follow(
    log: Path,
    config_path: Path,
    out: Path | None,
    as_json: bool,
    until_converged: bool,
    timeout: float | None,
    report: Path | None = None,
    urdf: Path | None = None,
) -> None:
    """calibrate --follow: from the first data what each sensor has and waits for, then an
    update per window (a JSON line with --json, a table on a terminal, else a line on stderr),
    then the last estimate with each sensor's missing axes, and why it stopped; exit codes as
    the SPEC says."""
    import json
    import time

    from imucal_cli.api import follow_log
    from imucal_cli.documents import to_plain
    from imucal_cli.pipeline import missing_axes

    deadline = None if timeout is None else time.monotonic() + timeout
    # the log, and the tree of a config that leaves transforms out: waited for within --timeout
    limit = deadline if deadline is not None else time.monotonic() + WAIT_FOR_LOG_S
    _wait_for(log, limit)
    cfg = _follow_config(config_path, log, limit, urdf)
    live = None
    if not as_json and sys.stderr.isatty():  # a table on the terminal, redrawn each window
        from rich.console import Console
        from rich.live import Live

        live = Live(console=Console(stderr=True), auto_refresh=False)

    heard = [time.monotonic(), -1e9]  # the last news of the recording, the last stall said

    def update(result: Any, windows: int) -> None:
        heard[0] = time.monotonic()
        sensors = {
            name: {
                "status": e.status,
                "rotation_std_deg": e.rotation_std_deg,
                "translation_std_m": e.translation_std_m,
                "missing": missing_axes(e, cfg.stop),
            }
            for name, e in result.estimates.items()
        }
        if as_json:
            typer.echo(json.dumps(to_plain({"windows": windows, "sensors": sensors})))
        elif live is not None:
            live.update(_follow_table(log, windows, result, sensors), refresh=True)
        else:
            _err(
                f"imucal: {windows} windows: "
                + ", ".join(
                    f"{n} {s['status']} ({len(s['missing'])} axes missing)"
                    for n, s in sensors.items()
                )
            )

    told = [-1e9]

    def progress(state: dict[str, Any]) -> None:  # before the first estimate
        heard[0] = time.monotonic()
        if as_json:
            typer.echo(json.dumps(to_plain({"windows": 0, **state})))
        elif live is not None:
            live.update(_waiting_table(log, state), refresh=True)
        elif time.monotonic() - told[0] >= 5.0:  # (a log file: every 5 s)
            told[0] = time.monotonic()
            first: dict[str, Any] = next(iter(state["sensors"].values()), {})
            _err(
                f"imucal: following {log}: "
                + ", ".join(f"{n} {v['samples']:,} samples" for n, v in state["sensors"].items())
                + f"; waiting for {first.get('waiting_for', 'data')}"
            )

    def timed_out() -> bool:  # (asked at every poll of the recording)
        now = time.monotonic()
        if now - heard[0] >= FOLLOW_STALL_S and now - heard[1] >= FOLLOW_STALL_S:
            heard[1] = now  # a recording that stalls: said, not waited for in silence
            _err(
                f"imucal: {log}: nothing new for {now - heard[0]:.0f} s; still waiting"
                + (" (--timeout not given: Ctrl-C ends it)" if deadline is None else "")
            )
        return deadline is not None and now > deadline

    if live is not None:
        live.start()
    try:
        run, good, interrupted = follow_log(
            log, cfg, update, timed_out, until_converged, on_progress=progress
        )
    finally:
        if live is not None:
            live.stop()
    out_of_time = timed_out()  # why it stopped (the report below takes time of its own)
    _note_losses(log, run.document["losses"])  # (garbage appended to a recording, say)
    if report is not None:
        from imucal_cli.report import write_report

        with _progress("drawing the report", "figures") as bar:
            written = write_report(report, log, run.result, run.streamed, run.document, bar)
        _err(f"imucal: report: {written[-1]}")
    if out is not None:
        from imucal_cli.documents import write_document

        write_document(out, run.document)
    for name, s in run.document["sensors"].items():
        for line in s["missing"]:
            _err(f"imucal: {name}: missing {line}")
    if interrupted:
        raise _interrupted()
    if not (until_converged and good):
        _err("imucal: --timeout reached" if out_of_time else f"imucal: the recording {log} ended")
    if until_converged and not good:
        _err("imucal: not converged" + (" before --timeout" if out_of_time else ""))
        raise typer.Exit(EXIT_CHECK_FAILED)


#: Follow mode: after how long without news of the recording the wait is said (s of wall time).
FOLLOW_STALL_S = 30.0
#: Follow mode without --timeout: how long a log that does not exist yet is waited for (s).
WAIT_FOR_LOG_S = 30.0


def _wait_for(log: Path, limit: float) -> None:
    """Follow mode started beside a recorder: wait until ``limit`` (monotonic s) for the log to
    appear, a rosbag2 folder for its storage file."""
    import time

    def present() -> bool:
        if log.is_dir():
            return any(log.glob("*.mcap")) or any(log.glob("*.db3"))
        return log.exists()

    if present():
        return
    _err(f"imucal: waiting for {log} to be created")
    while not present():
        if time.monotonic() > limit:
            raise InputError(f"{log}: no such file or directory (waited for it to be created)")
        time.sleep(0.1)


def _follow_config(config_path: Path, log: Path, limit: float, urdf: Path | None) -> Any:
    """Follow mode's config; one that leaves sensor transforms out is read against the
    recording's /tf_static and the URDF (``urdf``, else its /robot_description) as soon as
    they hold them and the IMUs' first messages (until ``limit``, monotonic s): an error in
    the URDF itself is said at once."""
    import time

    from imucal_cli.config import load_config
    from imucal_cli.errors import ConfigError, ImucalError
    from imucal_cli.frames import leaves_out_transforms

    try:
        return load_config(config_path)
    except ConfigError as exc:
        if not leaves_out_transforms(exc):
            raise
    if urdf is not None:
        from imucal_cli.documents import read_capped
        from imucal_cli.frames import MAX_URDF_BYTES, FrameTree, read_urdf

        text = read_capped(urdf, MAX_URDF_BYTES, "a URDF").decode("utf-8", errors="replace")
        read_urdf(text, FrameTree(), str(urdf))  # (not a URDF: said now, not at --timeout)
    while True:
        try:
            return load_config(config_path, log, urdf)
        except ImucalError:
            if time.monotonic() > limit:
                raise
            time.sleep(0.5)


def _waiting_table(log: Path, state: dict[str, Any]) -> Any:
    """Follow mode's table before the first estimate: per sensor, samples and what it waits
    for."""
    from rich.table import Table

    table = Table(title=f"following {log}: base {state['base_samples']:,} samples")
    for column in ("sensor", "samples", "windows", "waiting for"):
        table.add_column(column)
    for name, s in state["sensors"].items():
        table.add_row(name, f"{s['samples']:,}", str(s["windows"]), s["waiting_for"])
    return table


PANEL_EXPORT = "Export"


def _parse_transform(text: str) -> Any:
    """A transform given on the command line: a YAML/JSON file, or seven numbers."""
    from imucal_cli.errors import ConfigError
    from imucal_cli.types import Transform

    path = Path(text)
    try:
        if path.is_file():
            from imucal_cli.documents import load_document

            return Transform.from_dict(load_document(path), str(path), "")
        values = [float(v) for v in text.replace(",", " ").split()]
    except ConfigError as exc:
        raise InputError(str(exc)) from None
    except ValueError:
        values = []
    if len(values) != 7:
        raise InputError(f"--parent-transform {text!r}: expected a file or 'x y z qx qy qz qw'")
    try:
        return Transform.from_dict(
            {"translation": values[:3], "rotation": values[3:]}, "--parent-transform", ""
        )
    except ConfigError as exc:
        raise InputError(str(exc)) from None


LAUNCH_SUFFIX = {"tf-static-ros2": ".launch.xml", "tf-static-ros1": ".launch"}


@app.command(cls=_Command, rich_help_panel=PANEL_EXPORT)
@handles_errors
def export(
    extrinsics: Annotated[
        Path, typer.Argument(help="What `imucal calibrate -o` wrote (YAML or JSON).")
    ],
    fmt: Annotated[
        str,
        typer.Option(
            "--format", "-f", help="autoware, urdf, tf-static-ros2, tf-static-ros1, kalibr or json."
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "-o",
            "--out",
            help="Write here (tf-static: the command lines; the launch file goes beside it as "
            "STEM.launch.xml for ROS 2, STEM.launch for ROS 1). Default: print.",
        ),
    ] = None,
    parent: Annotated[
        str | None,
        typer.Option(
            "--parent",
            help="Express every transform relative to this frame: the base frame, a lidar frame "
            "or sensor name, or any frame --parent-transform places.",
        ),
    ] = None,
    parent_transform: Annotated[
        str | None,
        typer.Option(
            "--parent-transform",
            help="T_base_PARENT: a YAML/JSON file {translation, rotation} or 'x y z qx qy qz qw'.",
        ),
    ] = None,
    allow_not_ok: Annotated[
        bool,
        typer.Option(
            "--allow-not-ok",
            metavar="",
            help="Export sensors whose status is not ok (their prior may go out as if calibrated).",
        ),
    ] = False,
) -> None:
    """The extrinsics in the layout of Autoware, URDF, tf2 static publishers, Kalibr or JSON."""
    from imucal_cli.documents import load_document, write_text_atomic
    from imucal_cli.exports import FORMATS, Extrinsics
    from imucal_cli.exports import export as make

    if fmt not in FORMATS:
        raise InputError(f"--format {fmt}: unknown format (expected one of: {', '.join(FORMATS)})")
    if out is not None and not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")
    if parent_transform is not None and parent is None:
        raise InputError("--parent-transform: give --parent FRAME too (the frame it places)")
    T_base_parent = _parse_transform(parent_transform) if parent_transform is not None else None
    targets: dict[str, Path] = {}
    if out is not None:
        targets["main"] = out
        if fmt in LAUNCH_SUFFIX:
            stem = out.name.split(".")[0] or out.name
            targets["launch"] = out.with_name(stem + LAUNCH_SUFFIX[fmt])
        from imucal_cli.paths import check_outputs

        inputs = [extrinsics, Path(parent_transform) if parent_transform is not None else None]
        launch = targets.get("launch")
        if launch is not None and launch.exists() and not _written_by_export(launch):
            raise InputError(
                f"{launch}: exists, and imucal export did not write it: not replaced (the launch "
                "file goes beside -o OUT as its stem's): move it, or name another OUT"
            )
        check_outputs(
            {"-o" if key == "main" else "the launch file": path for key, path in targets.items()},
            inputs,
        )
    files = make(
        Extrinsics.from_document(load_document(extrinsics), str(extrinsics)),
        fmt,
        parent,
        T_base_parent,
        allow_not_ok,
    )
    if out is None:
        typer.echo(files["main"], nl=False)  # one file: the launch file needs -o
        if "launch" in files:
            _err(
                "imucal: note: printed the command lines only; give -o OUT to write them and the "
                f"{LAUNCH_SUFFIX[fmt]} launch file beside OUT"
            )
        return
    for key, path in targets.items():
        write_text_atomic(path, files[key])
        if key == "main" and fmt.startswith("tf-static"):
            path.chmod(path.stat().st_mode | 0o111)  # the command lines: a script to run
        _err(f"imucal: wrote {path}")


def _written_by_export(path: Path) -> bool:
    """Whether ``path`` is a launch file an earlier ``export`` wrote (its mark in its head)."""
    from imucal_cli.exports import LAUNCH_MARK

    try:
        with path.open("rb") as handle:
            return LAUNCH_MARK.encode() in handle.read(4096)
    except OSError:
        return False


PANEL_FLEET = "Fleet"


@app.command(cls=_Command, rich_help_panel=PANEL_FLEET)
@handles_errors
def batch(
    logs: Annotated[
        list[Path] | None, typer.Argument(help="Logs to calibrate (or --manifest).")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            "-c",
            "--config",
            help="Calibration config for every log (a manifest may name one per log).",
        ),
    ] = None,
    out_dir: Annotated[
        Path, typer.Option("--out-dir", help="Folder for each log's calibration and the summary.")
    ] = Path("imucal-batch"),
    manifest: Annotated[
        Path | None,
        typer.Option("--manifest", help="CSV with columns log[, config, truth, reference]."),
    ] = None,
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help="Local worker processes.")] = 1,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler", help="Dask scheduler address (tcp://host:port); needs imucal\\[fleet]."
        ),
    ] = None,
    truth_dir: Annotated[
        Path | None,
        typer.Option("--truth-dir", help="Folder of STEM.truth.yaml files to compare against."),
    ] = None,
    reference: Annotated[
        Path | None,
        typer.Option(
            "--reference",
            help="The vehicle's previous calibration: sensors past the thresholds are flagged "
            "as moved.",
        ),
    ] = None,
    max_rotation_deg: Annotated[
        float | None,
        typer.Option(
            "--max-rotation-deg",
            min=0.0,
            help="Pass threshold on the rotation error against --truth-dir or --reference (deg).",
        ),
    ] = None,
    max_translation_m: Annotated[
        float | None,
        typer.Option(
            "--max-translation-m",
            min=0.0,
            help="Pass threshold on the translation error against --truth-dir or --reference (m).",
        ),
    ] = None,
    junit: Annotated[
        Path | None, typer.Option("--junit", help="Write JUnit XML here (for CI).")
    ] = None,
    max_lost_s: Annotated[
        float | None,
        typer.Option(
            "--max-lost-s",
            min=0.0,
            help="Pass a log whose read lost at most this many seconds (default: any loss fails).",
        ),
    ] = None,
    force: Annotated[
        bool,
        typer.Option(
            "--force", metavar="", help="Replace the outputs an earlier batch left in --out-dir."
        ),
    ] = False,
) -> None:
    """Calibrate many logs (local processes or a Dask cluster); summary CSV/JSON, JUnit; exit 1
    if any fails."""
    from imucal_cli.fleet import (
        MOVED_FALLBACK_DEG,
        MOVED_FALLBACK_M,
        MOVED_STD,
        check_batch_outputs,
        plan_tasks,
        read_manifest,
        run_dask,
        run_local,
    )

    if not out_dir.parent.is_dir():
        raise InputError(f"{out_dir}: output folder's parent {out_dir.parent} does not exist")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: --out-dir exists and is not a folder")
    if (
        junit is not None
        and not junit.parent.is_dir()
        and junit.parent.resolve() != out_dir.resolve()
    ):
        raise InputError(f"{junit}: folder {junit.parent} does not exist")
    entries = [{"log": str(p)} for p in logs or []] + (
        read_manifest(manifest) if manifest is not None else []
    )
    thresholds = [
        name
        for name, value in (
            ("--max-rotation-deg", max_rotation_deg),
            ("--max-translation-m", max_translation_m),
        )
        if value is not None
    ]
    if (
        thresholds
        and truth_dir is None
        and reference is None
        and not all(e.get("truth") or e.get("reference") for e in entries)
    ):
        raise InputError(
            f"{thresholds[0]}: nothing to compare with: give --truth-dir or --reference "
            "(or truth/reference columns in the manifest for every log)"
        )
    tasks = plan_tasks(
        entries,
        config,
        out_dir,
        truth_dir,
        reference,
        max_rotation_deg,
        max_translation_m,
        max_lost_s,
    )
    if reference is not None and (max_rotation_deg is None or max_translation_m is None):
        _err(
            f"imucal: --reference: a sensor moved past {MOVED_STD:g} combined std of the two "
            "calibrations "
            f"(largest axis; {MOVED_FALLBACK_DEG:g} deg, {MOVED_FALLBACK_M:g} m where a std is not "
            "known)"
            + "".join(
                f"; {k} {v:g}"
                for k, v in (
                    ("--max-rotation-deg", max_rotation_deg),
                    ("--max-translation-m", max_translation_m),
                )
                if v is not None
            )
        )
    from imucal_cli.paths import only_writer

    with only_writer(out_dir):  # (a second batch into it at once is refused)
        check_batch_outputs(
            tasks,
            [out_dir / "summary.csv", out_dir / "summary.json", *([junit] if junit else [])],
            [manifest, reference, config],
            force,
        )
        for task in tasks:
            try:
                Path(task.out).parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise InputError(
                    f"{Path(task.out).parent}: cannot make the output folder: {exc.strerror}"
                ) from None

        finished: dict[int, list[Any]] = {}

        def done(i: int, rows: list[Any]) -> None:
            finished[i] = rows
            verdict = "ok" if all(r.passed for r in rows) else "FAIL"
            _err(f"imucal: [{i + 1}/{len(tasks)}] {tasks[i].name}: {verdict}")

        settings = {
            "jobs": jobs,
            "scheduler": scheduler,
            "max_rotation_deg": max_rotation_deg,
            "max_translation_m": max_translation_m,
            "max_lost_s": max_lost_s,
            "truth_dir": str(truth_dir) if truth_dir else None,
            "reference": str(reference) if reference else None,
        }
        try:
            results = (
                run_dask(tasks, scheduler, done) if scheduler else run_local(tasks, jobs, done)
            )
        except KeyboardInterrupt as exc:  # the logs finished by then are summarised all the same
            rows = [row for i in sorted(finished) for row in finished[i]]
            settings["interrupted"] = f"after {len(finished)} of {len(tasks)} logs"
            _summaries(rows, settings, out_dir, junit)
            _err(f"imucal: {len(finished)} of {len(tasks)} logs summarised in {out_dir}")
            raise _interrupted(exc) from None
        rows = [row for result in results for row in result]
        _summaries(rows, settings, out_dir, junit)
        failed = sum(not r.passed for r in rows)
        _err(
            f"imucal: {len(tasks)} logs, {len(rows)} rows, {failed} failed; summary in "
            f"{out_dir / 'summary.csv'}"
        )
    if failed:
        raise typer.Exit(EXIT_CHECK_FAILED)


def _summaries(
    rows: list[Any], settings: dict[str, Any], out_dir: Path, junit: Path | None
) -> None:
    """batch's summaries: the JUnit first (what a CI reads: a full disk then costs the CSV and
    JSON, said in the error), then the CSV and the JSON."""
    from imucal_cli.documents import write_text_atomic
    from imucal_cli.fleet import junit_xml, summary_csv, summary_json

    if junit is not None:
        write_text_atomic(junit, junit_xml(rows))
    write_text_atomic(out_dir / "summary.csv", summary_csv(rows))
    write_text_atomic(out_dir / "summary.json", summary_json(rows, settings))


@app.command(cls=_Command, rich_help_panel=PANEL_CAL)
@handles_errors
def evaluate(
    estimate: Annotated[Path, typer.Argument(help="Output of imucal calibrate (YAML/JSON).")],
    truth: Annotated[Path, typer.Argument(help="Truth file: sensors.NAME.T_base_lidar.")],
    max_rotation_deg: Annotated[
        float | None, typer.Option(help="Fail (exit 1) above this rotation error.", min=0.0)
    ] = None,
    max_translation_m: Annotated[
        float | None, typer.Option(help="Fail (exit 1) above this translation error.", min=0.0)
    ] = None,
    out: OutOption = None,
    as_json: JsonOption = False,
    allow_missing: Annotated[
        bool,
        typer.Option(
            "--allow-missing", metavar="", help="Pass although a sensor is in one file only."
        ),
    ] = False,
    junit: Annotated[
        Path | None, typer.Option("--junit", help="Also write JUnit XML here (for CI).")
    ] = None,
) -> None:
    """Rotation and translation errors of every sensor and pair against ground truth."""
    from imucal_cli.api import evaluate as compare
    from imucal_cli.documents import write_text_atomic
    from imucal_cli.fleet import evaluate_junit

    _check_output(out, estimate, truth, junit=junit)
    document = compare(estimate, truth, max_rotation_deg, max_translation_m, allow_missing)
    for side, names in document["missing"].items():
        for name in names:
            where = estimate if side == "estimate_only" else truth
            _err(
                f"imucal: {'note' if allow_missing else 'error'}: sensor {name} is in {where} only"
            )
    if junit is not None:
        write_text_atomic(junit, evaluate_junit(document, str(estimate), str(truth)))

    def render(doc: dict[str, Any]) -> None:
        limits = doc["thresholds"]

        def over(r: dict[str, Any]) -> list[str]:  # the thresholds a row exceeds, named
            return [
                f"{key.removeprefix('max_').replace('_', ' ')} > {limits[key]:g}"
                for key, value in (
                    ("max_rotation_deg", "rotation_error_deg"),
                    ("max_translation_m", "translation_error_m"),
                )
                if limits[key] is not None and r[value] > limits[key]
            ]

        rows = {**doc["sensors"], **doc["pairs"]}
        console = _print_table(
            f"{estimate} vs {truth}",
            ("sensor / pair", "rotation error deg", "translation error m", "eq. 20 m", "over"),
            (
                (
                    name,
                    f"{r['rotation_error_deg']:.4f}",
                    f"{r['translation_error_m']:.4f}",
                    f"{r['translation_error_eq20_m']:.4f}",
                    ", ".join(over(r)) or "-",
                )
                for name, r in rows.items()
            ),
            right=("rotation error deg", "translation error m", "eq. 20 m"),
        )
        failed = [name for name, r in rows.items() if over(r)]
        missing = [name for names in doc["missing"].values() for name in names]
        why = [f"{len(failed)} over a threshold ({', '.join(failed)})"] * bool(failed) + [
            f"in one file only: {', '.join(missing)}"
        ] * bool(missing and not doc["pass"])
        console.print(
            "pass" if doc["pass"] else "fail: " + "; ".join(why),
            style="green" if doc["pass"] else "red",
        )

    _emit(document, out, as_json, render)
    if not document["pass"]:
        raise typer.Exit(EXIT_CHECK_FAILED)


# --------------------------------------------------------------------------- simulate


#: What each log suffix of ``simulate OUT`` writes by default (anything else: a rosbag2 folder).
SUFFIX_FORMAT = {".mcap": "mcap", ".bag": "rosbag1"}


@app.command(cls=_Command, rich_help_panel=PANEL_SIM)
@handles_errors
def simulate(
    out: Annotated[
        Path, typer.Argument(help="Log to write (.mcap, .bag, or a rosbag2 directory name).")
    ],
    scenario: Annotated[Scenario, typer.Option(help="Kind of drive.")] = Scenario.urban,
    duration: Annotated[
        float | None,
        typer.Option(
            help="Seconds (default: aggressive 81, urban 283, highway/parking 120).", min=1.0
        ),
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed: the same seed gives the same log.")] = 0,
    log_format: Annotated[
        LogFormat | None,
        typer.Option(
            "--format",
            help="Log format (default: from OUT: .mcap -> mcap, .bag -> rosbag1, "
            "else rosbag2-sqlite3).",
        ),
    ] = None,
    sensors: Annotated[
        int, typer.Option("--sensors", help="Number of lidars (1-4).", min=1, max=4)
    ] = 2,
    noise_scale: Annotated[
        float,
        typer.Option(help="Multiplies every IMU error (0: ideal sensors, exact timing).", min=0.0),
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
    errors: Annotated[
        str,
        typer.Option(
            "--errors",
            help="Sensor or mount errors beyond the estimator's model: none, mems (scale factors, "
            "non-orthogonality, g-sensitivity, vibration), misaligned (gyro and accelerometer "
            "triads "
            "apart), tilting-mount, clock-offsets (+-40 ms), prior-off (0.5 m), accel-g, gyro-dps, "
            "ins-away (the base IMU turned and 1.6 m away, declared), clock-jitter (+-40 ms, "
            "0.5 ms jitter, 1% drops, 200 Hz); consumer, industrial, tactical, navigation, "
            "mems-base (errors drawn from those grades), gyros-low (both gyros 10% low).",
        ),
    ] = "none",
    lidar_grade: Annotated[
        str | None,
        typer.Option(
            help="Draw each lidar IMU's own errors from this grade (consumer, industrial, "
            "tactical, navigation, ideal) and declare it in the config (default: ideal, or "
            "the error class's).",
        ),
    ] = None,
    base_grade: Annotated[
        str | None,
        typer.Option(help="The same for the base IMU (default: ideal, or the error class's)."),
    ] = None,
    tf_static: Annotated[
        bool,
        typer.Option(
            "--tf-static",
            metavar="",
            help="Write /tf_static: per lidar <name>/os_sensor at the CAD prior with the IMU's "
            "and the lidar's frames under it, and the base IMU's frame gnss_imu in base_link.",
        ),
    ] = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            metavar="",
            help="Replace an existing OUT if it is a log (and the truth and config beside it).",
        ),
    ] = False,
) -> None:
    """Simulate a drive: a log OUT with STEM.truth.yaml and STEM.config.yaml beside it."""
    from dataclasses import replace

    from imucal_cli.core.grades import GRADES
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, with_errors
    from imucal_cli.sim.drive import BiasTrack, drive_pieces
    from imucal_cli.sim.writers import write_imu_log

    suffix = out.suffix.lower()
    fmt = (
        log_format.value if log_format is not None else SUFFIX_FORMAT.get(suffix, "rosbag2-sqlite3")
    )
    expected = {"mcap": ".mcap", "mcap-ros1": ".mcap", "rosbag1": ".bag"}.get(fmt)
    if expected is not None and suffix != expected:
        raise InputError(f"{out}: format {fmt} writes a {expected} file; name OUT with that suffix")
    if expected is None and suffix in {".mcap", ".bag"}:
        raise InputError(
            f"{out}: format {fmt} writes a rosbag2 directory; name OUT without {suffix}"
        )
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} does not exist")
    truth_path, config_path = _simulate_outputs(out, force)
    options = DriveOptions(
        scenario=scenario.value,
        duration_s=duration,
        seed=seed,
        sensors=sensors,
        noise_scale=noise_scale,
        time_offsets_s=tuple(time_offset_s) if time_offset_s else None,
        lidar_rate_hz=lidar_rate_hz,
    )
    grades = {"lidar_grade": lidar_grade, "base_grade": base_grade}
    for key, grade in grades.items():
        if grade is not None and grade not in GRADES:
            raise InputError(
                f"--{key.replace('_', '-')}: {grade!r} is not one of {', '.join(GRADES)}"
            )
    try:
        options = with_errors(options, errors)
        options = replace(
            options,
            lidar_grade=lidar_grade or options.lidar_grade,
            base_grade=base_grade or options.base_grade,
            tf_static=tf_static,
        )
        pieces = drive_pieces(options)  # (made as written: memory does not grow with --duration)
        drive = next(pieces)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    track = BiasTrack(drive)
    counts = {topic: len(data.stream) for topic, data in drive.topics().items()}

    def later() -> Iterator[Any]:
        for piece in pieces:
            track.add(piece)
            for topic, data in piece.topics().items():
                counts[topic] += len(data.stream)
            yield piece.topics()

    with _progress(f"writing {out}") as progress:
        write_imu_log(
            out,
            fmt,
            drive.topics(),
            progress,
            force,
            drive.static_transforms(),
            later=(later(), None),
        )
    write_document(truth_path, drive.truth_document(track))
    write_document(config_path, drive.config_document())
    console = _stdout_console()
    from rich.text import Text

    console.print(
        Text.assemble(
            (str(out), "bold"),
            f" ({fmt}, {scenario.value}, seed {seed}): "
            + ", ".join(f"{topic} {count:,}" for topic, count in counts.items()),
        )
    )
    console.print(f"truth:  {truth_path}\nconfig: {config_path}")


def _simulate_outputs(out: Path, force: bool) -> tuple[Path, Path]:
    """The truth and config files beside OUT, checked before any work: an existing log OUT is
    replaced only with ``--force`` and only if it is a log; its truth and config likewise, and
    only if they are such documents."""
    from imucal_cli.documents import load_document
    from imucal_cli.paths import refuse_existing

    refuse_existing(out, force)
    stem = out.with_suffix("") if out.suffix.lower() in SUFFIX_FORMAT else out  # the prefix of both
    truth_path = stem.with_name(stem.name + ".truth.yaml")
    config_path = stem.with_name(stem.name + ".config.yaml")
    for path in (truth_path, config_path):
        if not (path.exists() or path.is_symlink()):
            continue
        if not force:
            raise InputError(f"{path}: exists: name a new log, or give --force to replace it")
        try:
            document = load_document(path) if path.is_file() and not path.is_symlink() else None
        except InputError:
            document = None
        if not isinstance(document, dict) or "sensors" not in document:
            raise InputError(
                f"{path}: exists and is not a truth or config imucal wrote: not replaced"
            )
    return truth_path, config_path


# --------------------------------------------------------------------------- entry point


def main() -> None:
    """Console-script entry point (usage errors exit 2, as Typer does); a SIGTERM ends a
    command as a Ctrl-C does, with exit code 143."""
    import signal

    signal.signal(signal.SIGTERM, _terminate)
    os.register_at_fork(after_in_child=_default_sigterm)
    app()


if __name__ == "__main__":
    main()
