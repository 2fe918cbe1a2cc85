"""Fleet runs: one calibration per log, in local processes or on a Dask cluster, with a summary
(CSV, JSON, JUnit XML) of every log and sensor against truth files or a reference calibration.

Every task is :func:`run_one`: it calibrates one log and returns the summary rows and its
calibrate document, which the batch's own process writes into the output folder (a worker
that is lost writes nothing); it never raises (a broken log is a failed row), so one bad log
never stops the others. The same function runs under ``--jobs N`` (a process per log) and
``--scheduler tcp://...`` (``dask.distributed``, the optional extra ``imucal[fleet]``); results
do not depend on where a task ran.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any
from xml.sax import saxutils

import numpy as np

from imucal_cli.config import Config
from imucal_cli.errors import ImucalError, InputError, Terminated
from imucal_cli.names import printable
from imucal_cli.paths import log_folder
from imucal_cli.types import Transform

#: A sensor moved when its calibration and the reference differ by more than this many
#: combined std (largest axis of each); where a std is not known, the fallbacks below.
MOVED_STD = 3.0
MOVED_FALLBACK_DEG, MOVED_FALLBACK_M = 0.1, 0.02
#: How long a batch waits for a Dask worker to join its scheduler (s).
DASK_WORKERS_S = 30.0

#: Log file suffixes a batch output's name drops (``2024.01.05.mcap`` -> ``2024.01.05.yaml``).
LOG_SUFFIXES = (".mcap", ".bag", ".db3")

SUMMARY_COLUMNS = (
    "log",
    "sensor",
    "status",
    "x_m",
    "y_m",
    "z_m",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "rotation_std_deg",
    "translation_std_m",
    "rotation_error_deg",
    "translation_error_m",
    "moved",
    "lost_s",
    "dropped",
    "warnings",
    "pass",
    "error",
)


@dataclass(frozen=True)
class Task:
    """One log's calibration, self-contained: absolute paths and the config's content, so a
    worker started anywhere (another folder, another machine with the same mounts) runs it."""

    log: str  # absolute
    name: str  # the log as the summary names it: its full path
    #: The config, or the path of one that leaves transforms out (read against the log's
    #: /tf_static by the worker: a log that lacks them is that log's failed row)
    config: Config | str
    out: str  # absolute: where the calibrate document goes
    against: dict[str, Transform] | None = None  # truth or reference T_base_lidar per sensor
    against_source: str = ""  # the file they came from (for messages)
    reference: bool = (
        False  # against is the vehicle's previous calibration: past the thresholds is "moved"
    )
    max_rotation_deg: float | None = None
    max_translation_m: float | None = None
    max_lost_s: float | None = None  # None: any read loss fails the log's rows
    #: Against a reference without thresholds: per sensor its (rotation deg, translation m) std
    #: (largest axis) in the reference, for the default "moved" test (:data:`MOVED_STD`).
    reference_std: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)


@dataclass
class Row:
    log: str
    sensor: str
    status: str
    x_m: float | None = None
    y_m: float | None = None
    z_m: float | None = None
    roll_deg: float | None = None
    pitch_deg: float | None = None
    yaw_deg: float | None = None
    rotation_std_deg: float | None = None  # the largest of the three axes
    translation_std_m: float | None = None
    rotation_error_deg: float | None = None  # against truth or reference
    translation_error_m: float | None = None
    moved: bool | None = None  # against a reference: past a threshold
    lost_s: float | None = 0.0  # log time the read lost (None: not known, a log cut off mid-write)
    dropped: int = (
        0  # samples the read dropped (not decodable, not finite, clipped, ...), every topic
    )
    warnings: str = ""  # what reading lost and what the calibration warned of, "; "-separated
    passed: bool = False
    error: str = ""
    seconds: float = field(default=0.0, compare=False)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["pass"] = out.pop("passed")
        out.pop("seconds")
        return out


Outcome = tuple[list["Row"], dict[str, Any] | None]


def run_one(task: Task) -> Outcome:
    """Calibrate one log and compare: the summary rows and the calibrate document (None where
    it failed); never raises. Safe to run in any process or worker: it writes nothing (the
    process that runs the batch writes each document as it arrives, :func:`deliver`)."""
    import time

    from imucal_cli.api import calibrate_log
    from imucal_cli.outputs import transform_errors

    start = time.perf_counter()
    try:
        run = calibrate_log(task.log, task.config)
    except ImucalError as exc:
        return [
            Row(task.name, "", "failed", error=str(exc), seconds=time.perf_counter() - start)
        ], None
    except Exception as exc:
        where = traceback.extract_tb(exc.__traceback__)[-1]
        at = f"{Path(where.filename).name}:{where.lineno}"
        error = f"internal error: {type(exc).__name__}: {exc} ({at})"
        return [
            Row(task.name, "", "failed", error=error, seconds=time.perf_counter() - start)
        ], None
    lost_s, losses, dropped = (
        run.document["lost_s"],
        run.document["losses"],
        run.document["dropped"],
    )
    undecodable = sum(d.get("decode_errors", 0) for d in dropped.values())  # (counted in lost_s)
    lost_ok = not (losses or undecodable) or (
        task.max_lost_s is not None and lost_s is not None and lost_s <= task.max_lost_s
    )
    rows = []
    for sensor, s in run.document["sensors"].items():
        T = run.result.T_base_lidar(sensor)
        std_r, std_t = s["rotation_std_deg"], s["translation_std_m"]
        statistical = s.get("statistical_std") or {}  # how far two drives differ: for "moved"
        stat_r = max(statistical["rotation_deg"]) if statistical else None
        stat_t = max(statistical["translation_m"]) if statistical else None
        x, y, z = (float(v) for v in T.translation)
        roll, pitch, yaw = (float(v) for v in np.degrees(T.rpy_rad))
        row = Row(
            task.name,
            sensor,
            s["status"],
            x,
            y,
            z,
            roll,
            pitch,
            yaw,
            None if std_r is None else float(max(std_r)),
            None if std_t is None else float(max(std_t)),
            lost_s=lost_s,
            dropped=sum(sum(d.values()) for d in dropped.values()),
            warnings="; ".join([x["reason"] for x in losses] + s["warnings"]),
        )
        row.passed = s["status"] == "ok" and lost_ok
        if not lost_ok:
            limit = (
                "any loss fails (--max-lost-s)"
                if task.max_lost_s is None
                else f"--max-lost-s {task.max_lost_s:g}"
            )
            lost = "an unknown span" if lost_s is None else f"{lost_s:.2f} s"
            damaged = f" ({undecodable:,} messages not decodable)" if undecodable else ""
            row.error = f"the read lost {lost} of the log{damaged}; {limit}"
        if task.against is not None and sensor in task.against:
            errors = transform_errors(T, task.against[sensor])
            row.rotation_error_deg = errors["rotation_error_deg"]
            row.translation_error_m = errors["translation_error_m"]
            limit_r, limit_t = task.max_rotation_deg, task.max_translation_m
            if task.reference:
                ref_r, ref_t = task.reference_std.get(sensor, (None, None))
                limit_r = (
                    limit_r if limit_r is not None else _combined(stat_r, ref_r, MOVED_FALLBACK_DEG)
                )
                limit_t = (
                    limit_t if limit_t is not None else _combined(stat_t, ref_t, MOVED_FALLBACK_M)
                )
            over = (limit_r is not None and row.rotation_error_deg > limit_r) or (
                limit_t is not None and row.translation_error_m > limit_t
            )
            if over and task.reference:
                row.error = (
                    row.error
                    or f"moved: {row.rotation_error_deg:.4f} deg (limit {limit_r:.4g}), "
                    f"{row.translation_error_m:.4f} m (limit {limit_t:.4g})"
                )
            elif over:  # the threshold that failed, as evaluate names it
                row.error = row.error or "; ".join(
                    f"{name} {value:.6g} > {option} {limit:g}"
                    for name, value, option, limit in (
                        (
                            "rotation_error_deg",
                            row.rotation_error_deg,
                            "--max-rotation-deg",
                            limit_r,
                        ),
                        (
                            "translation_error_m",
                            row.translation_error_m,
                            "--max-translation-m",
                            limit_t,
                        ),
                    )
                    if limit is not None and value > limit
                )
            if task.reference:
                row.moved = bool(over)
            row.passed = row.passed and not over
        elif task.against is not None:
            row.passed = False
            missing_file = task.against_source and not Path(task.against_source).is_file()
            row.error = (
                f"{task.against_source}: no such truth file for this log"
                if missing_file
                else f"{task.against_source}: no entry for sensor {sensor}"
            )
        rows.append(row)
    elapsed = time.perf_counter() - start
    for row in rows:
        row.seconds = elapsed
    return rows, run.document


def deliver(task: Task, outcome: Outcome) -> list[Row]:
    """Write a task's document where it goes (in the process that runs the batch: a worker
    that is lost writes nothing) and return its rows; a write that fails fails the rows."""
    from imucal_cli.documents import write_document

    rows, document = outcome
    if document is not None:
        try:
            write_document(task.out, document)
        except (OSError, ImucalError) as exc:
            return [
                Row(
                    task.name,
                    "",
                    "failed",
                    error=f"{task.out}: cannot write: {getattr(exc, 'strerror', None) or exc}",
                )
            ]
    return rows


def _failed(task: Task, why: str) -> Outcome:
    return [Row(task.name, "", "failed", error=why)], None


def _combined(now: float | None, before: float | None, fallback: float) -> float:
    """:data:`MOVED_STD` combined std of two calibrations, or ``fallback`` where one is unknown."""
    if now is None or before is None:
        return fallback
    return MOVED_STD * float(np.hypot(now, before))


def run_local(
    tasks: Sequence[Task], jobs: int, on_done: Callable[[int, list[Row]], None] | None = None
) -> list[list[Row]]:
    """Every task, ``jobs`` at a time, each in a process of its own: a process that dies (the
    out-of-memory killer) fails its log alone, by name; a Ctrl-C stops the running ones and
    starts no other."""
    results: list[list[Row]] = [[] for _ in tasks]
    if jobs <= 1:
        for i, task in enumerate(tasks):
            results[i] = deliver(task, run_one(task))
            if on_done:
                on_done(i, results[i])
        return results
    import multiprocessing
    import signal
    import threading
    from multiprocessing.connection import wait

    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    context: Any = multiprocessing.get_context(method)
    waiting = list(enumerate(tasks))
    running: dict[Any, tuple[int, Any]] = {}  # result pipe -> (task number, process)
    # A Ctrl-C is noted and acted on here, between two steps: raised anywhere (in a pipe's
    # finaliser, a fork) Python may print it and carry on with the whole queue
    interrupted: list[int] = []
    main = (
        threading.current_thread() is threading.main_thread()
    )  # (only there can a handler be set)
    signals = (signal.SIGINT, signal.SIGTERM)  # (a SIGTERM ends it as a Ctrl-C does)
    previous = (
        [signal.signal(n, lambda number, frame: interrupted.append(number)) for n in signals]
        if main
        else []
    )
    try:
        while waiting or running:
            while waiting and len(running) < jobs and not interrupted:
                i, task = waiting.pop(0)
                receive, send = context.Pipe(duplex=False)
                process = context.Process(
                    target=_work, args=(task, send), name=f"imucal {task.name}", daemon=True
                )
                process.start()
                send.close()
                running[receive] = (i, process)
            if interrupted:
                raise Terminated if signal.SIGTERM in interrupted else KeyboardInterrupt
            ready: list[Any] = wait(list(running), timeout=0.2)
            for receive in ready:
                i, process = running.pop(receive)
                try:
                    outcome = receive.recv()
                except EOFError:  # it died before it answered
                    process.join()
                    outcome = _failed(
                        tasks[i],
                        f"the worker calibrating {tasks[i].log} died ({_death(process.exitcode)})",
                    )
                process.join()
                results[i] = deliver(tasks[i], outcome)
                if on_done:
                    on_done(i, results[i])
    finally:
        for number, handler in zip(signals, previous, strict=False):
            signal.signal(number, handler)
        for _, process in running.values():  # interrupted: stop what runs, start nothing more
            process.kill()
            process.join()
    return results


def _work(task: Task, send: Any) -> None:
    import signal

    signal.signal(
        signal.SIGINT, signal.SIG_IGN
    )  # a Ctrl-C is the batch's to handle: it kills this process
    send.send(run_one(task))
    send.close()


def _death(exitcode: int | None) -> str:
    import signal

    if exitcode is not None and exitcode < 0:
        name = signal.Signals(-exitcode).name
        return f"killed by {name}" + (
            ", as the out-of-memory killer does" if name == "SIGKILL" else ""
        )
    return f"exit code {exitcode}"


def run_dask(
    tasks: Sequence[Task], address: str, on_done: Callable[[int, list[Row]], None] | None = None
) -> list[list[Row]]:
    """Every task on the Dask cluster whose scheduler listens at ``address``; a scheduler
    without workers is an error, one lost mid-batch fails the logs not yet done."""
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'imucal[fleet]'"
        ) from None
    import logging

    for name in [n for n in logging.root.manager.loggerDict if n.startswith("distributed")]:
        logging.getLogger(name).setLevel(
            logging.CRITICAL + 1
        )  # a lost scheduler is said in the rows, once
    try:
        client = Client(address, timeout="10s")
    except Exception as exc:
        raise InputError(f"--scheduler {address}: cannot connect: {exc}") from None
    results: list[list[Row] | None] = [None] * len(tasks)
    try:
        try:
            client.wait_for_workers(1, timeout=DASK_WORKERS_S)
        except Exception:
            raise InputError(
                f"--scheduler {address}: no worker joined within {DASK_WORKERS_S:g} s"
            ) from None
        futures = client.map(run_one, list(tasks), pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        try:
            for future in as_completed(futures):
                i = index[future.key]
                try:
                    outcome = future.result()
                except Exception as exc:
                    lost = "connection-lost" in str(exc)
                    why = (
                        f"the scheduler at {address} was lost"
                        if lost
                        else f"worker failed: {type(exc).__name__}: "
                        f"{(str(exc).splitlines() or [''])[0]}"
                    )
                    outcome = _failed(tasks[i], why)
                results[i] = deliver(tasks[i], outcome)
                if on_done:
                    on_done(i, results[i])  # type: ignore[arg-type]
        except Exception as exc:  # the scheduler went away
            for i, task in enumerate(tasks):
                if results[i] is None:
                    results[i] = deliver(
                        task,
                        _failed(
                            task, f"the scheduler at {address} was lost ({type(exc).__name__})"
                        ),
                    )
                    if on_done:
                        on_done(i, results[i])  # type: ignore[arg-type]
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=5)
    return [r or [] for r in results]


def _shared_config(path: str) -> Config | None:
    """The config every log of the run shares, or None where it leaves transforms out: each
    log's own ``/tf_static`` (or ``/robot_description``) then gives them (SPEC)."""
    from imucal_cli.config import load_config
    from imucal_cli.errors import ConfigError
    from imucal_cli.frames import leaves_out_transforms

    try:
        return load_config(path)
    except ConfigError as exc:
        if leaves_out_transforms(exc):
            return None
        raise


