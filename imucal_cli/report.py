"""A calibration report: PNG figures like the paper's and one ``report.html`` that embeds them
with the result table (``imucal calibrate --report DIR``).

Figures (matplotlib, Agg backend; the optional extra ``imucal[report]``):

- ``gyro_<sensor>.png``: base and sensor gyro per axis, raw (sensor axes) and after calibration
  (rotated into the base frame, relative bias removed, clock offset applied), paper Figs. 7-8;
- ``biases.png``: every IMU's gyro bias track (Kalman filter, eqs. 7-9) with its +-1 std band,
  rest periods shaded, paper Figs. 5-6;
- ``windows.png``: per sensor, each window's rotation std (eq. 19) against the threshold, over
  the base's ``|w|``, selected windows shaded, paper Figs. 9b-10b;
- ``residuals.png``: the specific-force residual of every sensor after calibration (eq. 11 with
  the estimated rotation, lever arm and bias), per axis;
- ``std.png``: the standard deviation of every estimated axis (rotation and translation);
- ``vehicle.png``: top and side view of the vehicle: the base frame and every IMU and lidar at
  its estimated pose, the CAD prior beside it.

The report needs the IMU streams in memory (the calibration itself does not): it reads the log
once more, which costs memory in proportion to its length.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.errors import InputError
from imucal_cli.types import Transform

#: Most points drawn per line (longer series are thinned evenly).
MAX_POINTS = 6000
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


def _thin(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    n = len(arrays[0])
    step = max(1, n // MAX_POINTS)
    return tuple(a[::step] for a in arrays)


def _save(fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def gyro_figure(plt: Any, name: str, t_base: np.ndarray, w_base: np.ndarray, t_sensor: np.ndarray, w_sensor: np.ndarray,
                R_base_imu: np.ndarray, gyro_bias: np.ndarray, tau_s: float, path: Path) -> Path:
    """Base vs sensor gyro per axis: raw (left) and calibrated (right)."""
    # calibrated: the sensor's sample at base time t is the one stamped t + tau; rotate it into
    # the base frame after removing its relative bias
    w_cal = np.column_stack([np.interp(t_base + tau_s, t_sensor, w_sensor[:, k]) for k in range(3)])
    w_cal = (w_cal - gyro_bias) @ R_base_imu.T
    fig, axes = plt.subplots(3, 2, figsize=(13, 8), sharex=True)
    rms = np.sqrt(np.nanmean((w_cal - w_base) ** 2, axis=0))
    tb, wb, wc = _thin(t_base, w_base, w_cal)
    ts, ws = _thin(t_sensor, w_sensor)
    for k in range(3):
        left, right = axes[k, 0], axes[k, 1]
        left.plot(tb, wb[:, k], color="black", lw=0.8, label="base")
        left.plot(ts, ws[:, k], color=COLOURS[k], lw=0.8, alpha=0.8, label=f"{name} (own axes)")
        right.plot(tb, wb[:, k], color="black", lw=0.8, label="base")
        right.plot(tb, wc[:, k], color=COLOURS[k], lw=0.8, alpha=0.8, ls="--", label=f"{name} calibrated (rms diff {rms[k]:.4f} rad/s)")
        left.set_ylabel(f"w_{AXES[k]} (rad/s)")
        for ax in (left, right):
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right", fontsize=8)
    axes[0, 0].set_title("raw: base axes vs the sensor IMU's own axes")
    axes[0, 1].set_title("calibrated: rotated into the base frame, bias removed, time-aligned")
    axes[2, 0].set_xlabel("time since the log's first IMU stamp (s)")
    axes[2, 1].set_xlabel("time since the log's first IMU stamp (s)")
    fig.suptitle(f"Angular velocity, base and {name}")
    fig.tight_layout()
    return _save(fig, path)


def bias_figure(plt: Any, tracks: Mapping[str, tuple[np.ndarray, Any]], path: Path) -> Path:
    """Each IMU's gyro bias track with its +-1 std band; rest periods shaded."""
    fig, axes = plt.subplots(len(tracks), 1, figsize=(13, 2.6 * len(tracks)), sharex=True, squeeze=False)
    for ax, (name, (t, report)) in zip(axes[:, 0], tracks.items(), strict=True):
        track, std = report.gyro_bias_track, report.gyro_bias_track_std_series
        tt, tr, sd = _thin(t, track, std)
        for k in range(3):
            ax.plot(tt, np.degrees(tr[:, k]), color=COLOURS[k], lw=1.0, label=f"b_{AXES[k]}")
            ax.fill_between(tt, np.degrees(tr[:, k] - sd[:, k]), np.degrees(tr[:, k] + sd[:, k]), color=COLOURS[k], alpha=0.15)
        for i, rest in enumerate(report.rest_periods):  # rest times count from the stream's first sample
            ax.axvspan(t[0] + rest.start_s, t[0] + rest.end_s, color="grey", alpha=0.2, label="rest" if i == 0 else None)
        low, high = np.degrees(np.nanmin(track)), np.degrees(np.nanmax(track))
        margin = max(0.1, 0.6 * (high - low))
        ax.set_ylim(low - margin, high + margin)  # the band grows off the chart while driving
        ax.set_ylabel("gyro bias (deg/s)")
        ax.set_title(f"{name}: gyro bias (Kalman filter) with +-1 std (grows between rests), rest periods shaded", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, ncol=4)
    axes[-1, 0].set_xlabel("time since the log's first IMU stamp (s)")
    fig.tight_layout()
    return _save(fig, path)


