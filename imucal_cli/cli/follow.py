"""``calibrate --follow``: what each sensor has and waits for, an update per window (a JSON
line with --json, a table on a terminal, else a line on stderr), then the last estimate with
each sensor's missing axes and why it stopped."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import typer

from imucal_cli import tables
from imucal_cli.cli import render
from imucal_cli.cli.app import EXIT_CHECK_FAILED, err, interrupted

#: After how long without news of the recording the wait is said (s of wall time).
FOLLOW_STALL_S = 30.0


class _View:
    """How the follow is shown: JSON lines, a live table on a terminal, or lines on stderr;
    and the stalls of the recording said."""

    def __init__(self, log: Path, as_json: bool, deadline: float | None) -> None:
        self.log, self.as_json, self.deadline = log, as_json, deadline
        self.live = None
        if not as_json and sys.stderr.isatty():  # a table on the terminal, redrawn each window
            from rich.console import Console
            from rich.live import Live

            self.live = Live(console=Console(stderr=True), auto_refresh=False)
        self.heard, self.stalled, self.told = time.monotonic(), -1e9, -1e9

    def _show(self, line: dict[str, Any], table: Any, lines: Callable[[], list[str]]) -> None:
        """A JSON line, the live table (``table(width)``) or ``lines()`` on stderr."""
        from imucal_cli.documents import to_plain

        self.heard = time.monotonic()
        if self.as_json:
            typer.echo(json.dumps(to_plain(line)))
        elif self.live is not None:
            self.live.update(table(self.live.console.width), refresh=True)
        else:
            for text in lines():
                err(f"imucal: {text}")

    def window(self, calibration: Any, windows: int) -> None:
        followed = calibration.follow_line(windows)  # (once: the JSON, the table or the lines)
        table = partial(tables.follow, self.log, followed, calibration.config.stop)
        self._show(followed, table, partial(tables.follow_lines, followed))

    def waiting(self, state: dict[str, Any]) -> None:  # before the first estimate
        def lines() -> list[str]:  # (in a log file: every 5 s)
            if time.monotonic() - self.told < 5.0:
                return []
            self.told = time.monotonic()
            return [tables.waiting_line(self.log, state)]

        self._show({"windows": 0, **state}, partial(tables.waiting, self.log, state), lines)

    def timed_out(self) -> bool:  # (asked at every poll of the recording)
        now = time.monotonic()
        if now - self.heard >= FOLLOW_STALL_S and now - self.stalled >= FOLLOW_STALL_S:
            self.stalled = now  # a recording that stalls: said, not waited for in silence
            err(
                f"imucal: {self.log}: nothing new for {now - self.heard:.0f} s; still waiting"
                + (" (--timeout not given: Ctrl-C ends it)" if self.deadline is None else "")
            )
        return self.deadline is not None and now > self.deadline


def follow_log(
    log: Path,
    config_path: Path,
    out: Path | None,
    as_json: bool,
    until_converged: bool,
    timeout: float | None,
    report: Path | None = None,
    urdf: Path | None = None,
) -> None:
    """calibrate --follow, shown and written; exit codes as the SPEC says."""
    from imucal_cli import api
    from imucal_cli.documents import write_document
    from imucal_cli.pipeline import WAIT_FOR_LOG_S

    deadline = None if timeout is None else time.monotonic() + timeout
    # the log, and the tree of a config that leaves transforms out: waited for within --timeout
    limit = deadline if deadline is not None else time.monotonic() + WAIT_FOR_LOG_S
    api.wait_for_log(log, limit, lambda: err(f"imucal: waiting for {log} to be created"))
    config, note = api.recording_config(config_path, log, limit, urdf)
    if note:
        err(f"imucal: note: {note}")
    view = _View(log, as_json, deadline)
    if view.live is not None:
        view.live.start()
    try:
        calibration, stopped = api.follow(
            log,
            config,
            on_window=view.window,
            on_waiting=view.waiting,
            stop=view.timed_out,
            until_converged=until_converged,
        )
    finally:
        if view.live is not None:
            view.live.stop()
    out_of_time = view.timed_out()  # why it stopped (the report below takes time of its own)
    document = calibration.document()
    render.note_losses(log, document["losses"])  # (garbage appended to a recording, say)
    if report is not None:
        render.report(report, calibration)
    if out is not None:
        write_document(out, document)
    for name, s in document["sensors"].items():
        for line in s["missing"]:
            err(f"imucal: {name}: missing {line}")
    if stopped:
        raise interrupted()
    good = calibration.converged
    if not (until_converged and good):
        err("imucal: --timeout reached" if out_of_time else f"imucal: the recording {log} ended")
    if until_converged and not good:
        err("imucal: not converged" + (" before --timeout" if out_of_time else ""))
        raise typer.Exit(EXIT_CHECK_FAILED)
