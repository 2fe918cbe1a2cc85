"""A config completed from a log: the transforms it leaves out taken from the log's
``/tf_static`` and a URDF (the file given, else the log's ``/robot_description``), each value
said as the log's where it is wrong. Loading a config alone (:func:`imucal_cli.config.
load_config`) opens no log."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from imucal_cli.config import Config, parse_config, read_config
from imucal_cli.errors import ConfigError
from imucal_cli.frames import complete_from_log, leaves_out, leaves_out_transforms


def config_alone(path: str | Path) -> tuple[Config | None, bool]:
    """The config as its file alone gives it (the file read once), and whether it leaves a
    transform out for a log's tree to supply (the base IMU's pose included): None where the
    file alone gives none (a sensor's transforms left out). Any other problem: its
    :class:`ConfigError`."""
    data = read_config(path)
    try:
        config = parse_config(data, str(path))
    except ConfigError as exc:
        if leaves_out_transforms(exc):
            return None, True
        raise
    return config, leaves_out(data)


def load_config_for(path: str | Path, log: str | Path, urdf: str | Path | None = None) -> Config:
    """The config at ``path`` with what it leaves out from ``log``
    (:func:`imucal_cli.frames.complete_from_log`); where each transform came from in
    :attr:`Config.priors`."""
    data, priors = complete_from_log(read_config(path), log, str(path), urdf)
    try:
        return replace(parse_config(data, str(path)), priors=priors)
    except ConfigError as exc:  # a value the log supplied: said as the log's, not the file's
        name, _, key = exc.key.removeprefix("sensors.").partition(".")
        origin = priors.get(name, {}).get(key.split(".")[0], "config")
        if exc.key.startswith("base."):
            origin = next(iter(priors.values()), {}).get("base.T_base_imu", "config")
        if origin == "config":
            raise
        raise ConfigError(
            str(path),
            exc.key,
            f"{exc.problem} (the value {path} leaves out, taken from {origin} in {log})",
        ) from None
