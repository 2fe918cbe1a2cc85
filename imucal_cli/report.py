"""A calibration report: PNG figures and one ``report.html`` that embeds them with the result
table (``imucal calibrate --report DIR``), drawn from what the calibration computed, with no
second read of the log and no model of its own.

Figures (matplotlib, Agg backend; the optional extra ``imucal[report]``):

- ``biases.png``: per sensor, the relative gyro and accelerometer bias the joint fit estimated
  at each knot (eqs. 5-9 within eq. 10-17's fit);
- ``windows.png``: per sensor, each window's rotation std (eq. 19) against the threshold,
  selected windows shaded, paper Figs. 9b-10b;
- ``residuals.png``: per sensor, the gyro and specific-force residual RMS of the fit in every
  window used (eqs. 10 and 11), against the noise the data imply;
- ``timeline.png``: per sensor, each epoch's estimate (the sensor alone in ``epoch_s`` of the
  log) less the log's, with its std, and where the mount moved;
- ``std.png``: the standard deviation of every estimated axis (rotation and translation);
- ``vehicle.png``: top and side view of the vehicle: the base frame and every IMU and lidar at
  its estimated pose, the CAD prior beside it.
"""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from imucal_cli.core.segments import window_counts
from imucal_cli.errors import InputError
from imucal_cli.types import Transform

if TYPE_CHECKING:
    from imucal_cli.calibration import Calibration

AXES = ("x", "y", "z")
COLOURS = ("tab:red", "tab:green", "tab:blue")


def pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise InputError("--report needs matplotlib: pip install 'imucal[report]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def check_outputs(
    folder: Path, others: Mapping[str, Path | None], inputs: Sequence[Path | None]
) -> None:
    """Before the work: the report's files in ``folder`` are none of ``others`` and replace no
    input (:func:`~imucal_cli.paths.check_outputs`), and matplotlib is there to draw them."""
    from imucal_cli.paths import check_outputs as check

    files = {f"--report ({name})": folder / name for name in ("report.html", *FIGURES)}
    check({**others, **files}, inputs)
    pyplot()


