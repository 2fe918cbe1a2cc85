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
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.config import Config
from imucal_cli.errors import ImucalError, InputError, Terminated
from imucal_cli.io.formats import LOG_SUFFIXES
from imucal_cli.names import quoteattr, xml_text
from imucal_cli.paths import log_folder
from imucal_cli.types import Transform

#: A sensor moved when its calibration and the reference differ by more than this many
#: combined std (largest axis of each); where a std is not known, the fallbacks below.
MOVED_STD = 3.0
MOVED_FALLBACK_DEG, MOVED_FALLBACK_M = 0.1, 0.02
#: How long a batch waits for a Dask worker to join its scheduler (s).
DASK_WORKERS_S = 30.0


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

    from imucal_cli.api import calibrate

    start = time.perf_counter()
    try:
        calibration = calibrate(task.log, task.config)
    except ImucalError as exc:
        error = str(exc)
    except Exception as exc:
        where = traceback.extract_tb(exc.__traceback__)[-1]
        at = f"{Path(where.filename).name}:{where.lineno}"
        error = f"internal error: {type(exc).__name__}: {exc} ({at})"
    else:
        document = calibration.document()
        read_error = _read_error(task, document)
        rows = []
        for name, s in document["sensors"].items():
            T = calibration.T_base_lidar(name)
            rows.append(_compared(task, _row(task, name, s, T, document, read_error), s, T))
        for row in rows:
            row.seconds = time.perf_counter() - start
        return rows, document
    return [Row(task.name, "", "failed", error=error, seconds=time.perf_counter() - start)], None


def _read_error(task: Task, document: dict[str, Any]) -> str:
    """Why what the read lost fails the log ("" where it does not: nothing lost, or within
    ``--max-lost-s``)."""
    lost_s, losses, dropped = document["lost_s"], document["losses"], document["dropped"]
    undecodable = sum(d.get("decode_errors", 0) for d in dropped.values())  # (counted in lost_s)
    if not (losses or undecodable) or (
        task.max_lost_s is not None and lost_s is not None and lost_s <= task.max_lost_s
    ):
        return ""
    limit = (
        "any loss fails (--max-lost-s)"
        if task.max_lost_s is None
        else f"--max-lost-s {task.max_lost_s:g}"
    )
    lost = "an unknown span" if lost_s is None else f"{lost_s:.2f} s"
    damaged = f" ({undecodable:,} messages not decodable)" if undecodable else ""
    return f"the read lost {lost} of the log{damaged}; {limit}"


def _row(
    task: Task,
    sensor: str,
    s: dict[str, Any],
    T: Transform,
    document: dict[str, Any],
    read_error: str,
) -> Row:
    """A sensor's summary row from the calibrate document and its part of it."""
    losses = [x["reason"] for x in document["losses"]]
    dropped = sum(sum(d.values()) for d in document["dropped"].values())
    std_r, std_t = s["rotation_std_deg"], s["translation_std_m"]
    x, y, z = (float(v) for v in T.translation)
    roll, pitch, yaw = (float(v) for v in np.degrees(T.rpy_rad))
    row = Row(
        task.name,
        sensor,
        s["status"],
        *(x, y, z, roll, pitch, yaw),
        None if std_r is None else float(max(std_r)),
        None if std_t is None else float(max(std_t)),
        lost_s=document["lost_s"],
        dropped=dropped,
        warnings="; ".join([*losses, *s["warnings"]]),
        error=read_error,
    )
    row.passed = s["status"] == "ok" and not read_error
    return row


