"""The Python API: calibrate a recorded log, export and evaluate, without the command line.

>>> from imucal_cli import calibrate_log, load_config              # doctest: +SKIP
>>> run = calibrate_log("drive.mcap", load_config("vehicle.yaml"))  # doctest: +SKIP
>>> run.result.T_base_lidar("front_left_top").as_matrix()          # doctest: +SKIP
>>> run.document["sensors"]["front_left_top"]["status"]             # doctest: +SKIP

Everything here raises :class:`~imucal_cli.errors.ImucalError` subclasses on bad input (with
the file, topic or key in the message) and prints nothing; what reading found (counts, losses)
is returned for the caller to report.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from imucal_cli.errors import InputError
from imucal_cli.pipeline import (
    LogCalibration,
    StreamedLog,
    calibrate_log,
    estimate,
    follow_log,
    lost_summary,
    stream_biases,
    stream_log,
)
from imucal_cli.types import Transform

__all__ = [
    "LogCalibration",
    "StreamedLog",
    "calibrate_log",
    "estimate",
    "evaluate",
    "export_extrinsics",
    "follow_log",
    "load_transforms",
    "lost_summary",
    "stream_biases",
    "stream_log",
    "write_report",
]


def export_extrinsics(
    document: Mapping[str, Any],
    fmt: str,
    parent: str | None = None,
    source: str = "<document>",
    T_base_parent: Transform | None = None,
    allow_not_ok: bool = False,
) -> dict[str, str]:
    """The text of one export format (:mod:`imucal_cli.exports`) from a calibrate document:
    ``{"main": ...}``, plus ``{"launch": ...}`` for the tf2 static publishers; relative to
    ``parent`` where given; sensors not ``ok`` only with ``allow_not_ok``."""
    from imucal_cli.exports import Extrinsics, export

    return export(
        Extrinsics.from_document(dict(document), source), fmt, parent, T_base_parent, allow_not_ok
    )


def evaluate(
    estimate: str | Path | Mapping[str, Any],
    truth: str | Path | Mapping[str, Any],
    max_rotation_deg: float | None = None,
    max_translation_m: float | None = None,
    allow_missing: bool = False,
) -> dict[str, Any]:
    """The SPEC's evaluate document of a calibrate output (or any document with ``sensors:
    NAME: T_base_lidar``) against a truth, each a file or the document itself (``run.document``);
    ``document["pass"]`` is the verdict."""
    from imucal_cli.outputs import evaluate_document

    estimates, truths = load_transforms(estimate), load_transforms(truth)
    if not set(estimates) & set(truths):
        raise InputError(f"{estimate}: no sensor in common with {truth}")
    return evaluate_document(estimates, truths, max_rotation_deg, max_translation_m, allow_missing)


def write_report(out_dir: str | Path, run: LogCalibration) -> list[Path]:
    """The report's figures and ``report.html`` of a calibration into ``out_dir`` (needs
    matplotlib, ``imucal[report]``); returns the files written."""
    from imucal_cli.report import write_report as draw

    return draw(Path(out_dir), run.streamed.log, run.result, run.streamed, run.document)


def write_document(path: str | Path, document: Any) -> None:
    """Write a document (``run.document``, an evaluate or biases document) as YAML or JSON by
    the suffix of ``path``, atomically, as the commands' ``-o`` does."""
    from imucal_cli.documents import write_document as write

    write(path, document)


def load_transforms(
    path: str | Path | Mapping[str, Any], key: str = "T_base_lidar"
) -> dict[str, Transform]:
    """``key`` of every sensor of a calibrate output or truth (``sensors: NAME: key``), a file
    or the document itself; :class:`InputError` naming the file and the key path when one is
    missing or malformed."""
    from imucal_cli.documents import load_document
    from imucal_cli.errors import ConfigError

    document = path if isinstance(path, Mapping) else load_document(path)
    path = "<document>" if isinstance(path, Mapping) else path
    if not isinstance(document, dict) or not isinstance(document.get("sensors"), dict):
        raise InputError(f"{path}: expected a mapping with 'sensors'")
    out = {}
    for name, sensor in document["sensors"].items():
        if not isinstance(sensor, dict) or key not in sensor:
            raise InputError(f"{path}: sensors.{name}.{key}: missing")
        try:
            out[str(name)] = Transform.from_dict(sensor[key], str(path), f"sensors.{name}.{key}")
        except ConfigError as exc:
            raise InputError(str(exc)) from None
    return out