def _legend(ax: Any, **kwargs: Any) -> None:
    """The axes' legend beside them, on the right, where it covers no data."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8, **kwargs)


def _save(fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _save_over_time(fig: Any, bottom: Any, path: Path) -> Path:
    """A figure over the log's time saved: its ``bottom`` axes labelled with the time, laid
    out tight."""
    for ax in bottom:
        ax.set_xlabel("time since the log's first IMU stamp (s)")
    fig.tight_layout()
    return _save(fig, path)


def bias_figure(plt: Any, estimates: Mapping[str, Any], offset_s: float, path: Path) -> Path:
    """Per sensor: the relative gyro (left) and accelerometer (right) bias at every knot."""
    fig, axes = plt.subplots(
        len(estimates), 2, figsize=(13, 2.6 * len(estimates)), sharex=True, squeeze=False
    )
    for row, (name, est) in zip(axes, estimates.items(), strict=True):
        t = est.bias_knots_s + offset_s
        if est.status == "unobservable":
            for ax in row:
                not_observable(ax)
            row[0].set_title(f"{name}: relative gyro bias", fontsize=10)
            row[1].set_title(f"{name}: relative accelerometer bias", fontsize=10)
            continue
        for k in range(3):
            row[0].plot(
                t,
                np.degrees(est.gyro_bias_knots[:, k]),
                color=COLOURS[k],
                lw=1.0,
                label=f"b_{AXES[k]}",
            )
            row[1].plot(
                t, est.accel_bias_knots[:, k], color=COLOURS[k], lw=1.0, label=f"b_{AXES[k]}"
            )
        row[0].set_ylabel("gyro bias (deg/s)")
        row[1].set_ylabel("accel bias (m/s^2)")
        row[0].set_title(f"{name}: relative gyro bias, sensor minus base (IMU axes)", fontsize=10)
        row[1].set_title(f"{name}: relative accelerometer bias (IMU axes)", fontsize=10)
        for ax in row:
            ax.grid(alpha=0.3)
            _legend(ax)
    return _save_over_time(fig, axes[-1], path)


def excitation_figure(plt: Any, windows: Sequence[Any], offset_s: float, path: Path) -> Path:
    """The drive's excitation window by window, from the base IMU: its rate's RMS and its
    specific force's spread (the turns and the changes of speed that make the extrinsics
    observable), the windows selected shaded. Speed is not drawn: no IMU measures it."""
    fig, (rate, accel) = plt.subplots(2, 1, figsize=(13, 4.2), sharex=True)
    middle = [0.5 * (w.start_s + w.end_s) + offset_s for w in windows]
    rate.plot(middle, [np.degrees(w.rate_rms_radps) for w in windows], "o-", ms=3)
    accel.plot(middle, [w.accel_std_mps2 for w in windows], "o-", ms=3, color="tab:purple")
    rate.set_ylabel("rate RMS (deg/s)")
    accel.set_ylabel("specific force std (m/s^2)")
    for ax in (rate, accel):
        _shade_selected(ax, windows, offset_s, alpha=0.12)
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
    if any(w.selected for w in windows):
        _legend(rate)
    rate.set_title(
        "Excitation per window (base IMU): turning, and accelerating or braking", fontsize=10
    )
    return _save_over_time(fig, [accel], path)


def _shade_selected(ax: Any, windows: Sequence[Any], offset_s: float, alpha: float) -> None:
    """The selected windows shaded green on ``ax`` (one legend entry for them all)."""
    for i, w in enumerate(w for w in windows if w.selected):
        ax.axvspan(
            w.start_s + offset_s,
            w.end_s + offset_s,
            color="tab:green",
            alpha=alpha,
            label=None if i else "selected window",
        )


def windows_figure(
    plt: Any, estimates: Mapping[str, Any], offset_s: float, threshold_deg: float, path: Path
) -> Path:
    """Per sensor: each window's rotation std against the threshold, selected windows shaded."""
    fig, axes = plt.subplots(
        len(estimates), 1, figsize=(13, 2.8 * len(estimates)), sharex=True, squeeze=False
    )
    for ax, (name, est) in zip(axes[:, 0], estimates.items(), strict=True):
        infos = est.windows
        _shade_selected(ax, infos, offset_s, alpha=0.15)
        for valid, colour, label in (
            (True, "tab:blue", "window std"),
            (False, "tab:orange", "window with a gap (not used)"),
        ):
            mid = [0.5 * (w.start_s + w.end_s) + offset_s for w in infos if w.valid == valid]
            std = [
                w.rotation_std_deg if np.isfinite(w.rotation_std_deg) else np.nan
                for w in infos
                if w.valid == valid
            ]
            if mid:
                ax.plot(mid, std, "_", color=colour, ms=8, mew=2, label=label)
        ax.axhline(
            threshold_deg, color="tab:red", ls="--", lw=1, label=f"threshold {threshold_deg:g} deg"
        )
        ax.set_yscale("log")
        ax.set_ylabel("rotation std (deg, eq. 19)")
        ax.set_title(
            "{}: windows ({} of {} selected)".format(name, *window_counts(infos)),
            fontsize=10,
        )
        _legend(ax)
        ax.grid(alpha=0.3)
    return _save_over_time(fig, axes[-1], path)


def not_observable(ax: Any) -> None:
    """An unobservable sensor's panel: said, not drawn empty."""
    ax.text(0.5, 0.5, "not observable", ha="center", va="center", transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])


