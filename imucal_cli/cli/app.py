"""The ``imucal`` application: the Typer app, its exit codes and the error boundary.

Every :class:`ImucalError` becomes one line on stderr and exit code 2, with no traceback and no
partial output file; a Ctrl-C exits 130, a SIGTERM 143. Commands import what they run inside
themselves, so that ``imucal --help`` is quick.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Annotated, Any, ParamSpec, TypeVar

import typer

from imucal_cli.cli.options import flag
from imucal_cli.errors import ImucalError, Terminated
from imucal_cli.names import printable
from imucal_cli.version import version

P = ParamSpec("P")
R = TypeVar("R")

EXIT_OK, EXIT_CHECK_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143

PANEL_LOGS, PANEL_CONFIG, PANEL_CAL = "Logs", "Configuration", "Calibration"
PANEL_EXPORT, PANEL_FLEET, PANEL_SIM = "Export", "Fleet", "Simulation"


def _flag(option: Any) -> Any:
    """The help option shown as the flag it is: no ``<bool>`` (Typer 0.29 gives its own
    ``--help`` a type; this program's flags have ``metavar=""``)."""
    if option is not None:
        option.metavar = ""
    return option


class Command(typer.core.TyperCommand):
    def get_help_option(self, ctx: Any) -> Any:
        return _flag(super().get_help_option(ctx))

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        """A bad value (a file that does not exist, an output folder that does not) is said
        as every bad input is: one line naming it, exit 2."""
        try:
            return super().parse_args(ctx, args)
        except typer.BadParameter as exc:
            err(f"imucal: error: {exc.format_message()}")
            ctx.exit(EXIT_BAD_INPUT)
            raise  # (ctx.exit raises)


class _Group(typer.core.TyperGroup):
    def get_help_option(self, ctx: Any) -> Any:
        return _flag(super().get_help_option(ctx))

    def get_params(self, ctx: Any) -> list[Any]:
        # (Typer's completion options are flags, shown as this program's flags are)
        return [_flag(p) if getattr(p, "is_flag", False) else p for p in super().get_params(ctx)]


app = typer.Typer(
    cls=_Group,
    name="imucal",
    help="Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone.",
    add_completion=True,  # (--install-completion, --show-completion: bash, zsh, fish)
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"imucal {version()}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, flag("--version", help="Print the version.", callback=_version, is_eager=True)
    ] = False,
) -> None:
    """Calibrate the extrinsics of every lidar on a vehicle from raw IMU signals alone."""


def command(panel: str, name: str | None = None) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Register a command of the app in a help panel, its errors handled
    (:func:`handles_errors`)."""

    def register(function: Callable[P, R]) -> Callable[P, R]:
        app.command(name, cls=Command, rich_help_panel=panel, help=_paragraphs(function.__doc__))(
            handles_errors(function)
        )
        return function

    return register


def _paragraphs(doc: str | None) -> str | None:
    """A docstring as help: its paragraphs' lines joined (the source's line breaks are not the
    terminal's), paragraphs apart."""
    import inspect

    if doc is None:
        return None
    paragraphs = inspect.cleandoc(doc).split("\n\n")
    return "\n\n".join(" ".join(p.split()) for p in paragraphs)


def err(text: str) -> None:
    """One line on stderr, control characters shown as escapes: what a log or config names
    (topics, frames, paths) can never move the cursor, retitle the terminal or fake a line."""
    typer.echo(printable(text), err=True)


class _Process:
    #: A SIGTERM came (:func:`_terminate`).
    terminated = False


def handles_errors(function: Callable[P, R]) -> Callable[P, R]:
    """Turn :class:`ImucalError` into one line on stderr and exit 2 (no traceback)."""

    @functools.wraps(function)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return function(*args, **kwargs)
        except ImucalError as exc:
            err(f"imucal: error: {exc}")
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt as exc:
            raise interrupted(exc) from None

    return wrapper


def interrupted(exc: BaseException | None = None) -> typer.Exit:
    """The exit of a Ctrl-C (130) or a SIGTERM (143, :class:`Terminated`), said on stderr."""
    _handled_interrupt()
    if isinstance(exc, Terminated) or (exc is None and _Process.terminated):
        err("imucal: terminated")
        return typer.Exit(EXIT_TERMINATED)
    err("imucal: interrupted")
    return typer.Exit(EXIT_INTERRUPTED)


def _handled_interrupt() -> None:
    """Clear CPython's mark of a Ctrl-C not handled. A KeyboardInterrupt that passed through an
    ``exec`` of a string (a library making a function while it is imported, say) marks the
    interpreter, which then kills itself with SIGINT at exit (status -2, not 130) however the
    exception was handled; an ``exec`` of a string that completes clears the mark
    (``run_eval_code_obj`` in CPython's ``Python/pythonrun.c``)."""
    exec("")


def _terminate(number: int, frame: Any) -> None:
    """SIGTERM's handler: raise :class:`Terminated` where the command runs."""
    _Process.terminated = True
    raise Terminated


def _default_sigterm() -> None:
    """In a forked child (a batch worker): SIGTERM ends it at once, as before; its parent ends
    it in turn when the command is ended."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main() -> None:
    """Console-script entry point (usage errors exit 2, as Typer does); a SIGTERM ends a
    command as a Ctrl-C does, with exit code 143."""
    import signal

    signal.signal(signal.SIGTERM, _terminate)
    os.register_at_fork(after_in_child=_default_sigterm)
    app()
