"""The ``imucal`` command's entry point: starts reading the log first, then runs the CLI.

``calibrate`` and ``segments`` spend their first half second or so importing (Typer and its
option handling, numpy, then scipy), on one core. Their log's reader needs none of that: it runs
in a child process that imports what reading needs by itself. So the entry point finds the log
and the config's topics in the arguments before anything else is imported, forks the reader,
and only then imports the CLI, which takes the reading over (:func:`take_early`) if its own
parsing finds the same log and config, and ends it otherwise. The arguments are read here for
that guess only; the CLI parses and checks them as always. Before numpy is imported it also
sets the BLAS library to one thread per process (see :func:`begin`).
"""

from __future__ import annotations

import os
import sys
from functools import partial
from pathlib import Path
from typing import Any

#: The commands that stream a log through the calibration.
STREAMING_COMMANDS = ("calibrate", "segments")
#: Their options that take a value (the rest are flags).
_WITH_VALUE = ("-c", "--config", "-o", "--out", "--report")

#: What sets the thread count of the BLAS library under numpy and scipy (OpenBLAS reads the
#: first of these it finds).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")

#: The reading started for (log, config), until the CLI takes it.
_early: tuple[Path, Path, Any] | None = None


def main() -> None:
    """Console-script entry point (see the module's docstring)."""
    begin(sys.argv[1:])
    from imucal_cli.cli import main as cli_main

    cli_main()


def begin(args: list[str]) -> None:
    """What the command does before importing numpy or the CLI, for the command line ``args``
    (the arguments after the program's name).

    - One BLAS thread per process, unless the environment sets a count: ``calibrate`` already
      keeps every core busy with its processes (log reader, math, math worker), and BLAS
      threads on top only compete with them (the 1 h MCAP of ``benchmarks/throughput.py``:
      8% less CPU and 7% less wall time, 14 alternating pairs of runs).
    - For ``calibrate`` and ``segments``, start reading the log, for the CLI to take over;
      nothing for other commands, nor where anything goes wrong here (the CLI then reads as it
      would anyway, and says what is wrong)."""
    global _early
    if not any(name in os.environ for name in BLAS_THREAD_VARIABLES):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"  # read when numpy is first imported
    found = log_and_config(args)
    if found is None:
        return
    try:
        reading = start_reading(*found)
    except Exception:  # noqa: BLE001 - a guess only: never the reason a command fails
        return
    if reading is not None:
        _early = (*found, reading)


def log_and_config(args: list[str]) -> tuple[Path, Path] | None:
    """``(log, config)`` of a ``calibrate`` or ``segments`` command line, or None where it is
    another command or anything is unusual (help, ``--``, a second positional argument)."""
    if not args or args[0] not in STREAMING_COMMANDS:
        return None
    log = config = None
    rest = iter(args[1:])
    for arg in rest:
        if arg in ("--help", "-h", "--"):
            return None
        if arg in _WITH_VALUE:
            value = next(rest, None)
            if value is None:
                return None
            if arg in ("-c", "--config"):
                config = value
        elif arg.startswith("--config="):
            config = arg.removeprefix("--config=")
        elif arg.startswith("-"):
            continue  # a flag (or a form not guessed at: the CLI will say)
        elif log is None:
            log = arg
        else:
            return None
    if log is None or config is None:
        return None
    return Path(log), Path(config)


def _topics(config: Path) -> list[str] | None:
    """The IMU topics the config names (base first), read plainly; None when unusual (the CLI's
    own loading then says what is wrong)."""
    import yaml

    try:
        data = yaml.safe_load(config.read_text(encoding="utf-8"))
        topics = [data["base"]["topic"], *(sensor["imu_topic"] for sensor in data["sensors"].values())]
    except Exception:  # noqa: BLE001 - anything unusual is left to the full check
        return None
    if not all(isinstance(topic, str) for topic in topics) or len(set(topics)) != len(topics):
        return None
    return topics


def _imu_batches(log: Path, topics: list[str]) -> Any:  # runs in the reader process
    from imucal_cli.io.logs import ImuBatches

    return ImuBatches(log, topics)


def start_reading(log: Path, config: Path) -> Any:
    """Start reading ``log``'s IMU topics, as ``config`` names them, in a child process, for
    :func:`imucal_cli.api.stream_log`'s ``reading``; None when the topics cannot be read plainly
    or the log does not exist."""
    topics = _topics(config)
    if topics is None or not log.exists():
        return None
    from imucal_cli.io.prefetch import read_made_ahead
    from imucal_cli.parallel import reuse_freed_memory

    reuse_freed_memory()  # before the fork: the child keeps the setting
    return read_made_ahead(partial(_imu_batches, log, topics), log, topics)


def take_early(log: Path, config: Path) -> Any:
    """The reading :func:`begin` started for ``(log, config)``, or None; one started for
    anything else is ended."""
    global _early
    early, _early = _early, None
    if early is None:
        return None
    if (early[0], early[1]) == (log, config):
        return early[2]
    early[2][1].close()
    return None


if __name__ == "__main__":  # python -m imucal_cli.launch: this module's own copy, as the CLI imports it
    from imucal_cli.launch import main as _main

    _main()
