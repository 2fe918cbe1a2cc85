"""``export``: the extrinsics in the layout of the software that reads them."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from imucal_cli.cli import options
from imucal_cli.cli.app import PANEL_EXPORT, command, err
from imucal_cli.errors import InputError
from imucal_cli.exports import FORMATS, export_targets, parse_transform

Extrinsics = Annotated[
    Path, typer.Argument(help="What `imucal calibrate -o` wrote (YAML or JSON).", exists=True)
]
Format = Annotated[
    str,
    typer.Option(
        "--format", "-f", help="; ".join(f"{n}: {f.what}" for n, f in FORMATS.items()) + "."
    ),
]
Out = Annotated[
    Path | None,
    typer.Option(
        "-o",
        "--out",
        callback=options.output_path,
        help="Write here (tf-static: the command lines; the launch file goes beside it as "
        "STEM.launch.xml for ROS 2, STEM.launch for ROS 1). Default: print.",
    ),
]
Parent = Annotated[
    str | None,
    typer.Option(
        "--parent",
        help="Express every transform relative to this frame: the base frame, a lidar frame "
        "or sensor name, or any frame --parent-transform places.",
    ),
]
ParentTransform = Annotated[
    str | None,
    typer.Option(
        "--parent-transform",
        help="T_base_PARENT: a YAML/JSON file {translation, rotation} or 'x y z qx qy qz qw'.",
    ),
]
AllowNotOk = Annotated[
    bool,
    options.flag(
        "--allow-not-ok",
        help="Export sensors whose status is not ok (their prior may go out as if calibrated).",
    ),
]


@command(PANEL_EXPORT)
def export(
    extrinsics: Extrinsics,
    fmt: Format,
    out: Out = None,
    parent: Parent = None,
    parent_transform: ParentTransform = None,
    allow_not_ok: AllowNotOk = False,
) -> None:
    """The extrinsics in the layout of Autoware, URDF, tf2 static publishers, Kalibr or JSON."""
    from imucal_cli import api
    from imucal_cli.documents import load_document, write_text_atomic

    if fmt not in FORMATS:
        raise InputError(f"--format {fmt}: unknown format (expected one of: {', '.join(FORMATS)})")
    options.needs(
        "--parent-transform", parent_transform, "--parent FRAME (the frame it places)", parent
    )
    T_base_parent = parse_transform(parent_transform) if parent_transform is not None else None
    inputs = [extrinsics, Path(parent_transform) if parent_transform is not None else None]
    targets = export_targets(out, fmt)
    names = {"main": "-o", "launch": "the launch file"}
    options.guard({names[key]: path for key, path in targets.items()}, inputs)
    document = load_document(extrinsics)
    files = api.export(document, fmt, parent, str(extrinsics), T_base_parent, allow_not_ok)
    if out is None:
        typer.echo(files["main"], nl=False)  # one file: the launch file needs -o
        if "launch" in files:
            err(
                "imucal: note: printed the command lines only; give -o OUT to write them and the "
                f"{FORMATS[fmt].launch_suffix} launch file beside OUT"
            )
        return
    for key, path in targets.items():
        write_text_atomic(path, files[key])
        if key == "main" and fmt.startswith("tf-static"):
            path.chmod(path.stat().st_mode | 0o111)  # the command lines: a script to run
        err(f"imucal: wrote {path}")