def residual_figure(plt: Any, estimates: Mapping[str, Any], offset_s: float, path: Path) -> Path:
    """Per sensor: the reported fit's residual RMS in every window used (per grid sample, after
    the low-pass), with their RMS over all windows (the residual check's figure), against the
    level the check holds them to and its limit."""
    from imucal_cli.core.checks import RESIDUAL_LEVEL_MAX

    fig, axes = plt.subplots(
        len(estimates), 2, figsize=(13, 2.6 * len(estimates)), sharex=True, squeeze=False
    )
    for row, (name, est) in zip(axes, estimates.items(), strict=True):
        r = est.window_residuals
        level = (getattr(est, "checks", None) or {}).get("residual_level", {})
        for ax, col, unit, key, figure in (
            (row[0], 1, "rad/s", "expected_gyro_radps", "gyro"),
            (row[1], 2, "m/s^2", "expected_accel_mps2", "accel"),
        ):
            if est.status == "unobservable" or not len(r):
                not_observable(ax)
                continue
            ax.plot(
                r[:, 0] + offset_s, r[:, col], ".", color="black", ms=3, label="window residual RMS"
            )
            if key in level:
                ax.axhline(level[key], color="tab:blue", ls="--", lw=1, label="the noise level")
                ax.axhline(  # what the check tests: these windows' RMS, over the noise level
                    level[figure] * level[key],
                    color="black",
                    lw=1,
                    label=f"all windows: {level[figure]:.2f}x, the check's figure",
                )
                ax.axhline(
                    RESIDUAL_LEVEL_MAX * level[key],
                    color="tab:red",
                    ls=":",
                    lw=1,
                    label=f"the check's limit ({RESIDUAL_LEVEL_MAX:g}x)",
                )
            ax.set_ylabel(f"residual ({unit})")
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
            _legend(ax)
        row[0].set_title(f"{name}: gyro residual after calibration (eq. 10)", fontsize=10)
        row[1].set_title(f"{name}: specific-force residual after calibration (eq. 11)", fontsize=10)
    return _save_over_time(fig, axes[-1], path)


def std_figure(plt: Any, stds: Mapping[str, tuple[Any, Any]], path: Path) -> Path:
    """Per-axis standard deviation of every estimate."""
    names = list(stds)
    fig, (rot, tra) = plt.subplots(1, 2, figsize=(13, 4))
    x = np.arange(len(names))
    for k in range(3):
        r = [np.nan if stds[n][0] is None else stds[n][0][k] for n in names]
        t = [np.nan if stds[n][1] is None else 1000 * stds[n][1][k] for n in names]
        rot.bar(x + (k - 1) * 0.25, r, 0.25, color=COLOURS[k], label=f"about {AXES[k]}")
        tra.bar(x + (k - 1) * 0.25, t, 0.25, color=COLOURS[k], label=AXES[k])
    rot.set_ylabel("rotation std (deg)")
    tra.set_ylabel("translation std (mm)")
    rot.set_title("T_base_lidar rotation: 1 std per axis")
    tra.set_title("T_base_lidar translation: 1 std per axis")
    for ax in (rot, tra):
        ax.set_xticks(x, names, rotation=15)
        ax.grid(alpha=0.3, axis="y")
        _legend(ax)
        for i, name in enumerate(names):  # (an unobservable sensor has no std: said so)
            if stds[name][0] is None:
                ax.text(
                    i,
                    0.5,
                    "not observable",
                    ha="center",
                    va="center",
                    rotation=90,
                    transform=ax.get_xaxis_transform(),
                )
        if all(stds[n][0] is None for n in names):  # (no std at all: no scale to show)
            ax.set_ylim(0.0, 1.0)
            ax.set_yticks([])
        else:
            ax.set_ylim(bottom=0.0)  # (a std is never negative)
    fig.tight_layout()
    return _save(fig, path)


def _draw_axes(
    ax: Any, T: Any, i: int, j: int, length: float, style: str, alpha: float, width: float = 1.4
) -> None:
    origin = T.translation
    R = T.rotation.as_matrix()
    for k in range(3):
        end = origin + length * R[:, k]
        ax.plot(
            [origin[i], end[i]],
            [origin[j], end[j]],
            color=COLOURS[k],
            ls=style,
            lw=width,
            alpha=alpha,
        )


