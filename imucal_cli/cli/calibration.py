"""``biases``, ``segments``, ``calibrate`` and ``evaluate``: each parses, calls the API and
renders or writes its document."""

from __future__ import annotations

from itertools import islice
from pathlib import Path
from typing import Annotated, Any

import typer

from imucal_cli.cli import options, render
from imucal_cli.cli.app import EXIT_CHECK_FAILED, PANEL_CAL, command, err
from imucal_cli.names import printable


def _config(log: Path, config: Path, urdf: Path | None) -> Any:
    from imucal_cli.api import load_config

    return load_config(config, log, urdf)  # what it leaves out: the log's /tf_static, a URDF


def _render_biases(log: Path, document: dict[str, Any]) -> None:
    columns = ("IMU", "rests", "rest s", "accel bias along g m/s^2", "gyro bias rad/s (final)")
    shown = render.table(
        f"IMU biases: {log}",
        (*columns, "final std rad/s"),
        (
            (
                *(name, str(len(imu["rest_periods"]))),
                f"{sum(b - a for a, b in imu['rest_periods']):.1f}",
                "n/a"
                if imu["accel_bias_along_gravity_mps2"] is None
                else f"{imu['accel_bias_along_gravity_mps2']:.4f}",
                render.fmt(imu["gyro_bias_radps"]["final"], 5),
                render.fmt(imu["gyro_bias_radps"]["final_std"], 5),
            )
            for name, imu in document["imus"].items()
        ),
    )
    shown.print(
        "accel bias: at rest only its component along gravity is seen; the full vector, "
        "relative to the base IMU, is calibrate's accel_bias_mps2"
    )
    for name, imu in document["imus"].items():
        for warning in imu["warnings"]:
            shown.print(printable(f"{name}: {warning}"), style="yellow")


@command(PANEL_CAL)
def biases(
    log: options.Log,
    config: options.Config,
    out: options.Out = None,
    as_json: options.Json = False,
    urdf: options.Urdf = None,
) -> None:
    """Per IMU: rest periods, accelerometer bias and noise, gyro bias track summary."""
    from imucal_cli import api

    options.guard({"-o": out}, [log, config, urdf])
    cfg = _config(log, config, urdf)
    with render.progress(f"reading {log.name}") as progress:
        document = api.biases(log, cfg, progress=progress)
    render.note_losses(log, document["losses"])
    render.emit(document, out, as_json, lambda doc: _render_biases(log, doc))
    if out is not None or as_json:  # (the summary says them otherwise: as calibrate does)
        for name, imu in document["imus"].items():
            for warning in imu["warnings"]:
                err(f"imucal: {name}: {warning}")


def _window_row(w: dict[str, Any]) -> tuple[str, ...]:
    # (padded to the widest each column takes: the blocks of a long log's table line up)
    selected = "no: gap in the data" if w.get("gap") else "no: too little motion"
    return (
        f"{w['start_s']:8.1f}",
        f"{w['end_s']:8.1f}",
        f"{w['min_singular_value']:.4g}",
        "inf" if w["rotation_std_deg"] is None else f"{w['rotation_std_deg']:.4f}",
        f"{'yes' if w['selected'] else selected:>21}",
        " ".join("y" if v else "n" for v in w["translation_observable"]),
    )


#: Windows a table of ``segments`` shows at a time (a day's log has 8,640 a sensor: shown in
#: blocks, each held only while it is drawn).
TABLE_ROWS = 1000


def _render_segments(document: dict[str, Any]) -> None:
    columns = ("start s", "end s", "min singular value 1/rad^2", "rotation std deg", "selected")
    for name, sensor in document["sensors"].items():
        title = (
            f"{name}: {sensor['selected']} of {sensor['total']} windows selected (rotation std "
            f"< {document['max_rotation_std_deg']:g} deg)"
        )
        rows, shown = map(_window_row, sensor["windows"]), 0
        block = list(islice(rows, TABLE_ROWS))
        while True:  # (the first block, empty or not, under the sensor's title)
            render.table(
                f"{name}, windows {shown + 1}-{shown + len(block)}" if shown else title,
                (*columns, "translation observable x y z"),
                block,
                right=(*columns, "translation observable x y z"),
            )
            shown += len(block)
            block = list(islice(rows, TABLE_ROWS))
            if not block:
                break


def _read(log: Path, config: Path, urdf: Path | None, run: Any) -> Any:
    """``run(log, config, progress=...)`` with a bar, and what reading noted said."""
    cfg = _config(log, config, urdf)
    with render.progress(f"reading {log.name}") as progress:
        calibration = run(log, cfg, progress=progress)
    render.note_losses(log, calibration.reading.losses)
    render.note_read(log, calibration.reading.counts)
    return calibration


