"""``calibrate --follow``: what each sensor has and waits for, an update per window (a JSON
line with --json, a table on a terminal, else a line on stderr), then the last estimate with
each sensor's missing axes and why it stopped."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import typer

from imucal_cli.cli import render
from imucal_cli.cli.app import EXIT_CHECK_FAILED, err, interrupted

#: After how long without news of the recording the wait is said (s of wall time).
FOLLOW_STALL_S = 30.0


def follow_table(log: Path, windows: int, calibration: Any, width: int = 1 << 16) -> Any:
    """The live view: per sensor its status, the estimate (``T_base_lidar``), its statistical
    std (what ``stop:`` tests: what more driving shrinks) against the targets, the windows used
    and what it lacks; stacked where ``width`` is too narrow for a table."""
    stop = calibration.config.stop
    rows = []
    for name, line in calibration.follow_line(windows)["sensors"].items():  # (as a row)
        T, std = line["T_base_lidar"], line["statistical_std"] or {}
        rows.append(
            (
                name,
                line["status"],
                render.fmt(T["translation"], 4),
                render.fmt(T["rpy_deg"], 3),
                render.fmt(std.get("rotation_deg"), 4),
                render.fmt(_mm(std.get("translation_m")), 2),
                line["windows"],
                " ".join(_axis(m) for m in line["missing"]) or "-",
            )
        )
    columns = (
        "sensor",
        "status",
        "xyz m",
        "rpy deg",
        f"std rpy deg (stop {stop.max_rotation_std_deg:g})",
        f"std xyz mm (stop {1000 * stop.max_translation_std_m:g})",
        "windows used",
        "missing axes",
    )
    return render.fitted(f"following {log}: {windows} windows", columns, rows, width)


def _axis(missing: str) -> str:
    """A missing axis in short: ``roll``, ``pitch``, ``yaw``, ``tx``, ``ty``, ``tz``."""
    name = missing.split(":")[0]
    return name[name.find("(") + 1 : -1] if "(" in name else "t" + name.split()[-1]


def _mm(values: Any) -> Any:
    return None if values is None else [1000 * v for v in values]


def _waiting_table(log: Path, state: dict[str, Any], width: int = 1 << 16) -> Any:
    """The table before the first estimate: per sensor, samples and what it waits for (the
    counts right-justified; stacked where ``width`` is too narrow)."""
    rows = [
        (name, f"{s['samples']:,}", str(s["windows"]), s["waiting_for"])
        for name, s in state["sensors"].items()
    ]
    return render.fitted(
        f"following {log}: base {state['base_samples']:,} samples",
        ("sensor", "samples", "windows", "waiting for"),
        rows,
        width,
        right=("samples", "windows"),
    )


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

    def window(self, calibration: Any, windows: int) -> None:
        from imucal_cli.documents import to_plain

        self.heard = time.monotonic()
        if self.as_json:
            typer.echo(json.dumps(to_plain(calibration.follow_line(windows))))
        elif self.live is not None:
            width = self.live.console.width
            self.live.update(follow_table(self.log, windows, calibration, width), refresh=True)
        else:
            for name, line in calibration.follow_line(windows)["sensors"].items():
                T, std = line["T_base_lidar"], line["statistical_std"] or {}
                missing = " ".join(_axis(m) for m in line["missing"]) or "none"
                err(
                    f"imucal: {windows} windows: {name} {line['status']} xyz "
                    f"{render.fmt(T['translation'], 4)} m rpy {render.fmt(T['rpy_deg'], 3)} deg, "
                    f"statistical std {render.fmt(std.get('rotation_deg'), 4)} deg "
                    f"{render.fmt(_mm(std.get('translation_m')), 2)} mm; missing: {missing}"
                )

    def waiting(self, state: dict[str, Any]) -> None:  # before the first estimate
        from imucal_cli.documents import to_plain

        self.heard = time.monotonic()
        if self.as_json:
            typer.echo(json.dumps(to_plain({"windows": 0, **state})))
        elif self.live is not None:
            width = self.live.console.width
            self.live.update(_waiting_table(self.log, state, width), refresh=True)
        elif time.monotonic() - self.told >= 5.0:  # (a log file: every 5 s)
            self.told = time.monotonic()
            first: dict[str, Any] = next(iter(state["sensors"].values()), {})
            samples = (f"{n} {v['samples']:,} samples" for n, v in state["sensors"].items())
            err(
                f"imucal: following {self.log}: {', '.join(samples)}; waiting for "
                f"{first.get('waiting_for', 'data')}"
            )

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
