"""The ``imucal`` command line: each command parses its options, calls :mod:`imucal_cli.api`
and renders or writes what it returns (a module per group of commands)."""

from importlib import import_module

from imucal_cli.cli.app import app, main

#: The command modules, in the order their commands are shown.
COMMANDS = ("logs", "calibration", "export", "fleet", "simulate")
for _name in COMMANDS:
    import_module(f"imucal_cli.cli.{_name}")

__all__ = ["app", "main"]