@command(PANEL_CAL)
def segments(
    log: options.Log,
    config: options.Config,
    out: options.Out = None,
    as_json: options.Json = False,
    urdf: options.Urdf = None,
) -> None:
    """Per sensor: each window's Fisher-information min singular value, rotation std, selected
    or not."""
    from imucal_cli import api

    options.guard({"-o": out}, [log, config, urdf])
    calibration = _read(log, config, urdf, api.segments)
    render.emit(calibration.segments_document(streamed=True), out, as_json, _render_segments)


def _sensor_row(name: str, s: dict[str, Any]) -> tuple[Any, ...]:
    from rich.text import Text

    std_t = None if s["translation_std_m"] is None else [v * 1000 for v in s["translation_std_m"]]
    style = {"ok": "green", "partial": "yellow"}.get(s["status"], "red")
    return (
        name,
        Text(s["status"], style=style),
        render.fmt(s["T_base_lidar"]["translation"], 4),
        render.fmt(s["T_base_lidar"]["rpy_deg"], 3),
        render.fmt(std_t, 2),
        render.fmt(s["rotation_std_deg"], 4),
        f"{s['time_offset_s'] * 1000:.2f}" if s["time_offset_observable"] else "not shown",
        f"{s['segments']['selected']}/{s['segments']['total']}",
    )


def _render_calibration(log: Path, doc: dict[str, Any]) -> None:
    from rich.text import Text

    columns = ("sensor", "status", "xyz m", "rpy deg", "std xyz mm", "std rpy deg")
    shown = render.table(
        f"T_{doc['base_frame']}_lidar from {log}",
        (*columns, "time offset ms", "windows"),
        (_sensor_row(name, s) for name, s in doc["sensors"].items()),
    )
    for name, s in doc["sensors"].items():
        for warning in s["warnings"]:
            shown.print(Text(printable(f"{name}: {warning}"), style="yellow"))
    for pair, T in doc["pairs"].items():
        xyz, rpy = render.fmt(T["translation"], 4), render.fmt(T["rpy_deg"], 3)
        shown.print(f"{pair}: xyz {xyz} m, rpy {rpy} deg")


def _report_path(path: Path | None) -> Path | None:
    if path is not None and not path.parent.is_dir():
        raise typer.BadParameter(f"{path}: report folder's parent {path.parent} does not exist")
    if path is not None and path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{path}: exists and is not a folder")
    return path


Report = Annotated[
    Path | None,
    typer.Option(
        "--report",
        callback=_report_path,
        help="Also write figures (PNG) and report.html into this folder (needs imucal\\[report]).",
    ),
]
Follow = Annotated[
    bool,
    options.flag(
        "--follow",
        help="Read a log still being written; update the estimate as each window completes.",
    ),
]
UntilConverged = Annotated[
    bool,
    options.flag(
        "--until-converged",
        help="With --follow: exit 0 once every sensor meets the config's stop: targets.",
    ),
]
Timeout = Annotated[
    float | None,
    typer.Option(
        "--timeout",
        min=0.0,
        help="With --follow: stop after this many seconds (exit 1 with --until-converged).",
    ),
]
RequireObservable = Annotated[
    bool,
    options.flag(
        "--require-observable",
        help="Exit 1 unless every sensor is ok (partial, inconsistent and unobservable fail).",
    ),
]
Quiet = Annotated[
    bool, options.flag("--quiet", "-q", help="With -o or --json: print no status lines on stderr.")
]


def _guard_report(report: Path | None, out: Path | None, inputs: list[Path | None]) -> None:
    """The report's files replace no input; matplotlib is there (said before the work)."""
    if report is None:
        return
    from imucal_cli.report import FIGURES, pyplot

    files = {f"--report ({name})": report / name for name in ("report.html", *FIGURES)}
    options.guard({"--report": out, **files}, inputs)
    pyplot()