def windows_figure(plt: Any, t_base: np.ndarray, w_base: np.ndarray, windows: Mapping[str, list[Any]], offset_s: float,
                   threshold_deg: float, path: Path) -> Path:
    """Per sensor: each window's rotation std against the threshold, over the base's |w|."""
    fig, axes = plt.subplots(len(windows), 1, figsize=(13, 2.8 * len(windows)), sharex=True, squeeze=False)
    tb, wb = _thin(t_base, np.linalg.norm(w_base, axis=1))
    for ax, (name, infos) in zip(axes[:, 0], windows.items(), strict=True):
        ax.plot(tb, np.degrees(wb), color="grey", lw=0.7)
        ax.set_ylabel("|w| base (deg/s)", color="grey")
        right = ax.twinx()
        labelled = set()
        for w in infos:
            a, b = w.start_s + offset_s, w.end_s + offset_s
            if w.selected:
                ax.axvspan(a, b, color="tab:green", alpha=0.15, label=None if "sel" in labelled else "selected window")
                labelled.add("sel")
            std = w.rotation_std_deg if np.isfinite(w.rotation_std_deg) else np.nan
            kind = "window std" if w.valid else "window with a gap (not used)"
            right.plot([a, b], [std, std], color="tab:blue" if w.valid else "tab:orange", lw=2, label=None if kind in labelled else kind)
            labelled.add(kind)
        right.axhline(threshold_deg, color="tab:red", ls="--", lw=1, label=f"threshold {threshold_deg:g} deg")
        right.set_yscale("log")
        right.set_ylabel("rotation std (deg, eq. 19)", color="tab:blue")
        ax.set_title(f"{name}: windows ({sum(w.selected for w in infos)} of {len(infos)} selected)", fontsize=10)
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = right.get_legend_handles_labels()
        right.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time since the log's first IMU stamp (s)")
    fig.tight_layout()
    return _save(fig, path)