def _limits(task: Task, s: dict[str, Any]) -> tuple[float | None, float | None]:
    """The thresholds a sensor is held to: the task's, else (against a reference) the two
    calibrations' combined statistical std, or the fallback where one is not known."""
    limit_r, limit_t = task.max_rotation_deg, task.max_translation_m
    if not task.reference:
        return limit_r, limit_t
    statistical = s.get("statistical_std") or {}  # how far two drives differ: for "moved"
    stat_r = max(statistical["rotation_deg"]) if statistical else None
    stat_t = max(statistical["translation_m"]) if statistical else None
    ref_r, ref_t = task.reference_std.get(s["_name"], (None, None))
    return (
        limit_r if limit_r is not None else _combined(stat_r, ref_r, MOVED_FALLBACK_DEG),
        limit_t if limit_t is not None else _combined(stat_t, ref_t, MOVED_FALLBACK_M),
    )


def _compared(task: Task, row: Row, s: dict[str, Any], T: Transform) -> Row:
    """The row compared with the task's truth or reference, where it has one."""
    from imucal_cli.outputs import transform_errors

    if task.against is None:
        return row
    if row.sensor not in task.against:
        missing_file = task.against_source and not Path(task.against_source).is_file()
        row.passed = False
        row.error = (
            f"{task.against_source}: no such truth file for this log"
            if missing_file
            else f"{task.against_source}: no entry for sensor {row.sensor}"
        )
        return row
    errors = transform_errors(T, task.against[row.sensor])
    row.rotation_error_deg = errors["rotation_error_deg"]
    row.translation_error_m = errors["translation_error_m"]
    limit_r, limit_t = _limits(task, {**s, "_name": row.sensor})
    over = [
        (name, value, option, limit)
        for name, value, option, limit in (
            ("rotation_error_deg", row.rotation_error_deg, "--max-rotation-deg", limit_r),
            ("translation_error_m", row.translation_error_m, "--max-translation-m", limit_t),
        )
        if limit is not None and value > limit
    ]
    if over and task.reference:
        row.error = row.error or (
            f"moved: {row.rotation_error_deg:.4f} deg (limit {limit_r:.4g}), "
            f"{row.translation_error_m:.4f} m (limit {limit_t:.4g})"
        )
    elif over:  # the threshold that failed, as evaluate names it
        row.error = row.error or "; ".join(f"{n} {v:.6g} > {o} {lim:g}" for n, v, o, lim in over)
    if task.reference:
        row.moved = bool(over)
    row.passed = row.passed and not over
    return row


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

    def done(i: int, outcome: Outcome) -> None:
        results[i] = deliver(tasks[i], outcome)
        if on_done:
            on_done(i, results[i])

    if jobs <= 1:
        for i, task in enumerate(tasks):
            done(i, run_one(task))
        return results
    from multiprocessing.connection import wait

    waiting = list(enumerate(tasks))
    running: dict[Any, tuple[int, Any]] = {}  # result pipe -> (task number, process)
    with _signals_noted() as interrupted:
        try:
            while waiting or running:
                while waiting and len(running) < jobs and not interrupted:
                    i, task = waiting.pop(0)
                    running[_start(task)] = (i, task)
                if interrupted:
                    raise Terminated if interrupted[0] == "SIGTERM" else KeyboardInterrupt
                for receive in wait(list(running), timeout=0.2):
                    i, _ = running.pop(receive)
                    done(i, _outcome(tasks[i], receive))
        finally:
            for receive in running:  # interrupted: stop what runs, start nothing more
                receive.process.kill()
                receive.process.join()
    return results


@contextlib.contextmanager
def _signals_noted() -> Any:
    """A Ctrl-C or SIGTERM noted (their names, in the list yielded) and acted on by the
    caller between two steps: raised anywhere (in a pipe's finaliser, a fork) Python may print
    it and carry on with the whole queue. Only the main thread can set handlers."""
    import signal
    import threading

    noted: list[str] = []
    numbers = (signal.SIGINT, signal.SIGTERM)
    main = threading.current_thread() is threading.main_thread()
    previous = [
        signal.signal(n, lambda number, frame: noted.append(signal.Signals(number).name))
        for n in (numbers if main else ())
    ]
    try:
        yield noted
    finally:
        for number, handler in zip(numbers, previous, strict=False):
            signal.signal(number, handler)