@command(PANEL_CAL)
def calibrate(
    log: options.Log,
    config: options.Config,
    out: options.Out = None,
    as_json: options.Json = False,
    require_observable: RequireObservable = False,
    report: Report = None,
    follow: Follow = False,
    until_converged: UntilConverged = False,
    timeout: Timeout = None,
    quiet: Quiet = False,
    urdf: options.Urdf = None,
) -> None:
    """The extrinsics of every sensor and every lidar pair."""
    from imucal_cli import api
    from imucal_cli.cli.follow import follow_log

    options.guard({"-o": out}, [log, config, urdf])
    options.needs("--until-converged", until_converged, "--follow", follow)
    options.needs("--timeout", timeout, "--follow", follow)
    _guard_report(report, out, [log, config])
    if follow:
        follow_log(log, config, out, as_json, until_converged, timeout, report, urdf)
        return
    calibration = _read(log, config, urdf, api.calibrate)
    document = calibration.document()
    if report is not None:
        render.report(report, calibration)
    render.emit(document, out, as_json, lambda doc: _render_calibration(log, doc))
    if (out is not None or as_json) and not quiet:
        render.status_lines(document)
    if require_observable and not calibration.all_ok:
        weak = [f"{n} {e.status}" for n, e in calibration.estimates.items() if e.status != "ok"]
        err(f"imucal: --require-observable: not every sensor is ok: {', '.join(weak)}")
        raise typer.Exit(EXIT_CHECK_FAILED)


def _over(row: dict[str, Any], limits: dict[str, Any]) -> list[str]:
    """The thresholds a row of an evaluate document exceeds, named."""
    from imucal_cli.outputs import over_thresholds

    return [
        f"{key.removeprefix('max_').replace('_', ' ')} > {limits[key]:g}"
        for key, _ in over_thresholds(row, limits)
    ]


def _render_evaluation(estimate: Path, truth: Path, doc: dict[str, Any]) -> None:
    rows = {**doc["sensors"], **doc["pairs"]}
    numbers = ("rotation error deg", "translation error m", "eq. 20 m", "time offset error ms")
    shown = render.table(
        f"{estimate} vs {truth}",
        ("sensor / pair", *numbers, "over"),
        (
            (
                name,
                *(f"{r[key]:.4f}" for key in ("rotation_error_deg", "translation_error_m")),
                f"{r['translation_error_eq20_m']:.4f}",
                "-"
                if r.get("time_offset_error_s") is None
                else f"{r['time_offset_error_s'] * 1e3:.3f}",
                ", ".join(_over(r, doc["thresholds"])) or "-",
            )
            for name, r in rows.items()
        ),
        right=numbers,
    )
    failed = [name for name, r in rows.items() if _over(r, doc["thresholds"])]
    missing = [name for names in doc["missing"].values() for name in names]
    why = [f"{len(failed)} over a threshold ({', '.join(failed)})"] * bool(failed) + [
        f"in one file only: {', '.join(missing)}"
    ] * bool(missing and not doc["pass"])
    verdict = "pass" if doc["pass"] else "fail: " + "; ".join(why)
    shown.print(verdict, style="green" if doc["pass"] else "red")


@command(PANEL_CAL)
def evaluate(
    estimate: Annotated[
        Path, typer.Argument(help="Output of imucal calibrate (YAML/JSON).", exists=True)
    ],
    truth: Annotated[
        Path, typer.Argument(help="Truth file: sensors.NAME.T_base_lidar.", exists=True)
    ],
    max_rotation_deg: options.MaxRotation = None,
    max_translation_m: options.MaxTranslation = None,
    out: options.Out = None,
    as_json: options.Json = False,
    max_time_offset_s: Annotated[
        float | None,
        typer.Option(
            "--max-time-offset-s",
            min=0.0,
            help="Pass threshold on each sensor's clock offset error (s), where the truth has "
            "time_offset_s.",
        ),
    ] = None,
    allow_missing: Annotated[
        bool, options.flag("--allow-missing", help="Pass although a sensor is in one file only.")
    ] = False,
    junit: options.Junit = None,
) -> None:
    """Rotation and translation errors of every sensor and pair against ground truth."""
    from imucal_cli import api
    from imucal_cli.documents import write_text_atomic
    from imucal_cli.fleet import evaluate_junit

    options.guard({"-o": out, "--junit": junit}, [estimate, truth])
    document = api.evaluate(
        estimate, truth, max_rotation_deg, max_translation_m, allow_missing, max_time_offset_s
    )
    for side, names in document["missing"].items():
        where = estimate if side == "estimate_only" else truth
        for name in names:
            err(f"imucal: {'note' if allow_missing else 'error'}: sensor {name} is in {where} only")
    if junit is not None:
        write_text_atomic(junit, evaluate_junit(document, str(estimate), str(truth)))
    render.emit(document, out, as_json, lambda doc: _render_evaluation(estimate, truth, doc))
    if not document["pass"]:
        raise typer.Exit(EXIT_CHECK_FAILED)
