"""The options the commands share, as ``Annotated`` aliases, and the checks of output paths
made before any work."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any

import typer

from imucal_cli.errors import InputError

DOCUMENT_SUFFIXES = {".yaml", ".yml", ".json"}


def output_path(path: Path | None) -> Path | None:
    """The callback of every output option: a folder that exists and can be written."""
    if path is not None and not path.parent.is_dir():
        raise typer.BadParameter(f"{path}: output folder {path.parent} does not exist")
    if path is not None and not os.access(path.parent, os.W_OK):
        raise typer.BadParameter(f"{path}: output folder {path.parent} is not writable")
    return path


def document_path(path: Path | None) -> Path | None:
    """:func:`output_path` of a document: YAML or JSON by its suffix."""
    if path is not None and path.suffix.lower() not in DOCUMENT_SUFFIXES:
        raise typer.BadParameter(f"{path}: output must end in .yaml, .yml or .json")
    return output_path(path)


def folder_path(path: Path | None) -> Path | None:
    """The callback of an output folder: it is one, or its parent is, to make it in."""
    if path is not None and not path.parent.is_dir():
        raise typer.BadParameter(f"{path}: the folder's parent {path.parent} does not exist")
    if path is not None and path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{path}: exists and is not a folder")
    return path


def guard(outputs: dict[str, Path | None], inputs: list[Path | None]) -> None:
    """No output replaces an input, a log, or goes into a rosbag2 folder
    (:func:`~imucal_cli.paths.check_outputs`)."""
    from imucal_cli.paths import check_outputs

    check_outputs(outputs, inputs)


def flag(*names: str, help: str, **more: Any) -> Any:
    """A yes/no option, shown as the flag it is (no ``<bool>`` after it)."""
    return typer.Option(*names, metavar="", help=help, **more)


def needs(option: str, value: object, other: str, given: object) -> None:
    """``option`` goes with ``other``: an error naming both when only ``option`` is given."""
    if value not in (None, False) and given in (None, False):
        raise InputError(f"{option} goes with {other}")


LOG_HELP = "Log: a .mcap file, a rosbag2 directory (sqlite3 or mcap storage) or a ROS 1 .bag."
Log = Annotated[Path, typer.Argument(help=LOG_HELP)]
Config = Annotated[
    Path, typer.Option("-c", "--config", help="Calibration config (YAML).", exists=True)
]
Urdf = Annotated[
    Path | None,
    typer.Option(
        "--urdf",
        exists=True,
        help="A URDF whose joints stand in for transforms the config leaves out (beside the "
        "log's /tf_static; default: the log's /robot_description).",
    ),
]
Out = Annotated[
    Path | None,
    typer.Option("-o", "--out", help="Write YAML (.yaml) or JSON (.json).", callback=document_path),
]
Json = Annotated[bool, flag("--json", help="Print JSON instead of a summary.")]
Junit = Annotated[
    Path | None,
    typer.Option("--junit", help="Also write JUnit XML here (for CI).", callback=output_path),
]
MaxRotation = Annotated[
    float | None,
    typer.Option("--max-rotation-deg", min=0.0, help="Pass threshold on the rotation error (deg)."),
]
MaxTranslation = Annotated[
    float | None,
    typer.Option(
        "--max-translation-m", min=0.0, help="Pass threshold on the translation error (m)."
    ),
]
