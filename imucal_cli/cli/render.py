"""What the commands show: progress on stderr, tables on stdout, status lines, and documents
written or printed."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
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


def table(
    title: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[Any]],
    right: Iterable[str] = (),
    no_wrap: Iterable[str] = (),
) -> Any:
    """A rich table on stdout, the ``right`` columns right-justified (numbers); returns the
    console (for what follows the table). Where the terminal is too narrow for it
    (:func:`fitted`), each row is stacked instead: no value is ever cut."""
    shown = console()
    shown.print(fitted(title, columns, rows, shown.width, right, no_wrap))
    return shown


def fitted(
    title: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[Any]],
    width: int,
    right: Iterable[str] = (),
    no_wrap: Iterable[str] = (),
) -> Any:
    """A table of ``rows`` that fits ``width`` columns, its cells wrapped between words; where
    even that does not fit (rich would then cut numbers short, ``[4.348…``), each row stacked
    as lines of ``column  value`` under its first cell."""
    from rich.console import Console, Group
    from rich.measure import Measurement
    from rich.table import Table
    from rich.text import Text

    out = Table(title=printable(title))
    right, no_wrap = set(right), set(no_wrap)
    for column in columns:
        out.add_column(
            column,
            justify="right" if column in right else "left",
            no_wrap=column in no_wrap,
            overflow="fold",  # (never an ellipsis in place of digits)
        )
    kept = [[printable(cell) if isinstance(cell, str) else cell for cell in row] for row in rows]
    for row in kept:
        out.add_row(*row)
    wide = Console(width=1 << 16)
    if Measurement.get(wide, wide.options, out).minimum <= width:
        return out
    label = max(len(column) for column in columns[1:]) if len(columns) > 1 else 0
    lines = [Text(printable(title), style="bold")]
    for row in kept:
        lines.append(Text.assemble(row[0] if isinstance(row[0], Text) else str(row[0])))
        for column, cell in zip(columns[1:], row[1:], strict=True):
            value = cell if isinstance(cell, Text) else Text(str(cell))
            lines.append(Text.assemble(f"  {column:<{label}}  ", value))
    return Group(*lines)


def emit(document: dict[str, Any], out: Path | None, as_json: bool, render: Any) -> None:
    """Write ``document`` to ``out`` (YAML/JSON by suffix), or print JSON, or render it."""
    from imucal_cli.documents import dump_chunks, write_document

    if out is not None:
        write_document(out, document)
    elif as_json:
        for text in dump_chunks(document, as_json=True):
            typer.echo(text, nl=False)
    else:
        render(document)


def fmt(values: Any, digits: int) -> str:
    if values is None:
        return "-"
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"


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


def status_lines(document: dict[str, Any]) -> None:
    """Where the readable summary is not printed (``-o``, ``--json``): each sensor's status
    with its worst std, then each of its warnings, one line each on stderr, so that a terminal
    or a job's log shows what is wrong without opening the output."""
    for name, sensor in document["sensors"].items():
        line = f"imucal: {name}: {sensor['status']}"
        if sensor["rotation_std_deg"] is not None:
            line += f", std {max(sensor['rotation_std_deg']):.3g} deg"
        if sensor["translation_std_m"] is not None:
            line += f" and {1000 * max(sensor['translation_std_m']):.3g} mm (worst axis)"
        err(f"{line}, {sensor['segments']['selected']}/{sensor['segments']['total']} windows")
        for warning in sensor["warnings"]:
            err(f"imucal: {name}: {warning}")


def report(out: Path, calibration: Any) -> None:
    """The report's figures and page into ``out``, with a bar; its page said on stderr."""
    from imucal_cli.api import write_report

    with progress("drawing the report", "figures") as bar:
        written = write_report(out, calibration, bar)
    err(f"imucal: report: {written[-1]}")