def _start(task: Task) -> Any:
    """A process calibrating ``task``; the receiving end of its pipe (``.process``: it)."""
    import multiprocessing

    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    context: Any = multiprocessing.get_context(method)
    receive, send = context.Pipe(duplex=False)
    process = context.Process(
        target=_work, args=(task, send), name=f"imucal {task.name}", daemon=True
    )
    process.start()
    send.close()
    receive.process = process
    return receive


def _outcome(task: Task, receive: Any) -> Outcome:
    """What a worker process answered; a worker that died fails its log, saying how."""
    try:
        outcome = receive.recv()
    except EOFError:  # it died before it answered
        receive.process.join()
        why = _death(receive.process.exitcode)
        outcome = _failed(task, f"the worker calibrating {task.log} died ({why})")
    receive.process.join()
    return outcome


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
    from dask.distributed import as_completed

    results: list[list[Row] | None] = [None] * len(tasks)

    def done(i: int, outcome: Outcome) -> None:
        results[i] = deliver(tasks[i], outcome)
        if on_done:
            on_done(i, results[i] or [])

    client = _client(address)
    try:
        futures = client.map(run_one, list(tasks), pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        try:
            for future in as_completed(futures):
                i = index[future.key]
                try:
                    outcome = future.result()
                except Exception as exc:
                    outcome = _failed(tasks[i], _lost(address, exc))
                done(i, outcome)
        except Exception as exc:  # the scheduler went away
            lost = f"the scheduler at {address} was lost ({type(exc).__name__})"
            for i in [i for i, r in enumerate(results) if r is None]:
                done(i, _failed(tasks[i], lost))
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=5)
    return [r or [] for r in results]


def _client(address: str) -> Any:
    """A Dask client of the scheduler at ``address`` with a worker; errors said as the
    option's. Dask's own loggers are quieted: a lost scheduler is said in the rows, once."""
    try:
        from dask.distributed import Client
    except ImportError:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'imucal[fleet]'"
        ) from None
    import logging

    for name in [n for n in logging.root.manager.loggerDict if n.startswith("distributed")]:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)
    try:
        client = Client(address, timeout="10s")
    except Exception as exc:
        raise InputError(f"--scheduler {address}: cannot connect: {exc}") from None
    try:
        client.wait_for_workers(1, timeout=DASK_WORKERS_S)
    except Exception:
        with contextlib.suppress(Exception):
            client.close(timeout=5)
        raise InputError(
            f"--scheduler {address}: no worker joined within {DASK_WORKERS_S:g} s"
        ) from None
    return client


def _lost(address: str, exc: Exception) -> str:
    if "connection-lost" in str(exc):
        return f"the scheduler at {address} was lost"
    return f"worker failed: {type(exc).__name__}: {(str(exc).splitlines() or [''])[0]}"


def _shared_config(path: str) -> Config | None:
    """The config every log of the run shares, or None where it leaves a transform out (the
    base IMU's pose included): each log's own ``/tf_static`` (or ``/robot_description``) then
    gives it, as ``calibrate`` takes it (SPEC). An invalid one is said here, once."""
    from imucal_cli.priors import config_alone

    config, partial = config_alone(path)
    return None if partial else config


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
    stems, outputs = _stems(paths)
    configs: dict[str, Config | None] = {}
    loaded: dict[
        str, tuple[dict[str, Transform], dict[str, tuple[float | None, float | None]]]
    ] = {}  # truth or reference files
    tasks: list[Task] = []
    for entry, log, stem, output in zip(entries, paths, stems, outputs, strict=True):
        cfg = entry.get("config") or (str(config) if config else None)
        if cfg is None:
            raise InputError(f"{log}: no config: give -c CFG or a config column in the manifest")
        if cfg not in configs:
            configs[cfg] = _shared_config(cfg)
        # (a config that leaves transforms out is read by the worker against its log)
        job_config = configs[cfg] or str(Path(cfg).resolve())
        source, is_reference, optional = _against(entry, stem, truth_dir, reference)
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


