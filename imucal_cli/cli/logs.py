"""``inspect``, ``init`` and ``check-config``: what a log holds, and a config from it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from imucal_cli import tables
from imucal_cli.cli import options, render
from imucal_cli.cli.app import PANEL_CONFIG, PANEL_LOGS, command, err
from imucal_cli.errors import InputError


@command(PANEL_LOGS)
def inspect(
    log: options.Log,
    out: options.Out = None,
    as_json: Annotated[bool, options.flag("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """Topics, message types, counts, rates, duration, gaps and time jumps of a log."""
    from imucal_cli.inspection import summarize_log
    from imucal_cli.outputs import inspect_document

    options.guard({"-o": out}, [log])
    with render.progress(f"reading {log.name}") as progress:
        summary = summarize_log(log, progress)
    render.note_losses(log, summary.losses)
    render.emit(inspect_document(summary), out, as_json, tables.inspection)


def _yaml_path(path: Path | None) -> Path | None:
    if path is not None and path.suffix.lower() not in {".yaml", ".yml"}:
        raise typer.BadParameter(f"{path}: the config is YAML: name it .yaml")
    return options.output_path(path)


@command(PANEL_CONFIG, "init")
def init(
    log: options.Log,
    out: Annotated[
        Path | None,
        typer.Option("-o", "--out", help="Write the config here (.yaml).", callback=_yaml_path),
    ] = None,
    base: Annotated[
        str | None,
        typer.Option("--base", help="The base IMU's topic (default: found from /tf_static)."),
    ] = None,
    frame: Annotated[str, typer.Option("--frame", help="The base frame B.")] = "base_link",
    urdf: options.Urdf = None,
    force: Annotated[
        bool, options.flag("--force", help="Replace the config OUT if it exists.")
    ] = False,
) -> None:
    """Write a starting config from a log: its IMU topics, the base, the transforms in its
    /tf_static, a commented placeholder for each one it lacks."""
    from imucal_cli.documents import write_text_atomic
    from imucal_cli.init import find
    from imucal_cli.init import render as render_config
    from imucal_cli.version import version

    options.guard({"-o": out}, [log, urdf])
    if out is not None and out.exists() and not force:
        raise InputError(f"{out}: exists (a config of yours?): name a new one, or give --force")
    found = find(log, base, frame, urdf)
    text = render_config(found, log, version())
    if out is None:
        typer.echo(text, nl=False)
    else:
        write_text_atomic(out, text)
        err(f"imucal: config: {out} (base {found.base_topic}, {len(found.sensors)} sensors)")
    for line in found.notes():
        err(f"imucal: {line}")


@command(PANEL_CONFIG, "check-config")
def check_config(
    config: Annotated[
        Path, typer.Argument(help="Calibration config (YAML).", exists=True, dir_okay=False)
    ],
    as_json: Annotated[bool, options.flag("--json", help="Print JSON instead of YAML.")] = False,
    log: Annotated[
        Path | None,
        typer.Option(
            "--log", help="Take the transforms the config leaves out from this log's /tf_static."
        ),
    ] = None,
    urdf: options.Urdf = None,
) -> None:
    """Validate a config and print it with every default filled in."""
    from imucal_cli.api import load_config
    from imucal_cli.priors import config_text

    options.needs("--urdf", urdf, "--log (the IMUs' frames are in the log)", log)
    text, taken = config_text(load_config(config, log, urdf), as_json)
    for key, source in sorted(taken.items()):
        err(f"imucal: note: {key}: from {log}'s {source} (the config leaves it out)")
    typer.echo(text, nl=False)
