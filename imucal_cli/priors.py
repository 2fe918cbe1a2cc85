"""A config completed from a log: the transforms it leaves out taken from the log's
``/tf_static`` and a URDF (the file given, else the log's ``/robot_description``), each value
said as the log's where it is wrong. Loading a config alone (:func:`imucal_cli.config.
load_config`) opens no log."""

from __future__ import annotations

import re
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
    data, priors = complete_from_log(read_config(path), log, str(path), urdf, init_marks(path))
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


#: A transform's line as ``imucal init`` writes it: the key, its value, where it came from.
_MARKED = re.compile(
    r"^( {2}| {4})(T_imu_lidar|prior_T_base_imu|T_base_imu): .*# from (tf_static|urdf)"
)


def init_marks(path: str | Path) -> set[tuple[str, str]]:
    """The transforms a config gives as ``imucal init`` wrote them from a log's tree (its
    ``# from tf_static`` lines): (sensor, key), ``("", "T_base_imu")`` for the base's. Whether
    each is still the tree's is for the tree to say (:func:`complete_from_log`)."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return set()
    marks, section, sensor = set(), "", ""
    for line in text.splitlines():
        if line and not line[0].isspace():
            section = line.split(":")[0]
        elif section == "sensors" and (head := re.match(r"^  (\w+):\s*$", line)):
            sensor = head[1]
        if found := _MARKED.match(line):
            in_base = section == "base" and found[1] == "  " and found[2] == "T_base_imu"
            if in_base or (section == "sensors" and sensor and found[1] == "    "):
                marks.add(("" if in_base else sensor, found[2]))
    return marks


def config_text(config: Config, as_json: bool) -> tuple[str, dict[str, str]]:
    """The config as YAML (each key a log supplied marked on its line with where it came from)
    or JSON, and those keys with their sources (``sensors.NAME.KEY`` or ``base.KEY``)."""
    from imucal_cli.documents import dumps

    text = dumps(config.to_dict(), as_json=as_json)
    taken = {  # (the config's own keys are left as they are)
        (key if key.startswith("base.") else f"sensors.{name}.{key}"): source
        for name, sources in config.priors.items()
        for key, source in sources.items()
        if source != "config"
    }
    for key, source in [] if as_json else taken.items():
        *where, leaf = key.split(".")
        head = "base:\n" if where == ["base"] else f"\n  {where[-1]}:\n"
        line = f"\n{'  ' * len(where)}{leaf}:\n"
        found = text.find(line, max(text.find(head), 0))
        if found >= 0:
            text = text[:found] + f"{line[:-1]}  # from {source}\n" + text[found + len(line) :]
    return text, taken
