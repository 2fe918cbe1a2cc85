"""What the commands show: progress on stderr, tables on stdout, status lines, and documents
written or printed."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

from imucal_cli.cli.app import err
from imucal_cli.names import printable


def console() -> Any:
    """stdout's console. Piped output is read by people too: tables are not squeezed into 80
    columns. No markup: what is printed holds the user's names and paths (``lidar[front]``),
    shown as they are; colours are given as styles."""
    from rich.console import Console

    return Console(highlight=False, markup=False, width=None if sys.stdout.isatty() else 160)


@contextmanager
def progress(description: str, unit: str = "messages") -> Iterator[Callable[..., None]]:
    """A bar with the count, the total and the time left on stderr when it is a terminal (what
    it waits for while the total is not known); nothing otherwise. The callback takes
    ``(count, total)``."""
    if not sys.stderr.isatty():
        yield lambda count=None, total=None: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn
    from rich.table import Column
    from rich.text import Text

    class Count(ProgressColumn):
        """``12,345 of 67,890 messages, 0:00:03 left``; before the first batch, what is being
        done."""

        def render(self, task: Any) -> Text:
            said = count_text(task.completed, task.total, task.time_remaining, unit)
            return Text(said, style="progress.download")

    bar = Progress(
        # (a path, as it is; the columns of numbers keep their width where it is narrow)
        TextColumn("{task.description}", markup=False, table_column=Column(ratio=1)),
        BarColumn(bar_width=16),
        Count(),
        console=Console(stderr=True),
        transient=True,
    )
    task = bar.add_task(printable(description), total=None)
    bar.start()
    try:
        yield lambda count=None, total=None: bar.update(task, completed=count, total=total or None)
    finally:
        bar.stop()


def count_text(done: float, total: float | None, left: float | None, unit: str) -> str:
    """What the progress bar says: ``12,345 of 67,890 messages, 0:00:03 left``; before the
    total is known (the log being opened), that; once all is read, that."""
    from datetime import timedelta

    if total is None:
        return "opening the log"
    if done >= total:
        return f"all {int(total):,} {unit} read"
    time_left = "" if left is None else f", {timedelta(seconds=int(left))} left"
    return f"{int(done):,} of {int(total):,} {unit}{time_left}"


def emit(document: dict[str, Any], out: Path | None, as_json: bool, table: Any, *args: Any) -> None:
    """Write ``document`` to ``out`` (YAML/JSON by suffix), or print JSON, or print
    ``table(*args, document, width)`` (:mod:`imucal_cli.tables`, fitted to stdout's width; one
    that yields several tables prints each as it is made)."""
    from imucal_cli.documents import dump_chunks, write_document

    if out is not None:
        write_document(out, document)
    elif as_json:
        for text in dump_chunks(document, as_json=True):
            typer.echo(text, nl=False)
    else:
        shown = console()
        made = table(*args, document, shown.width)
        for each in made if isinstance(made, Iterator) else [made]:
            shown.print(each)


def note_read(log: Path, counts: dict[str, dict[str, int]]) -> None:
    """One line on stderr per topic whose reading sorted, replaced or dropped anything."""
    for topic, counted in counts.items():
        changed = {k: v for k, v in counted.items() if k != "messages" and v}
        if changed:
            details = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in changed.items())
            err(f"imucal: note: {log} [{topic}]: {counted['messages']} messages; {details}")


def note_losses(log: Path, losses: list[Any]) -> None:
    """One line on stderr per part of the log that could not be read (at most five, then a
    count); ``losses`` are :class:`~imucal_cli.io.base.Loss` es or a document's ``losses``."""
    for loss in losses[:5]:
        if isinstance(loss, dict):  # (a document lists only what was lost)
            err(f"imucal: warning: {log}: {loss['reason']}")
        else:  # a note says how the log was read, nothing lost
            err(f"imucal: {'warning' if loss.lost else 'note'}: {log}: {loss.describe()}")
    if len(losses) > 5:
        err(f"imucal: warning: {log}: {len(losses) - 5} more damaged parts not read")


def report(out: Path, calibration: Any) -> None:
    """The report's figures and page into ``out``, with a bar; its page said on stderr."""
    from imucal_cli.api import write_report

    with progress("drawing the report", "figures") as bar:
        written = write_report(out, calibration, bar)
    err(f"imucal: report: {written[-1]}")