def plan_tasks(
    entries: Sequence[dict[str, str]],
    config: str | Path | None,
    out_dir: Path,
    truth_dir: Path | None = None,
    reference: str | Path | None = None,
    max_rotation_deg: float | None = None,
    max_translation_m: float | None = None,
    max_lost_s: float | None = None,
) -> list[Task]:
    """One :class:`Task` per manifest entry (``log``, optional ``config``, ``truth``,
    ``reference``), named by its full path, its output ``out_dir/STEM.yaml``
    (:func:`_output_names`). Every path is resolved and
    every file read here: a worker started anywhere runs the task."""
    from imucal_cli.api import load_transforms

    if truth_dir is not None and reference is not None:
        raise InputError("--truth-dir and --reference: give one of them")
    if not entries:
        raise InputError("no logs: give LOG... or --manifest CSV")
    if truth_dir is not None and not truth_dir.is_dir():
        raise InputError(f"{truth_dir}: folder does not exist")
    paths = [log_folder(Path(e["log"]).resolve()) for e in entries]  # a rosbag2 log is its folder
    root = Path(os.path.commonpath([p.parent for p in paths]))
    configs: dict[str, Config | None] = {}
    loaded: dict[
        str, tuple[dict[str, Transform], dict[str, tuple[float | None, float | None]]]
    ] = {}  # truth or reference files
    tasks: list[Task] = []
    stems = [
        log.relative_to(root)
        .as_posix()
        .removesuffix(log.suffix if log.suffix in LOG_SUFFIXES else "")
        for log in paths
    ]
    outputs = _output_names(stems, paths)  # vehicle/2024.01.05.mcap -> 2024.01.05
    for entry, log, stem, output in zip(entries, paths, stems, outputs, strict=True):
        cfg = entry.get("config") or (str(config) if config else None)
        if cfg is None:
            raise InputError(f"{log}: no config: give -c CFG or a config column in the manifest")
        if cfg not in configs:
            configs[cfg] = _shared_config(cfg)
        # (a config that leaves transforms out is read by the worker against its log)
        job_config = configs[cfg] or str(Path(cfg).resolve())
        optional = False  # a truth file the folder may not have (then: nothing to compare with)
        if entry.get("reference") or entry.get("truth"):
            source, is_reference = (
                entry.get("reference") or entry["truth"],
                bool(entry.get("reference")),
            )
        elif truth_dir is not None:
            nested, flat = (
                truth_dir / f"{stem}.truth.yaml",
                truth_dir / f"{Path(stem).name}.truth.yaml",
            )
            source, is_reference, optional = str(nested if nested.is_file() else flat), False, True
        else:
            source, is_reference = str(reference or ""), reference is not None
        if source and source not in loaded and not (optional and not Path(source).is_file()):
            loaded[source] = load_transforms(source), _reference_std(source) if is_reference else {}
        against, std = loaded.get(source, ({} if source else None, {}))
        tasks.append(
            Task(
                str(log),
                str(log),
                job_config,
                str((out_dir / f"{output}.yaml").resolve()),
                against,
                source,
                is_reference,
                max_rotation_deg,
                max_translation_m,
                max_lost_s,
                std if is_reference else {},
            )
        )
    return tasks


