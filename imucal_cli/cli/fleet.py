"""``batch``: many logs calibrated (local processes or a Dask cluster), each compared with a
truth or the vehicle's previous calibration; summaries and JUnit."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from imucal_cli.cli import options
from imucal_cli.cli.app import EXIT_CHECK_FAILED, PANEL_FLEET, command, err, interrupted
from imucal_cli.errors import InputError

Logs = Annotated[list[Path] | None, typer.Argument(help="Logs to calibrate (or --manifest).")]
BatchConfig = Annotated[
    Path | None,
    typer.Option(
        "-c",
        "--config",
        exists=True,
        help="Calibration config for every log (a manifest may name one per log).",
    ),
]
OutDir = Annotated[
    Path,
    typer.Option(
        "--out-dir",
        callback=options.folder_path,
        help="Folder for each log's calibration and the summary.",
    ),
]
Manifest = Annotated[
    Path | None,
    typer.Option(
        "--manifest", exists=True, help="CSV with columns log[, config, truth, reference]."
    ),
]
Jobs = Annotated[int, typer.Option("--jobs", "-j", min=1, help="Local worker processes.")]
Scheduler = Annotated[
    str | None,
    typer.Option(
        "--scheduler", help="Dask scheduler address (tcp://host:port); needs imucal\\[fleet]."
    ),
]
TruthDir = Annotated[
    Path | None,
    typer.Option("--truth-dir", help="Folder of STEM.truth.yaml files to compare against."),
]
Reference = Annotated[
    Path | None,
    typer.Option(
        "--reference",
        exists=True,
        help="The vehicle's previous calibration: sensors past the thresholds are flagged "
        "as moved.",
    ),
]
MaxLost = Annotated[
    float | None,
    typer.Option(
        "--max-lost-s",
        min=0.0,
        help="Pass a log whose read lost at most this many seconds (default: any loss fails).",
    ),
]
Junit = Annotated[Path | None, typer.Option("--junit", help="Write JUnit XML here (for CI).")]
Force = Annotated[
    bool, options.flag("--force", help="Replace the outputs an earlier batch left in --out-dir.")
]


@command(PANEL_FLEET)
def batch(
    logs: Logs = None,
    config: BatchConfig = None,
    out_dir: OutDir = Path("imucal-batch"),
    manifest: Manifest = None,
    jobs: Jobs = 1,
    scheduler: Scheduler = None,
    truth_dir: TruthDir = None,
    reference: Reference = None,
    max_rotation_deg: options.MaxRotation = None,
    max_translation_m: options.MaxTranslation = None,
    junit: Junit = None,
    max_lost_s: MaxLost = None,
    force: Force = False,
) -> None:
    """Calibrate many logs (local processes or a Dask cluster); summary CSV/JSON, JUnit; exit 1
    if any fails."""
    from imucal_cli.fleet import Batch, read_manifest
    from imucal_cli.paths import only_writer

    if (
        junit is not None
        and not junit.parent.is_dir()
        and junit.parent.resolve() != out_dir.resolve()
    ):
        raise InputError(f"{junit}: folder {junit.parent} does not exist")
    entries = [{"log": str(p)} for p in logs or []]
    entries += read_manifest(manifest) if manifest is not None else []
    limits = (max_rotation_deg, max_translation_m, max_lost_s)
    plan = Batch(entries, config, out_dir, truth_dir, reference, *limits, junit, manifest)
    with only_writer(out_dir):  # (a second batch into it at once is refused)
        tasks = plan.plan(force)
        if rule := plan.moved_rule():
            err(f"imucal: {rule}")
        finished: list[int] = []

        def done(i: int, rows: list[Any]) -> None:
            finished.append(i)
            verdict = "ok" if all(r.passed for r in rows) else "FAIL"
            err(f"imucal: [{i + 1}/{len(tasks)}] {tasks[i].name}: {verdict}")

        try:
            rows = plan.run(tasks, jobs, scheduler, done)
        except KeyboardInterrupt as exc:  # the logs finished by then are summarised all the same
            err(f"imucal: {len(finished)} of {len(tasks)} logs summarised in {out_dir}")
            raise interrupted(exc) from None
    failed = sum(not r.passed for r in rows)
    summary = out_dir / "summary.csv"
    err(f"imucal: {len(tasks)} logs, {len(rows)} rows, {failed} failed; summary in {summary}")
    if failed:
        raise typer.Exit(EXIT_CHECK_FAILED)
