"""Typed errors. The CLI turns every :class:`ImucalError` into one line on stderr and exit 2."""

from __future__ import annotations


class ImucalError(Exception):
    """Base class of every error imucal raises on bad input."""


class ConfigError(ImucalError):
    """A configuration file or value is invalid. The message names the file and the key path."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str, str]]:  # picklable across processes
        return (type(self), (self.source, self.key, self.problem))


class LogError(ImucalError):
    """A log cannot be read, or lacks what was asked of it. The message names the file."""

    def __init__(self, path: str, problem: str, topic: str | None = None) -> None:
        self.path = path
        self.topic = topic
        self.problem = problem
        where = f"{path} [{topic}]" if topic else path
        super().__init__(f"{where}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str, str | None]]:  # picklable across processes
        return (type(self), (self.path, self.problem, self.topic))


class InputError(ImucalError):
    """Any other bad input (a truth file, an estimate file, an output path)."""


class Terminated(KeyboardInterrupt):
    """A SIGTERM (what a CI runner sends at its timeout), raised where the command runs so that
    it ends as a Ctrl-C does (children ended, nothing partial left), with exit 143."""
