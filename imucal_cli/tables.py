"""What a person reads of each document: rich tables (with the lines that go under them) of
``inspect``, ``biases``, ``segments``, ``calibrate`` and ``evaluate`` documents and of the follow
view, each fitted to a width. The CLI prints them; a notebook may too
(``console.print(tables.calibration(log, run.document(), console.width))``, ``console`` a
``rich.console.Console``). rich is imported when a table is made.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from itertools import islice
from typing import Any

from imucal_cli.names import printable

#: Windows a table of ``segments`` shows at a time (a day's log has 8,640 a sensor: shown in
#: blocks, each made only when it is drawn).
TABLE_ROWS = 1000
#: Wide enough for any table: nothing is stacked (:func:`fitted`).
WIDE = 1 << 16


def fmt(values: Any, digits: int) -> str:
    if values is None:
        return "-"
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"


def fitted(
    title: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[Any]],
    width: int = WIDE,
    right: Iterable[str] = (),
    no_wrap: Iterable[str] = (),
) -> Any:
    """A table of ``rows`` that fits ``width`` columns, its cells wrapped between words, the
    ``right`` columns right-justified (numbers); where even that does not fit (rich would then
    cut numbers short, ``[4.348…``), each row stacked as lines of ``column  value`` under its
    first cell: no value is ever cut."""
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
    wide = Console(width=WIDE)
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


def _under(table: Any, *lines: Any) -> Any:
    """A table and the lines printed under it (str: plain; :class:`rich.text.Text`: styled)."""
    from rich.console import Group
    from rich.text import Text

    return Group(table, *(line if isinstance(line, Text) else Text(line) for line in lines))


def _warned(name: str, warnings: Iterable[str]) -> list[Any]:
    from rich.text import Text

    return [Text(printable(f"{name}: {warning}"), style="yellow") for warning in warnings]


def _gaps(info: dict[str, Any]) -> str:
    if len(info["gaps"]) > 3:
        return str(len(info["gaps"]))
    return ", ".join(f"{a:.2f}-{b:.2f}" for a, b in info["gaps"]) or "0"


def inspection(document: dict[str, Any], width: int = WIDE) -> Any:
    """``inspect``'s table: per topic its type, count, rate, duration, gaps and time jumps."""
    columns = ("topic", "type", "count", "rate Hz", "duration s", "gaps", "backwards")
    return fitted(
        f"{document['log']} ({document['format']}), t0_ns = {document['t0_ns']}",
        (*columns, "duplicates"),
        (
            (
                *(topic, i["type"], f"{i['count']:,}", f"{i['rate_hz']:.2f}"),
                *(f"{i['duration_s']:.2f}", _gaps(i), str(i["backwards"]), str(i["duplicates"])),
            )
            for topic, i in document["topics"].items()
        ),
        width,
        right=(*columns[2:], "duplicates"),
        no_wrap=columns[:2],
    )


def biases(log: Any, document: dict[str, Any], width: int = WIDE) -> Any:
    """``biases``' table: per IMU its rests, the accelerometer bias along g and the gyro bias;
    then what the accelerometer bias is and each IMU's warnings."""
    columns = ("IMU", "rests", "rest s", "accel bias along g m/s^2", "gyro bias rad/s (final)")
    table = fitted(
        f"IMU biases: {log}",
        (*columns, "final std rad/s"),
        (
            (
                *(name, str(len(imu["rest_periods"]))),
                f"{sum(b - a for a, b in imu['rest_periods']):.1f}",
                "n/a"
                if imu["accel_bias_along_gravity_mps2"] is None
                else f"{imu['accel_bias_along_gravity_mps2']:.4f}",
                fmt(imu["gyro_bias_radps"]["final"], 5),
                fmt(imu["gyro_bias_radps"]["final_std"], 5),
            )
            for name, imu in document["imus"].items()
        ),
        width,
    )
    return _under(
        table,
        "accel bias: at rest only its component along gravity is seen; the full vector, "
        "relative to the base IMU, is calibrate's accel_bias_mps2",
        *(
            line
            for name, imu in document["imus"].items()
            for line in _warned(name, imu["warnings"])
        ),
    )


def _window_row(w: dict[str, Any]) -> tuple[str, ...]:
    # (padded to the widest each column takes: the blocks of a long log's table line up)
    selected = "no: gap in the data" if w.get("gap") else "no: too little motion"
    return (
        f"{w['start_s']:8.1f}",
        f"{w['end_s']:8.1f}",
        f"{w['min_singular_value']:.4g}",
        "inf" if w["rotation_std_deg"] is None else f"{w['rotation_std_deg']:.4f}",
        f"{'yes' if w['selected'] else selected:>21}",
        " ".join("y" if v else "n" for v in w["translation_observable"]),
    )


def segments(document: dict[str, Any], width: int = WIDE) -> Iterator[Any]:
    """``segments``' tables: per sensor its windows, :data:`TABLE_ROWS` a table (each made as
    it is asked for: a day's windows are never all rows at once)."""
    columns: tuple[str, ...] = ("start s", "end s", "min singular value 1/rad^2")
    columns += ("rotation std deg", "selected", "translation observable x y z")
    for name, sensor in document["sensors"].items():
        title = (
            f"{name}: {sensor['selected']} of {sensor['total']} windows selected (rotation std "
            f"< {document['max_rotation_std_deg']:g} deg)"
        )
        rows, shown = map(_window_row, sensor["windows"]), 0
        block = list(islice(rows, TABLE_ROWS))
        while True:  # (the first block, empty or not, under the sensor's title)
            heading = f"{name}, windows {shown + 1}-{shown + len(block)}" if shown else title
            yield fitted(heading, columns, block, width, right=columns)
            shown += len(block)
            block = list(islice(rows, TABLE_ROWS))
            if not block:
                break


def _sensor_row(name: str, s: dict[str, Any]) -> tuple[Any, ...]:
    from rich.text import Text

    std_t = None if s["translation_std_m"] is None else [v * 1000 for v in s["translation_std_m"]]
    style = {"ok": "green", "partial": "yellow"}.get(s["status"], "red")
    return (
        name,
        Text(s["status"], style=style),
        fmt(s["T_base_lidar"]["translation"], 4),
        fmt(s["T_base_lidar"]["rpy_deg"], 3),
        fmt(std_t, 2),
        fmt(s["rotation_std_deg"], 4),
        f"{s['time_offset_s'] * 1000:.2f}" if s["time_offset_observable"] else "not shown",
        f"{s['segments']['selected']}/{s['segments']['total']}",
    )


def calibration(log: Any, document: dict[str, Any], width: int = WIDE) -> Any:
    """``calibrate``'s table: per sensor its status, ``T_base_lidar``, std, clock offset and
    windows; then each sensor's warnings and every pair's transform."""
    columns = ("sensor", "status", "xyz m", "rpy deg", "std xyz mm", "std rpy deg")
    table = fitted(
        f"T_{document['base_frame']}_lidar from {log}",
        (*columns, "time offset ms", "windows"),
        (_sensor_row(name, s) for name, s in document["sensors"].items()),
        width,
    )
    pairs = (
        f"{pair}: xyz {fmt(T['translation'], 4)} m, rpy {fmt(T['rpy_deg'], 3)} deg"
        for pair, T in document["pairs"].items()
    )
    warned = (line for n, s in document["sensors"].items() for line in _warned(n, s["warnings"]))
    return _under(table, *warned, *pairs)


def over(row: dict[str, Any], limits: dict[str, Any]) -> list[str]:
    """The thresholds a row of an evaluate document exceeds, named."""
    from imucal_cli.outputs import over_thresholds

    return [
        f"{key.removeprefix('max_').replace('_', ' ')} > {limits[key]:g}"
        for key, _ in over_thresholds(row, limits)
    ]


def evaluation(estimate: Any, truth: Any, document: dict[str, Any], width: int = WIDE) -> Any:
    """``evaluate``'s table: per sensor and pair its errors and the thresholds it is over; then
    the verdict, with why it failed."""
    from rich.text import Text

    rows = {**document["sensors"], **document["pairs"]}
    overs = {name: over(r, document["thresholds"]) for name, r in rows.items()}
    numbers = ("rotation error deg", "translation error m", "eq. 20 m", "time offset error ms")
    table = fitted(
        f"{estimate} vs {truth}",
        ("sensor / pair", *numbers, "over"),
        (
            (
                name,
                *(f"{r[key]:.4f}" for key in ("rotation_error_deg", "translation_error_m")),
                f"{r['translation_error_eq20_m']:.4f}",
                "-"
                if r.get("time_offset_error_s") is None
                else f"{r['time_offset_error_s'] * 1e3:.3f}",
                ", ".join(overs[name]) or "-",
            )
            for name, r in rows.items()
        ),
        width,
        right=numbers,
    )
    failed = [name for name in rows if overs[name]]
    missing = [name for names in document["missing"].values() for name in names]
    why = [f"{len(failed)} over a threshold ({', '.join(failed)})"] * bool(failed) + [
        f"in one file only: {', '.join(missing)}"
    ] * bool(missing and not document["pass"])
    verdict = "pass" if document["pass"] else "fail: " + "; ".join(why)
    return _under(table, Text(verdict, style="green" if document["pass"] else "red"))


def axis(missing: str) -> str:
    """A missing axis in short: ``roll``, ``pitch``, ``yaw``, ``tx``, ``ty``, ``tz``."""
    name = missing.split(":")[0]
    return name[name.find("(") + 1 : -1] if "(" in name else "t" + name.split()[-1]


def mm(values: Any) -> Any:
    return None if values is None else [1000 * v for v in values]


def follow(log: Any, followed: dict[str, Any], stop: Any, width: int = WIDE) -> Any:
    """The follow view of a follow line (``Calibration.follow_line``): per sensor its status,
    the estimate (``T_base_lidar``), its statistical std (what ``stop:`` tests: what more
    driving shrinks) against the config's ``stop`` targets, the windows used and what it
    lacks."""
    rows = []
    for name, line in followed["sensors"].items():  # (as a row)
        T, std = line["T_base_lidar"], line["statistical_std"] or {}
        rows.append(
            (
                name,
                line["status"],
                fmt(T["translation"], 4),
                fmt(T["rpy_deg"], 3),
                fmt(std.get("rotation_deg"), 4),
                fmt(mm(std.get("translation_m")), 2),
                line["windows"],
                " ".join(axis(m) for m in line["missing"]) or "-",
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
    return fitted(f"following {log}: {followed['windows']} windows", columns, rows, width)


def waiting(log: Any, state: dict[str, Any], width: int = WIDE) -> Any:
    """The follow view before the first estimate: per sensor, samples and what it waits for."""
    rows = [
        (name, f"{s['samples']:,}", str(s["windows"]), s["waiting_for"])
        for name, s in state["sensors"].items()
    ]
    return fitted(
        f"following {log}: base {state['base_samples']:,} samples",
        ("sensor", "samples", "windows", "waiting for"),
        rows,
        width,
        right=("samples", "windows"),
    )


def follow_lines(followed: dict[str, Any]) -> list[str]:
    """The follow view of a follow line as a line per sensor (for a log file, not a terminal)."""
    lines, windows = [], followed["windows"]
    for name, line in followed["sensors"].items():
        T, std = line["T_base_lidar"], line["statistical_std"] or {}
        missing = " ".join(axis(m) for m in line["missing"]) or "none"
        lines.append(
            f"{windows} windows: {name} {line['status']} xyz {fmt(T['translation'], 4)} m rpy "
            f"{fmt(T['rpy_deg'], 3)} deg, statistical std {fmt(std.get('rotation_deg'), 4)} deg "
            f"{fmt(mm(std.get('translation_m')), 2)} mm; missing: {missing}"
        )
    return lines


def status_lines(document: dict[str, Any]) -> list[str]:
    """A ``calibrate`` document in lines: each sensor's status with its worst std, then each of
    its warnings (what a job's log shows where the table is not printed)."""
    lines = []
    for name, sensor in document["sensors"].items():
        line = f"{name}: {sensor['status']}"
        if sensor["rotation_std_deg"] is not None:
            line += f", std {max(sensor['rotation_std_deg']):.3g} deg"
        if sensor["translation_std_m"] is not None:
            line += f" and {1000 * max(sensor['translation_std_m']):.3g} mm (worst axis)"
        segments = sensor["segments"]
        lines.append(f"{line}, {segments['selected']}/{segments['total']} windows")
        lines += [f"{name}: {warning}" for warning in sensor["warnings"]]
    return lines


def waiting_line(log: Any, state: dict[str, Any]) -> str:
    """The follow view before the first estimate, in a line."""
    first: dict[str, Any] = next(iter(state["sensors"].values()), {})
    samples = ", ".join(f"{n} {v['samples']:,} samples" for n, v in state["sensors"].items())
    return f"following {log}: {samples}; waiting for {first.get('waiting_for', 'data')}"