def _stems(paths: list[Path]) -> tuple[list[str], list[str]]:
    """Each log's path from the logs' common folder without its log suffix, and its output's
    name (:func:`_output_names`: vehicle/2024.01.05.mcap -> 2024.01.05)."""
    root = Path(os.path.commonpath([p.parent for p in paths]))
    stems = [
        log.relative_to(root)
        .as_posix()
        .removesuffix(log.suffix if log.suffix in LOG_SUFFIXES else "")
        for log in paths
    ]
    return stems, _output_names(stems, paths)


def _against(
    entry: dict[str, str], stem: str, truth_dir: Path | None, reference: str | Path | None
) -> tuple[str, bool, bool]:
    """What a log is compared with: the file ("" for nothing), whether it is a reference (a
    previous calibration) rather than a truth, and whether it may be missing (a truth folder
    need not hold every log's: then there is nothing to compare with)."""
    if entry.get("reference") or entry.get("truth"):
        return entry.get("reference") or entry["truth"], bool(entry.get("reference")), False
    if truth_dir is not None:
        nested = truth_dir / f"{stem}.truth.yaml"
        flat = truth_dir / f"{Path(stem).name}.truth.yaml"
        return str(nested if nested.is_file() else flat), False, True
    return str(reference or ""), reference is not None, False


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
        named = ", ".join(str(path) for path in existing[:3])
        more = f" and {len(existing) - 3} more" if len(existing) > 3 else ""
        raise InputError(
            f"{named}{more}: {'exists' if len(existing) == 1 else 'exist'} (an earlier batch's "
            f"output?): give a new --out-dir, or --force to replace "
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
    columns = [f.name for f in fields(Row) if f.compare]  # (as Row.to_dict names them)
    columns[columns.index("passed")] = "pass"
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
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
        out = f"<system-out>{xml_text(said)}</system-out>"
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
    from imucal_cli.outputs import THRESHOLDS, over_thresholds

    limits = document["thresholds"]
    allowed = document["pass"] or not (
        document["missing"]["estimate_only"] or document["missing"]["truth_only"]
    )
    cases, failures = [], 0
    for group in ("sensors", "pairs"):
        for name, row in document[group].items():
            values = ", ".join(
                f"{error} {row[error]:.6g}" for _, error in THRESHOLDS if row.get(error) is not None
            )
            over = [
                f"{value} {row[value]:.6g} > {key} {limits[key]:g}"
                for key, value in over_thresholds(row, limits)
            ]
            failures += bool(over)
            body = f"<failure message={quoteattr('; '.join(over))}/>" if over else ""
            cases.append(
                f"  <testcase classname={quoteattr(group)} "
                f"name={quoteattr(name)}>{body}<system-out>{xml_text(values)}</system-out></testcase>"
            )
    for side, names in document["missing"].items():
        for name in names:
            where = f"in {estimate} only" if side == "estimate_only" else f"in {truth} only"
            failures += not allowed
            body = "" if allowed else f"<failure message={quoteattr(f'sensor {name} is {where}')}/>"
            cases.append(
                '  <testcase classname="missing" '
                f"name={quoteattr(name)}>{body}<system-out>{xml_text(where)}</system-out></testcase>"
            )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuites><testsuite name="imucal evaluate" tests="{len(cases)}" failures="{failures}" '
        'errors="0">\n' + "\n".join(cases) + "\n</testsuite></testsuites>\n"
    )


