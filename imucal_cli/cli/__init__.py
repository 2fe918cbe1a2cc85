"""The ``imucal`` command line: each command parses its options, calls :mod:`imucal_cli.api`
and renders or writes what it returns (a module per group of commands, imported here in the
order their commands are shown)."""

from imucal_cli.cli.app import app, main

# isort: off
from imucal_cli.cli import logs, calibration, export, fleet, simulate  # noqa: F401
# isort: on

__all__ = ["app", "main"]
