"""The Python API, which the command line, ``batch`` and ``--follow`` call as users do.

>>> import imucal_cli                                                       # doctest: +SKIP
>>> cal = imucal_cli.calibrate("drive.mcap", "vehicle.yaml")               # doctest: +SKIP
>>> cal.T_base_lidar("front_left_top").as_matrix()                         # doctest: +SKIP
>>> cal.document()["sensors"]["front_left_top"]["status"]                  # doctest: +SKIP
>>> imucal_cli.export(cal.document(), "urdf")["main"]                      # doctest: +SKIP

Every function raises :class:`~imucal_cli.errors.ImucalError` subclasses on bad input (with
the file, topic or key in the message) and prints nothing; what reading found (counts, losses)
is in the :class:`~imucal_cli.calibration.Calibration` for the caller to report. A config is a
:class:`~imucal_cli.config.Config` or the path of its YAML file (what it leaves out taken from
the log's ``/tf_static`` and a URDF, ``urdf``, else the log's ``/robot_description``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from imucal_cli import pipeline
from imucal_cli.calibration import Calibration, Reading
from imucal_cli.config import Config
from imucal_cli.errors import InputError
from imucal_cli.pipeline import (
    DriveStreams,
    calibrate_streams,
    follow,
    lost_summary,
    recording_config,
    wait_for_log,
)
from imucal_cli.types import Transform

__all__ = [
    "Calibration",
    "DriveStreams",
    "Reading",
    "biases",
    "calibrate",
    "calibrate_streams",
    "evaluate",
    "export",
    "follow",
    "load_config",
    "load_transforms",
    "lost_summary",
    "recording_config",
    "segments",
    "wait_for_log",
    "write_document",
    "write_report",
]

Progress = Callable[[int, int], None]
ConfigLike = Config | str | Path


def load_config(
    path: str | Path, log: str | Path | None = None, urdf: str | Path | None = None
) -> Config:
    """The config at ``path``; with ``log``, the transforms it leaves out taken from the log's
    ``/tf_static`` and a URDF (``urdf``, else the log's ``/robot_description``)."""
    from imucal_cli import config, priors

    if log is None:
        return config.load_config(path)
    return priors.load_config_for(path, log, urdf)


def _config(config: ConfigLike, log: str | Path, urdf: str | Path | None) -> Config:
    return config if isinstance(config, Config) else load_config(config, log, urdf)


def calibrate(
    log: str | Path,
    config: ConfigLike,
    *,
    urdf: str | Path | None = None,
    progress: Progress | None = None,
    on_window: Callable[[int], None] | None = None,
    stop: Callable[[], bool] | None = None,
    workers: int = 1,
) -> Calibration:
    """Calibrate every sensor of ``config`` from the IMU topics of ``log`` (MCAP, rosbag2 or
    ROS 1 bag): ``progress(messages read, messages in the log)`` as reading goes,
    ``on_window(windows reduced)``, and where ``stop()`` says so the reading ends there and the
    calibration is of what was read. ``workers``: threads the linear algebra may take."""
    config = _config(config, log, urdf)
    return pipeline.calibrate(
        log, config, progress=progress, on_window=on_window, stop=stop, workers=workers
    )


def segments(
    log: str | Path,
    config: ConfigLike,
    *,
    urdf: str | Path | None = None,
    progress: Progress | None = None,
    workers: int = 1,
) -> Calibration:
    """Every window's observability (``.segments_document()``), nothing solved."""
    config = _config(config, log, urdf)
    return pipeline.segments(log, config, progress=progress, workers=workers)


def biases(
    log: str | Path,
    config: ConfigLike,
    *,
    urdf: str | Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The SPEC's ``biases`` document of ``log``."""
    return pipeline.biases(log, _config(config, log, urdf), progress=progress)


def export(
    document: Mapping[str, Any],
    fmt: str,
    parent: str | None = None,
    source: str = "<document>",
    T_base_parent: Transform | None = None,
    allow_not_ok: bool = False,
) -> dict[str, str]:
    """The text of one export format (:data:`imucal_cli.exports.FORMATS`) from a calibrate
    document: ``{"main": ...}``, plus ``{"launch": ...}`` for the tf2 static publishers;
    relative to ``parent`` where given; sensors not ``ok`` only with ``allow_not_ok``."""
    from imucal_cli.exports import Extrinsics
    from imucal_cli.exports import export as make

    return make(
        Extrinsics.from_document(document, source), fmt, parent, T_base_parent, allow_not_ok
    )


def evaluate(
    estimate: str | Path | Mapping[str, Any],
    truth: str | Path | Mapping[str, Any],
    max_rotation_deg: float | None = None,
    max_translation_m: float | None = None,
    allow_missing: bool = False,
    max_time_offset_s: float | None = None,
) -> dict[str, Any]:
    """The SPEC's evaluate document of a calibrate output (or any document with ``sensors:
    NAME: T_base_lidar``) against a truth, each a file or the document itself
    (``cal.document()``); ``document["pass"]`` is the verdict. Clock offsets are compared where
    both give ``time_offset_s``."""
    from imucal_cli.documents import load_document
    from imucal_cli.outputs import evaluate_document

    documents = [p if isinstance(p, Mapping) else load_document(p) for p in (estimate, truth)]
    names = [str(p) if not isinstance(p, Mapping) else "<document>" for p in (estimate, truth)]
    estimates, truths = (load_transforms(d, name=n) for d, n in zip(documents, names, strict=True))
    if not set(estimates) & set(truths):
        raise InputError(f"{estimate}: no sensor in common with {truth}")
    offsets = [_time_offsets(d, n) for d, n in zip(documents, names, strict=True)]
    return evaluate_document(
        estimates,
        truths,
        max_rotation_deg,
        max_translation_m,
        allow_missing,
        (offsets[0], offsets[1]),
        max_time_offset_s,
    )


def _time_offsets(document: Mapping[str, Any], name: str) -> dict[str, float]:
    """Each sensor's ``time_offset_s`` where the document gives one (a number, else the key is
    refused by name)."""
    out = {}
    for sensor, fields in document["sensors"].items():
        value = fields.get("time_offset_s")
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            raise InputError(f"{name}: sensors.{sensor}.time_offset_s: not a number: {value!r}")
        out[str(sensor)] = float(value)
    return out


def write_report(
    out_dir: str | Path, calibration: Calibration, progress: Progress | None = None
) -> list[Path]:
    """The report's figures and ``report.html`` of a calibration into ``out_dir`` (needs
    matplotlib, ``imucal[report]``); returns the files written."""
    from imucal_cli.report import write_report as draw

    return draw(Path(out_dir), calibration, progress)


def write_document(path: str | Path, document: Any) -> None:
    """Write a document (``cal.document()``, an evaluate or biases document) as YAML or JSON by
    the suffix of ``path``, atomically, as the commands' ``-o`` does."""
    from imucal_cli.documents import write_document as write

    write(path, document)


def load_transforms(
    path: str | Path | Mapping[str, Any], key: str = "T_base_lidar", name: str | None = None
) -> dict[str, Transform]:
    """``key`` of every sensor of a calibrate output or truth (``sensors: NAME: key``), a file
    or the document itself (called ``name`` in messages); :class:`InputError` naming the file
    and the key path when one is missing or malformed."""
    from imucal_cli.documents import load_document
    from imucal_cli.errors import ConfigError

    document = path if isinstance(path, Mapping) else load_document(path)
    path = name or ("<document>" if isinstance(path, Mapping) else path)
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