def _output_names(stems: Sequence[str], paths: Sequence[Path]) -> list[str]:
    """Each log's output name in the one output folder: its file name without the log suffix,
    and where two logs share that, as many of its folders before it as tell them apart
    (``truck0/2026-11-01/drive.mcap`` and ``truck1/2026-11-02/drive.mcap``: ``2026-11-01_drive``,
    ``2026-11-02_drive``)."""
    parts = [stem.split("/") for stem in stems]
    depth = [1] * len(parts)
    while True:
        names = ["_".join(p[-d:]) for p, d in zip(parts, depth, strict=True)]
        clashes = {n for n in names if names.count(n) > 1}
        if not clashes:
            return names
        grown = False
        for k, name in enumerate(names):
            if name in clashes and depth[k] < len(parts[k]):
                depth[k] += 1
                grown = True
        if not grown:
            k = next(k for k, name in enumerate(names) if name in clashes)
            raise InputError(f"{paths[k]}: given twice: its outputs would collide")


def check_batch_outputs(
    tasks: Sequence[Task], files: Sequence[Path], inputs: Sequence[Path | None], force: bool
) -> None:
    """Before any work: no output of the batch (each log's document, the summaries, ``files``)
    is one of its inputs or inside one (a rosbag2 folder), and none exists unless ``force``
    (an earlier batch's outputs are never silently replaced)."""
    from imucal_cli.paths import check_outputs

    outputs = {f"the output of {task.log}": Path(task.out) for task in tasks} | {
        str(path.name): path for path in files
    }
    every_input = [
        *inputs,
        *(Path(task.log) for task in tasks),
        *{Path(t.config if isinstance(t.config, str) else t.config.source) for t in tasks},
        *{Path(task.against_source) for task in tasks if task.against_source},
    ]
    check_outputs(outputs, every_input)
    existing = [path for path in outputs.values() if path.exists()]
    if existing and not force:
        raise InputError(
            f"{existing[0]}: exists (an earlier batch's output?): give a new --out-dir, or --force "
            "to replace "
            f"{'it' if len(existing) == 1 else f'these {len(existing)} files'}"
        )