def vehicle_figure(plt: Any, poses: Mapping[str, Mapping[str, Any]], path: Path) -> Path:
    """Top (x-y) and side (x-z) view of the whole vehicle, then a close-up per sensor (top view):
    the base frame, each lidar as estimated (solid) against the lidar its CAD prior places
    (``prior_T_base_imu * T_imu_lidar``, dashed: like against like, so a mount turned 180 deg
    inside its housing, as an Ouster's IMU is, looks as it is); the close-ups add the IMU and
    its prior."""
    from matplotlib.lines import Line2D

    n = len(poses)
    fig = plt.figure(figsize=(14, 10))
    grid = fig.add_gridspec(2, max(2, n), height_ratios=[1.3, 1])
    views = (
        ("whole vehicle, top view (x forward, y left)", 0, 1),
        ("whole vehicle, side view (x forward, z up)", 0, 2),
    )
    base_len, sensor_len, close = 0.5, 0.3, 0.06
    for col, (title, i, j) in enumerate(views):
        ax = fig.add_subplot(grid[0, col * max(2, n) // 2 : (col + 1) * max(2, n) // 2])
        _whole_vehicle(ax, poses, title, i, j, base_len, sensor_len)
    for col, (name, p) in enumerate(poses.items()):
        _close_up(fig.add_subplot(grid[1, col]), name, p, close)
    legend = [
        Line2D([], [], color="black", marker="o", lw=0.8, label="IMU, estimated (close-ups: thin)"),
        Line2D([], [], color="black", marker="s", lw=2.0, label="lidar, estimated"),
        Line2D([], [], color="grey", marker="x", ls="--", label="CAD prior (dashed axes)"),
        Line2D([], [], color="tab:red", label="x axis"),
        Line2D([], [], color="tab:green", label="y axis"),
        Line2D([], [], color="tab:blue", label="z axis"),
    ]
    fig.legend(handles=legend, loc="lower center", ncol=6, fontsize=9)
    fig.suptitle(
        f"Sensor poses (axes: base {base_len} m, sensors {sensor_len} m; close-ups {close} m)"
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path)


def _whole_vehicle(
    ax: Any,
    poses: Mapping[str, Mapping[str, Any]],
    title: str,
    i: int,
    j: int,
    base_len: float,
    sensor_len: float,
) -> None:
    """The base frame and every lidar (its prior dashed) on axes ``i``, ``j``."""
    _draw_axes(ax, Transform.identity(), i, j, base_len, "-", 1.0)
    ax.annotate("base", (0, 0), textcoords="offset points", xytext=(4, -14), fontsize=9)
    for name, p in poses.items():
        _draw_axes(ax, p["prior_lidar"], i, j, sensor_len, "--", 0.6)
        _draw_axes(ax, p["lidar"], i, j, sensor_len, "-", 1.0)
        at = p["lidar"].translation
        ax.plot(at[i], at[j], "s", color="black", ms=4)
        side = 1 if at[1] >= 0 else -1
        ax.annotate(
            name, (at[i], at[j]), textcoords="offset points", xytext=(6, 8 * side), fontsize=8
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.margins(0.15)
    ax.set_xlabel(f"{'xyz'[i]} in the base frame (m)")
    ax.set_ylabel(f"{'xyz'[j]} in the base frame (m)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)


def _close_up(ax: Any, name: str, p: Mapping[str, Any], close: float) -> None:
    """One sensor from above: its lidar (thick axes) and its IMU apart (thin, half as long),
    each beside its prior (dashed)."""
    for key, style, alpha, marker, colour, scale, width in (
        ("prior_imu", "--", 0.6, "x", "grey", 0.5, 0.8),
        ("prior_lidar", "--", 0.6, "x", "grey", 1.0, 2.0),
        ("imu", "-", 1.0, "o", "black", 0.5, 0.8),
        ("lidar", "-", 1.0, "s", "black", 1.0, 2.0),
    ):
        _draw_axes(ax, p[key], 0, 1, scale * close, style, alpha, width)
        ax.plot(p[key].translation[0], p[key].translation[1], marker, color=colour, ms=6)
    centre = p["lidar"].translation
    ax.set_xlim(centre[0] - 0.15, centre[0] + 0.15)
    ax.set_ylim(centre[1] - 0.15, centre[1] + 0.15)
    ax.set_aspect("equal")
    ax.set_title(f"{name}: close-up, top view", fontsize=10)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)


#: The summary table's columns.
SUMMARY = (
    "sensor",
    "status",
    "xyz (m)",
    "rpy (deg)",
    "&Delta; prior: angle (deg)",
    "&Delta; prior: xyz (mm)",
    "std rpy (deg): total / statistical",
    "std xyz (mm): total / statistical",
    "time offset (ms)",
    "clock drift (ppm)",
    "moved",
    "windows",
)


def html_page(
    title: str,
    document: Mapping[str, Any],
    figures: list[tuple[Path, str]],
    extra: Mapping[str, Mapping[str, Any]] | None = None,
) -> str:
    """One self-contained page: the summary of every sensor, the pairs, where each prior came
    from, what to drive next, why each sensor has its status, then every figure (embedded as
    data URIs). ``extra``, per sensor, what the document does not hold: its pose less the CAD
    prior's, its grades, what to drive next (:func:`_extra`)."""
    notes = "".join(_sensor_notes(name, s) for name, s in document["sensors"].items())
    images = "".join(
        f'<figure><img alt="{html.escape(path.name)}" '
        f'src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}"/>'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        for path, caption in figures
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1500px;margin:auto;padding:1em}}
table{{border-collapse:collapse;margin:0.5em 0}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}img{{max-width:100%}}
td.ok{{color:#060}}td.partial{{color:#a60}}td.inconsistent,td.unobservable{{color:#b00}}
figure{{margin:2em 0}}</style></head>
<body><h1>{html.escape(title)}</h1>
<p>T_{html.escape(str(document["base_frame"]))}_lidar per sensor from
{html.escape(str(document.get("log", "")))}
(imucal {html.escape(str(document["imucal_version"]))}). &Delta; prior: the estimate less
the lidar the CAD prior places (prior_T_base_imu &middot; T_imu_lidar). Total std: what to
gate accuracy on; statistical: what the data alone determine, what more driving shrinks
(stop: tests it).</p>
{_sections(document, extra or {})}
{notes}{images}</body></html>
"""


def _sections(document: Mapping[str, Any], extra: Mapping[str, Mapping[str, Any]]) -> str:
    """The page's tables: the summary, the pairs, where each prior came from, what to drive."""
    sensors = document["sensors"]
    summary = [_summary_row(name, s, extra.get(name, {})) for name, s in sensors.items()]
    pairs = [
        (pair, _numbers(T["translation"], 4), _numbers(T["rpy_deg"], 3))
        for pair, T in document.get("pairs", {}).items()
    ]
    keys = ("T_imu_lidar", "prior_T_base_imu", "base.T_base_imu")
    provenance = [
        (
            name,
            *(s.get("priors", {}).get(k, "config") for k in keys),
            extra.get(name, {}).get("grade", "-"),
            extra.get(name, {}).get("base_grade", "-"),
        )
        for name, s in sensors.items()
    ]
    drive = "".join(
        f"<h3>{html.escape(name)}</h3>" + _what_to_drive(sensors[name]["status"], missing)
        for name in sensors
        if (missing := extra.get(name, {}).get("missing"))
    )
    return (
        f"<h2>Summary</h2>{_table(SUMMARY, summary)}"
        f"<h2>Pairs</h2>{_table(('pair', 'xyz (m)', 'rpy (deg)'), pairs)}"
        f"<h2>Where each prior came from</h2>"
        f"{_table(('sensor', *keys, 'grade', 'base grade'), provenance)}"
        "<h2>What to drive next</h2>"
        + (
            drive
            or "<p>Nothing: every axis of every sensor is within the config's stop: targets.</p>"
        )
    )


def _what_to_drive(status: str, missing: list[str]) -> str:
    """The driving that supplies each missing axis; none for a sensor whose data contradict
    the model (more of the same driving does not mend that)."""
    if status == "inconsistent":
        return (
            "<p>No driving mends it: the data contradict the rigid-mount model (its warnings "
            "below say how), and its std is inflated for that.</p>"
        )
    return "<ul>" + "".join(f"<li>{html.escape(m)}</li>" for m in missing) + "</ul>"


def _table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """An HTML table; the head as given (entities allowed), the cells escaped; a ``status``
    cell is coloured by its class."""
    cells = "".join(
        "<tr>"
        + "".join(
            f'<td class="{html.escape(str(v))}">{html.escape(str(v))}</td>'
            if v in ("ok", "partial", "inconsistent", "unobservable")
            else f"<td>{html.escape(str(v))}</td>"
            for v in row
        )
        + "</tr>"
        for row in rows
    )
    return f"<table><tr>{''.join(f'<th>{h}</th>' for h in head)}</tr>{cells}</table>"


def _numbers(values: Any, digits: int, scale: float = 1.0) -> str:
    return "-" if values is None else ", ".join(f"{scale * v:.{digits}f}" for v in values)


def _summary_row(name: str, s: Mapping[str, Any], extra: Mapping[str, Any]) -> tuple[str, ...]:
    T, statistical = s["T_base_lidar"], s.get("statistical_std") or {}
    offset_std = s.get("time_offset_std_s")
    offset = (
        f"{1000 * s['time_offset_s']:.2f}"
        + ("" if offset_std is None else f" \u00b1 {1000 * offset_std:.2f}")
        if s["time_offset_observable"] and s["status"] != "unobservable"
        else ("not shown" if extra.get("offset_estimated", True) else "not estimated")
    )
    prior = s["status"] != "unobservable" and "prior_angle_deg" in extra  # (else: the prior)
    drift, drift_std = s.get("clock_drift_ppm"), s.get("clock_drift_std_ppm")
    moves = s.get("moved") or []
    return (
        name,
        s["status"],
        _numbers(T["translation"], 4),
        _numbers(T["rpy_deg"], 3),
        f"{extra['prior_angle_deg']:.3f}" if prior else "- (the prior)",
        _numbers(extra["prior_shift_m"], 1, 1000.0) if prior else "-",
        f"{_numbers(s['rotation_std_deg'], 4)} / {_numbers(statistical.get('rotation_deg'), 4)}",
        f"{_numbers(s['translation_std_m'], 2, 1000.0)} / "
        f"{_numbers(statistical.get('translation_m'), 2, 1000.0)}",
        offset,
        "-"
        if drift is None
        else f"{drift:.1f}" + ("" if drift_std is None else f" \u00b1 {drift_std:.1f}"),
        ", ".join(f"at {m['at_s']:.0f} s" for m in moves if "at_s" in m)
        or ("yes" if moves else "no"),
        f"{s['segments']['selected']}/{s['segments']['total']}",
    )


def _sensor_notes(name: str, sensor: Mapping[str, Any]) -> str:
    """A sensor's warnings and its checks with their figures (why it has its status)."""
    warnings = "".join(f"<li>{html.escape(w)}</li>" for w in sensor["warnings"])
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in sensor.get("notes") or [])

    def figures(check: Mapping[str, Any]) -> str:
        return ", ".join(
            f"{html.escape(k)} {v:.4g}" if isinstance(v, float) else f"{html.escape(k)} {v}"
            for k, v in check.items()
            if k != "pass" and isinstance(v, (int, float, str))
        )

    checks = "".join(
        f"<tr><td>{html.escape(c)}</td><td>{'pass' if v.get('pass') else 'FAIL'}</td>"
        f"<td>{figures(v)}</td></tr>"
        for c, v in (sensor.get("checks") or {}).items()
    )
    return (
        f"<h2>{html.escape(name)}: {html.escape(sensor['status'])}</h2>"
        + (f"<ul>{warnings}</ul>" if warnings else "<p>No warnings.</p>")
        + (f"<p>Notes (no action needed):</p><ul>{notes}</ul>" if notes else "")
        + (
            f"<table><tr><th>check</th><th>result</th><th>figures</th></tr>{checks}</table>"
            if checks
            else "<p>No checks: no window carried enough motion to make them.</p>"
        )
    )


def timeline_figure(plt: Any, sensors: Mapping[str, Mapping[str, Any]], path: Path) -> Path:
    """Per sensor (the calibrate document's): each epoch's lidar pose less the log's (the pose
    after the last move), rotation (deg, roll pitch yaw) and translation (mm), with one std,
    over time; where the mount moved, a line at the time with its std shaded."""
    fig, axes = plt.subplots(
        len(sensors), 2, figsize=(13, 2.6 * len(sensors)), sharex=True, squeeze=False
    )
    for row, (name, sensor) in zip(axes, sensors.items(), strict=True):
        epochs = sensor.get("timeline") or []
        final = sensor["T_base_lidar"]
        for ax, key, std_key, unit, scale, labels in (
            (row[0], "rpy_deg", "rotation_std_deg", "deg", 1.0, ("roll", "pitch", "yaw")),
            (row[1], "translation", "translation_std_m", "mm", 1000.0, AXES),
        ):
            if not epochs:
                not_observable(ax)
                continue
            middle = np.array([(e["start_s"] + e["end_s"]) / 2 for e in epochs])
            half = np.array([(e["end_s"] - e["start_s"]) / 2 for e in epochs])
            values = np.array([e[key] for e in epochs])
            delta = values - np.array(final[key])
            if key == "rpy_deg":
                delta = (delta + 180.0) % 360.0 - 180.0
            std = np.array([e[std_key] for e in epochs]) * scale
            for axis in range(3):
                ax.errorbar(
                    middle + (axis - 1) * 0.08 * half,
                    delta[:, axis] * scale,
                    yerr=std[:, axis],
                    xerr=half if axis == 1 else None,
                    fmt="o",
                    ms=3,
                    capsize=2,
                    color=COLOURS[axis],
                    label=labels[axis],
                )
            for move in sensor.get("moved") or []:
                at, at_std = move["at_s"], move["at_std_s"]
                ax.axvspan(at - at_std, at + at_std, color="tab:orange", alpha=0.25)
                ax.axvline(at, color="tab:orange", lw=1.5, label="mount moved")
            ax.axhline(0.0, color="black", lw=0.8)
            ax.set_ylabel(f"epoch - log ({unit})")
            ax.grid(alpha=0.3)
            _legend(ax)
        row[0].set_title(f"{name}: rotation of each epoch less the log's", fontsize=10)
        row[1].set_title(f"{name}: translation of each epoch less the log's", fontsize=10)
    return _save_over_time(fig, axes[-1], path)


#: The figures :func:`write_report` draws into its folder beside ``report.html``, each with
#: its caption on the page, in the page's order.
CAPTIONS = {
    "excitation.png": "The drive's excitation in each window (the base IMU's): what makes the "
    "extrinsics observable. Speed is not shown: no IMU measures it.",
    "biases.png": "Relative biases of every sensor at each knot of the joint fit.",
    "windows.png": "Per-window rotation std against the threshold; selected windows shaded "
    "(paper Figs. 9b-10b).",
    "residuals.png": "Residual RMS of the fit in every window used, against the noise.",
    "timeline.png": "Each epoch's estimate (the sensor alone in calibration.epoch_s of the log) "
    "less the log's, with one std; where the mount moved, its time and std shaded.",
    "std.png": "One standard deviation of every estimated axis.",
    "vehicle.png": "Top and side view: base frame and lidars as estimated (solid) and as the "
    "CAD prior places them (dashed); close-ups add each IMU and its prior.",
}
FIGURES = tuple(CAPTIONS)


def write_report(out_dir: Path, calibration: Calibration, progress: Any = None) -> list[Path]:
    """Draw every figure into ``out_dir`` and write ``report.html``; returns the files written.
    ``progress`` is told (figures drawn, figures in all) as it goes. The report is made in a
    hidden folder beside ``out_dir`` and moved in whole: a run ended midway (a Ctrl-C, a
    SIGTERM, a full disk: :class:`InputError`) leaves nothing of it."""
    import shutil
    import tempfile

    made = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        drawn = _draw_report(work, calibration, progress)
        for path in drawn:
            os.replace(path, out_dir / path.name)
        return [out_dir / path.name for path in drawn]
    except OSError as exc:
        raise InputError(f"{out_dir}: cannot write the report: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if made and not any(out_dir.iterdir()):
            out_dir.rmdir()


def _poses(result: Calibration) -> dict[str, dict[str, Transform]]:
    """Per sensor, what the vehicle figure draws: the IMU and the lidar as estimated, and as
    the CAD prior places them."""
    return {
        s.name: {
            "imu": result.estimates[s.name].T_base_imu,
            "lidar": result.T_base_lidar(s.name),
            "prior_imu": s.prior_T_base_imu,
            "prior_lidar": s.prior_T_base_imu * s.T_imu_lidar,
        }
        for s in result.config.sensors
    }


def _extra(result: Calibration) -> dict[str, dict[str, Any]]:
    """Per sensor, what the page shows beside the document: the lidar's pose less the one its
    CAD prior places (the angle between them, the shift in the base frame), the grades, and
    what to drive next (the axes whose statistical std is over the stop: targets)."""
    from imucal_cli.core.so3 import rotation_angle_deg

    out = {}
    for s in result.config.sensors:
        estimate, prior = result.T_base_lidar(s.name), s.prior_T_base_imu * s.T_imu_lidar
        out[s.name] = {
            "prior_angle_deg": rotation_angle_deg(prior.rotation, estimate.rotation),
            "prior_shift_m": estimate.translation - prior.translation,
            "grade": s.grade,
            "base_grade": result.config.base.grade,
            "missing": result.missing(s.name),
            "offset_estimated": result.config.calibration.max_time_offset_s > 0,
        }
    return out


def _draw_report(out_dir: Path, result: Calibration, progress: Any = None) -> list[Path]:
    """:func:`write_report`'s figures and page, drawn into ``out_dir``."""
    from imucal_cli.documents import write_text_atomic

    plt = pyplot()
    log, document = result.log, result.document()
    config = result.config
    estimates = {s.name: result.estimates[s.name] for s in config.sensors}
    offset = (result.t_ref_ns - result.t0_ns) * 1e-9  # the grid clock from the first stamp
    stds = {
        n: (s["rotation_std_deg"], s["translation_std_m"]) for n, s in document["sensors"].items()
    }
    threshold = config.segments.max_rotation_std_deg
    drawings = {
        "excitation.png": lambda path: excitation_figure(
            plt, next(iter(estimates.values())).windows, offset, path
        ),
        "biases.png": lambda path: bias_figure(plt, estimates, offset, path),
        "windows.png": lambda path: windows_figure(plt, estimates, offset, threshold, path),
        "residuals.png": lambda path: residual_figure(plt, estimates, offset, path),
        "timeline.png": lambda path: timeline_figure(plt, document["sensors"], path),
        "std.png": lambda path: std_figure(plt, stds, path),
        "vehicle.png": lambda path: vehicle_figure(plt, _poses(result), path),
    }
    figures = []
    for k, (name, draw) in enumerate(drawings.items(), start=1):
        figures.append((draw(out_dir / name), CAPTIONS[name]))
        if progress is not None:
            progress(k, len(drawings))
    page = out_dir / "report.html"
    title = f"imucal calibration report: {log.name}"
    write_text_atomic(page, html_page(title, document, figures, _extra(result)))
    return [p for p, _ in figures] + [page]