@dataclass
class Batch:
    """A batch of logs, as ``imucal batch`` gives it: the logs (``entries``, a manifest's
    rows), their config, where the outputs go, what each is compared with and how."""

    entries: list[dict[str, str]]
    config: Path | None
    out_dir: Path
    truth_dir: Path | None = None
    reference: Path | None = None
    max_rotation_deg: float | None = None
    max_translation_m: float | None = None
    max_lost_s: float | None = None
    junit: Path | None = None
    manifest: Path | None = None

    def plan(self, force: bool) -> list[Task]:
        """The tasks, every input read and every output checked before any work."""
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise InputError(f"{self.out_dir}: --out-dir exists and is not a folder")
        given = [f"--max-{k}" for k, v in self._limits().items() if v is not None]
        against = self.truth_dir or self.reference
        if (
            given
            and against is None
            and not all(e.get("truth") or e.get("reference") for e in self.entries)
        ):
            raise InputError(
                f"{given[0]}: nothing to compare with: give --truth-dir or --reference "
                "(or truth/reference columns in the manifest for every log)"
            )
        tasks = plan_tasks(
            self.entries,
            self.config,
            self.out_dir,
            self.truth_dir,
            self.reference,
            self.max_rotation_deg,
            self.max_translation_m,
            self.max_lost_s,
        )
        summaries = [self.out_dir / "summary.csv", self.out_dir / "summary.json"]
        inputs = [self.manifest, self.reference, self.config]
        check_batch_outputs(
            tasks, [*summaries, *([self.junit] if self.junit else [])], inputs, force
        )
        return tasks

    def _limits(self) -> dict[str, float | None]:
        return {"rotation-deg": self.max_rotation_deg, "translation-m": self.max_translation_m}

    def moved_rule(self) -> str | None:
        """With ``reference`` and a threshold not given: the rule that says a sensor moved."""
        if self.reference is None or None not in self._limits().values():
            return None
        given = "".join(f"; --max-{k} {v:g}" for k, v in self._limits().items() if v is not None)
        return (
            f"--reference: a sensor moved past {MOVED_STD:g} combined std of the two calibrations "
            f"(largest axis; {MOVED_FALLBACK_DEG:g} deg, {MOVED_FALLBACK_M:g} m where a std is "
            f"not known){given}"
        )

    def settings(self, jobs: int, scheduler: str | None) -> dict[str, Any]:
        return {
            "jobs": jobs,
            "scheduler": scheduler,
            "max_rotation_deg": self.max_rotation_deg,
            "max_translation_m": self.max_translation_m,
            "max_lost_s": self.max_lost_s,
            "truth_dir": str(self.truth_dir) if self.truth_dir else None,
            "reference": str(self.reference) if self.reference else None,
        }

    def summarise(self, rows: list[Row], settings: dict[str, Any]) -> None:
        """The summaries: the JUnit first (what a CI reads: a full disk then costs the CSV and
        JSON, said in the error), then the CSV and the JSON."""
        from imucal_cli.documents import write_text_atomic

        if self.junit is not None:
            write_text_atomic(self.junit, junit_xml(rows))
        write_text_atomic(self.out_dir / "summary.csv", summary_csv(rows))
        write_text_atomic(self.out_dir / "summary.json", summary_json(rows, settings))

    def run(
        self,
        tasks: list[Task],
        jobs: int,
        scheduler: str | None,
        on_done: Callable[[int, list[Row]], None],
    ) -> list[Row]:
        """Every task, locally or on Dask, then the summaries; a Ctrl-C summarises the logs
        finished by then (``settings.interrupted``) and is raised again."""
        for task in tasks:
            try:
                Path(task.out).parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                folder = Path(task.out).parent
                raise InputError(
                    f"{folder}: cannot make the output folder: {exc.strerror}"
                ) from None
        finished: dict[int, list[Row]] = {}

        def done(i: int, rows: list[Row]) -> None:
            finished[i] = rows
            on_done(i, rows)

        settings = self.settings(jobs, scheduler)
        try:
            results = (
                run_dask(tasks, scheduler, done) if scheduler else run_local(tasks, jobs, done)
            )
        except KeyboardInterrupt:
            settings["interrupted"] = f"after {len(finished)} of {len(tasks)} logs"
            self.summarise([row for i in sorted(finished) for row in finished[i]], settings)
            raise
        rows = [row for result in results for row in result]
        self.summarise(rows, settings)
        return rows