def residual_figure(plt: Any, residuals: Mapping[str, tuple[np.ndarray, np.ndarray]], path: Path) -> Path:
    """Specific-force residual per sensor and axis after calibration."""
    fig, axes = plt.subplots(len(residuals), 1, figsize=(13, 2.6 * len(residuals)), sharex=True, squeeze=False)
    for ax, (name, (t, r)) in zip(axes[:, 0], residuals.items(), strict=True):
        tt, rr = _thin(t, r)
        rms = np.sqrt(np.nanmean(r**2, axis=0))
        for k in range(3):
            ax.plot(tt, rr[:, k], color=COLOURS[k], lw=0.7, label=f"{AXES[k]} (rms {rms[k]:.4f})")
        ax.set_ylabel("residual (m/s^2)")
        ax.set_title(f"{name}: f_I - R^T (f_B + (W^2 + dW) t) - b_a, low-passed (eq. 11)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel("time since the log's first IMU stamp (s)")
    fig.tight_layout()
    return _save(fig, path)


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
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def _draw_axes(ax: Any, T: Any, i: int, j: int, length: float, style: str, alpha: float) -> None:
    origin = T.translation
    R = T.rotation.as_matrix()
    for k in range(3):
        end = origin + length * R[:, k]
        ax.plot([origin[i], end[i]], [origin[j], end[j]], color=COLOURS[k], ls=style, lw=1.4, alpha=alpha)


def vehicle_figure(plt: Any, poses: Mapping[str, Mapping[str, Any]], path: Path) -> Path:
    """Top (x-y) and side (x-z) view of the whole vehicle, then a close-up per sensor (top view):
    the base frame, each IMU and lidar as estimated (solid), the IMU's CAD prior (dashed)."""
    from matplotlib.lines import Line2D

    n = len(poses)
    fig = plt.figure(figsize=(14, 10))
    grid = fig.add_gridspec(2, max(2, n), height_ratios=[1.3, 1])
    views = (("whole vehicle, top view (x forward, y left)", 0, 1), ("whole vehicle, side view (x forward, z up)", 0, 2))
    base_len, sensor_len = 0.5, 0.3
    for col, (title, i, j) in enumerate(views):
        ax = fig.add_subplot(grid[0, col * max(2, n) // 2 : (col + 1) * max(2, n) // 2])
        _draw_axes(ax, Transform.identity(), i, j, base_len, "-", 1.0)
        ax.annotate("base", (0, 0), textcoords="offset points", xytext=(4, -14), fontsize=9)
        for name, p in poses.items():
            _draw_axes(ax, p["prior_imu"], i, j, sensor_len, "--", 0.6)
            _draw_axes(ax, p["lidar"], i, j, sensor_len, "-", 1.0)
            at = p["lidar"].translation
            ax.plot(at[i], at[j], "s", color="black", ms=4)
            side = 1 if at[1] >= 0 else -1
            ax.annotate(name, (at[i], at[j]), textcoords="offset points", xytext=(6, 8 * side), fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.margins(0.15)
        ax.set_xlabel(f"{'xyz'[i]} in the base frame (m)")
        ax.set_ylabel(f"{'xyz'[j]} in the base frame (m)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    for col, (name, p) in enumerate(poses.items()):
        ax = fig.add_subplot(grid[1, col])
        close = 0.06
        for key, style, alpha, marker, colour in (("prior_imu", "--", 0.6, "x", "grey"), ("imu", "-", 1.0, "o", "black"), ("lidar", "-", 1.0, "s", "black")):
            _draw_axes(ax, p[key], 0, 1, close, style, alpha)
            ax.plot(p[key].translation[0], p[key].translation[1], marker, color=colour, ms=6)
        centre = p["lidar"].translation
        ax.set_xlim(centre[0] - 0.15, centre[0] + 0.15)
        ax.set_ylim(centre[1] - 0.15, centre[1] + 0.15)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: close-up, top view", fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(alpha=0.3)
    legend = [
        Line2D([], [], color="black", marker="o", ls="", label="IMU, estimated"),
        Line2D([], [], color="black", marker="s", ls="", label="lidar, estimated"),
        Line2D([], [], color="grey", marker="x", ls="--", label="IMU, CAD prior (dashed axes)"),
        Line2D([], [], color="tab:red", label="x axis"), Line2D([], [], color="tab:green", label="y axis"),
        Line2D([], [], color="tab:blue", label="z axis"),
    ]
    fig.legend(handles=legend, loc="lower center", ncol=6, fontsize=9)
    fig.suptitle(f"Sensor poses (axes: base {base_len} m, sensors {sensor_len} m; close-ups {close} m)")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path)


def html_page(title: str, document: Mapping[str, Any], figures: list[tuple[Path, str]]) -> str:
    """One self-contained page: the result table and every figure (embedded as data URIs)."""
    rows = []
    for name, s in document["sensors"].items():
        T = s["T_base_lidar"]
        std_r = s["rotation_std_deg"]
        std_t = s["translation_std_m"]
        rows.append(
            "<tr>" + "".join(
                f"<td>{html.escape(str(v))}</td>"
                for v in (
                    name, s["status"], ", ".join(f"{v:.4f}" for v in T["translation"]), ", ".join(f"{v:.3f}" for v in T["rpy_deg"]),
                    "-" if std_t is None else ", ".join(f"{1000 * v:.2f}" for v in std_t),
                    "-" if std_r is None else ", ".join(f"{v:.4f}" for v in std_r),
                    f"{1000 * s['time_offset_s']:.2f}", f"{s['segments']['selected']}/{s['segments']['total']}",
                )
            ) + "</tr>"
        )
    head = "".join(f"<th>{h}</th>" for h in ("sensor", "status", "xyz (m)", "rpy (deg)", "std xyz (mm)", "std rpy (deg)", "time offset (ms)", "windows"))
    images = "".join(
        f'<figure><img alt="{html.escape(path.name)}" src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}"/>'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        for path, caption in figures
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1500px;margin:auto;padding:1em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}img{{max-width:100%}}figure{{margin:2em 0}}</style></head>
<body><h1>{html.escape(title)}</h1>
<p>T_{html.escape(str(document['base_frame']))}_lidar per sensor (imucal {html.escape(str(document['imucal_version']))}).</p>
<table><tr>{head}</tr>{''.join(rows)}</table>{images}</body></html>
"""


def write_report(out_dir: Path, log: Path, streams: Any, result: Any, streamed: Any, biases: Mapping[str, Any],
                 document: Mapping[str, Any]) -> list[Path]:
    """Draw every figure into ``out_dir`` and write ``report.html``; returns the files written."""
    from imucal_cli.core.signals import Lowpass

    plt = pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    config = result.config
    t0 = streams.t0_ns

    def seconds(t_ns: np.ndarray) -> np.ndarray:
        return (t_ns - t0) * 1e-9

    tb = seconds(streams.base.t_ns)
    figures: list[tuple[Path, str]] = []
    for sensor in config.sensors:
        est = result.estimates[sensor.name]
        s = streams.sensors[sensor.name]
        path = gyro_figure(plt, sensor.name, tb, streams.base.gyro, seconds(s.t_ns), s.gyro, est.T_base_imu.rotation.as_matrix(),
                           est.gyro_bias, est.time_offset_s, out_dir / f"gyro_{sensor.name}.png")
        figures.append((path, f"Gyro of the base and {sensor.name} per axis, raw and after calibration (paper Figs. 7-8)."))
    tracks = {"base": (tb, biases["base"])} | {n: (seconds(streams.sensors[n].t_ns), biases[n]) for n in streams.sensors}
    figures.append((bias_figure(plt, tracks, out_dir / "biases.png"), "Gyro bias tracks with +-1 std, rest periods shaded (paper Figs. 5-6)."))
    offset = (streamed.calibrator.t_ref_ns - t0) * 1e-9
    windows = {s.name: result.estimates[s.name].windows for s in config.sensors}
    figures.append((windows_figure(plt, tb, streams.base.gyro, windows, offset, config.segments.max_rotation_std_deg, out_dir / "windows.png"),
                    "Per-window rotation std against the threshold over the base |w|; selected windows shaded (paper Figs. 9b-10b)."))

    # specific-force residuals on a uniform grid, every term low-passed alike
    rate = config.calibration.resample_hz
    lowpass: Lowpass = streamed.calibrator.lowpass
    grid = np.arange(tb[0], tb[-1], 1.0 / rate)
    w_b = lowpass(np.column_stack([np.interp(grid, tb, streams.base.gyro[:, k]) for k in range(3)]))
    f_b = lowpass(np.column_stack([np.interp(grid, tb, streams.base.accel[:, k]) for k in range(3)]))
    dw_b = np.gradient(w_b, 1.0 / rate, axis=0)
    from imucal_cli.core.so3 import skew

    A = skew(w_b) @ skew(w_b) + skew(dw_b)
    residuals = {}
    for sensor in config.sensors:
        est = result.estimates[sensor.name]
        s = streams.sensors[sensor.name]
        ts = seconds(s.t_ns)
        f_i = lowpass(np.column_stack([np.interp(grid + est.time_offset_s, ts, s.accel[:, k]) for k in range(3)]))
        R = est.T_base_imu.rotation.as_matrix()
        predicted = (f_b + A @ est.T_base_imu.translation) @ R + est.accel_bias
        r = f_i - predicted
        # 2 s at each end are left out: the low-pass's edges, and the sensor's own ends
        outside = (grid < tb[0] + 2.0) | (grid > tb[-1] - 2.0)
        outside |= (grid + est.time_offset_s < ts[0] + 2.0) | (grid + est.time_offset_s > ts[-1] - 2.0)
        r[outside] = np.nan  # where the sensor's samples end, interpolation holds the edge value
        residuals[sensor.name] = (grid, r)
    figures.append((residual_figure(plt, residuals, out_dir / "residuals.png"), "Specific-force residuals after calibration, per sensor and axis."))
    stds = {n: (s["rotation_std_deg"], s["translation_std_m"]) for n, s in document["sensors"].items()}
    figures.append((std_figure(plt, stds, out_dir / "std.png"), "One standard deviation of every estimated axis."))
    poses = {}
    for sensor in config.sensors:
        est = result.estimates[sensor.name]
        poses[sensor.name] = {"imu": est.T_base_imu, "lidar": result.T_base_lidar(sensor.name), "prior_imu": sensor.prior_T_base_imu}
    figures.append((vehicle_figure(plt, poses, out_dir / "vehicle.png"), "Top and side view: base frame, IMUs and lidars as estimated (solid), CAD prior (dashed)."))
    page = out_dir / "report.html"
    from imucal_cli.documents import write_text_atomic

    write_text_atomic(page, html_page(f"imucal calibration report: {log.name}", document, figures))
    return [p for p, _ in figures] + [page]