def _reference_std(path: str) -> dict[str, tuple[float | None, float | None]]:
    """Per sensor of a reference calibration: its largest rotation (deg) and translation (m)
    statistical std (SPEC ``statistical_std``: how far two drives differ), or its total std in
    a document without one."""
    from imucal_cli.documents import load_document

    def largest(value: Any, key: str) -> float | None:
        if value is None:
            return None
        if (
            not isinstance(value, list)
            or not value
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        ):
            raise InputError(f"{path}: {key}: expected a list of numbers, got {value!r:.60}")
        return float(max(value))

    document = load_document(path)
    sensors = document.get("sensors") if isinstance(document, dict) else None
    if not isinstance(sensors, dict) or not all(isinstance(s, dict) for s in sensors.values()):
        raise InputError(f"{path}: not a calibration (expected sensors: NAME: {{...}})")
    out = {}
    for name, s in sensors.items():
        statistical = s.get("statistical_std")
        if isinstance(statistical, dict):
            key = f"sensors.{name}.statistical_std"
            out[name] = (
                largest(statistical.get("rotation_deg"), f"{key}.rotation_deg"),
                largest(statistical.get("translation_m"), f"{key}.translation_m"),
            )
        else:
            out[name] = (
                largest(s.get("rotation_std_deg"), f"sensors.{name}.rotation_std_deg"),
                largest(s.get("translation_std_m"), f"sensors.{name}.translation_std_m"),
            )
    return out


