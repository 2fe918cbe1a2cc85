"""``biases``, ``segments``, ``calibrate`` and ``evaluate``: each parses, calls the API and
renders or writes its document."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from imucal_cli import tables
from imucal_cli.cli import options, render
from imucal_cli.cli.app import EXIT_CHECK_FAILED, PANEL_CAL, command, err


def _config(log: Path, config: Path, urdf: Path | None) -> Any:
    from imucal_cli.api import load_config

    return load_config(config, log, urdf)  # what it leaves out: the log's /tf_static, a URDF


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
    render.emit(document, out, as_json, tables.biases, log)
    if out is not None or as_json:  # (the summary says them otherwise: as calibrate does)
        for name, imu in document["imus"].items():
            for warning in imu["warnings"]:
                err(f"imucal: {name}: {warning}")


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
    document = calibration.segments_document(streamed=True)
    render.emit(document, out, as_json, tables.segments)


Report = Annotated[
    Path | None,
    typer.Option(
        "--report",
        callback=options.folder_path,
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
    if report is not None:
        from imucal_cli.report import check_outputs

        check_outputs(report, {"--report": out}, [log, config])
    if follow:
        follow_log(log, config, out, as_json, until_converged, timeout, report, urdf)
        return
    calibration = _read(log, config, urdf, api.calibrate)
    document = calibration.document()
    if report is not None:
        render.report(report, calibration)
    render.emit(document, out, as_json, tables.calibration, log)
    if (out is not None or as_json) and not quiet:
        for line in tables.status_lines(document):
            err(f"imucal: {line}")
    if require_observable and not calibration.all_ok:
        weak = [f"{n} {e.status}" for n, e in calibration.estimates.items() if e.status != "ok"]
        err(f"imucal: --require-observable: not every sensor is ok: {', '.join(weak)}")
        raise typer.Exit(EXIT_CHECK_FAILED)


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
    render.emit(document, out, as_json, tables.evaluation, estimate, truth)
    if not document["pass"]:
        raise typer.Exit(EXIT_CHECK_FAILED)