def read_manifest(path: Path) -> list[dict[str, str]]:
    """A CSV with a ``log`` column (and optional ``config``, ``truth``, ``reference``); relative
    paths are relative to the manifest's folder."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror}") from None
    reader = csv.DictReader(io.StringIO(text))
    if not reader.fieldnames or "log" not in reader.fieldnames:
        raise InputError(f"{path}: expected a CSV with a 'log' column")
    unknown = set(reader.fieldnames) - {"log", "config", "truth", "reference"}
    if unknown:
        raise InputError(
            f"{path}: unknown column {min(unknown)!r} (expected log, config, truth, reference)"
        )
    rows = []
    for k, row in enumerate(reader, start=2):
        if not row.get("log"):
            raise InputError(f"{path}: line {k}: empty log")
        rows.append(
            {
                key: str(path.parent / value) if value and not os.path.isabs(value) else value
                for key, value in row.items()
                if value
            }
        )
    return rows


def summary_csv(rows: Iterable[Row]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(SUMMARY_COLUMNS), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v) for k, v in row.to_dict().items()})
    return out.getvalue()


def summary_json(rows: Iterable[Row], settings: dict[str, Any]) -> str:
    rows = list(rows)
    return (
        json.dumps(
            {
                "settings": settings,
                "logs": len({r.log for r in rows}),
                "failed": sum(not r.passed for r in rows),
                "rows": [r.to_dict() for r in rows],
            },
            indent=2,
        )
        + "\n"
    )


def quoteattr(text: str) -> str:
    """An XML attribute value: quoted, escaped, and without the control characters XML 1.0
    cannot hold at all (written as escapes: :func:`~imucal_cli.names.printable`)."""
    return saxutils.quoteattr(printable(text))


def escape(text: str) -> str:
    """XML character data, as :func:`quoteattr`."""
    return saxutils.escape(printable(text))


def junit_xml(rows: Sequence[Row]) -> str:
    """JUnit XML: a test case per log and sensor (a log that failed to run is one error); every
    case carries its figures and warnings in ``system-out``."""
    cases = []
    for r in rows:
        name = quoteattr(r.sensor or "calibration")
        head = f'  <testcase classname={quoteattr(r.log)} name={name} time="{r.seconds:.3f}">'
        figures = ", ".join(
            f"{k} {v:.6g}" if isinstance(v, float) else f"{k} {v}"
            for k, v in (
                ("status", r.status),
                ("rotation_error_deg", r.rotation_error_deg),
                ("translation_error_m", r.translation_error_m),
                ("moved", r.moved),
                ("lost_s", r.lost_s),
                ("dropped", r.dropped),
            )
            if v is not None
        )
        said = figures + (("; " + r.warnings) if r.warnings else "")
        out = f"<system-out>{escape(said)}</system-out>"
        if r.status == "failed":
            cases.append(f"{head}<error message={quoteattr(r.error)}/>{out}</testcase>")
        elif not r.passed:
            why = r.error or (
                f"status {r.status}"
                + (
                    ""
                    if r.rotation_error_deg is None
                    else f", rotation error {r.rotation_error_deg:.4f} deg, "
                    f"translation error {r.translation_error_m:.4f} m"
                )
                + (", moved" if r.moved else "")
            )
            cases.append(f"{head}<failure message={quoteattr(why)}/>{out}</testcase>")
        else:
            cases.append(f"{head}{out}</testcase>")
    failures = sum(1 for r in rows if not r.passed and r.status != "failed")
    errors = sum(1 for r in rows if r.status == "failed")
    total = sum(r.seconds for r in {(r.log): r for r in rows}.values())
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuites><testsuite name="imucal batch" tests="{len(rows)}" failures="{failures}" '
        f'errors="{errors}" time="{total:.3f}">\n'
        + "\n".join(cases)
        + "\n</testsuite></testsuites>\n"
    )


def evaluate_junit(document: dict[str, Any], estimate: str, truth: str) -> str:
    """JUnit XML of an ``evaluate`` document: a case per sensor and pair, failing with the
    threshold and the measured value; every case carries its errors in ``system-out``; a
    sensor in one file only is a failed case (an error when ``--allow-missing`` was not given)."""
    limits = document["thresholds"]
    allowed = document["pass"] or not (
        document["missing"]["estimate_only"] or document["missing"]["truth_only"]
    )
    cases, failures = [], 0
    for group in ("sensors", "pairs"):
        for name, row in document[group].items():
            values = (
                f"rotation_error_deg {row['rotation_error_deg']:.6g}, "
                f"translation_error_m {row['translation_error_m']:.6g}"
            )
            over = [
                f"{value} {row[value]:.6g} > {key} {limits[key]:g}"
                for key, value in (
                    ("max_rotation_deg", "rotation_error_deg"),
                    ("max_translation_m", "translation_error_m"),
                )
                if limits[key] is not None and row[value] > limits[key]
            ]
            failures += bool(over)
            body = f"<failure message={quoteattr('; '.join(over))}/>" if over else ""
            cases.append(
                f"  <testcase classname={quoteattr(group)} "
                f"name={quoteattr(name)}>{body}<system-out>{escape(values)}</system-out></testcase>"
            )
    for side, names in document["missing"].items():
        for name in names:
            where = f"in {estimate} only" if side == "estimate_only" else f"in {truth} only"
            failures += not allowed
            body = "" if allowed else f"<failure message={quoteattr(f'sensor {name} is {where}')}/>"
            cases.append(
                '  <testcase classname="missing" '
                f"name={quoteattr(name)}>{body}<system-out>{escape(where)}</system-out></testcase>"
            )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuites><testsuite name="imucal evaluate" tests="{len(cases)}" failures="{failures}" '
        'errors="0">\n' + "\n".join(cases) + "\n</testsuite></testsuites>\n"
    )
