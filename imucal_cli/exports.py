"""Extrinsics in the formats vehicle software reads: Autoware, URDF, tf2 static publishers
(ROS 2 and ROS 1), a Kalibr IMU chain, and plain JSON matrices.

Input is what ``imucal calibrate`` writes (its YAML or JSON document); every function returns
text and writes nothing. Full-precision formats print floats with ``repr`` (17 significant
digits: parsing them back gives the same doubles); Autoware's file has 6 decimals, as Autoware
writes it.

Conventions: ``T_a_b`` maps points from frame b to frame a (the pose of b in a). ROS RPY is
roll about x, then pitch about y, then yaw about z, all about the fixed parent axes:
``R = Rz(yaw) Ry(pitch) Rx(roll)``. tf2 quaternions are ``(qx, qy, qz, qw)``. ROS 1's
``static_transform_publisher`` also has an Euler form, ``x y z yaw pitch roll`` (yaw first):
only the quaternion form is written here, so nothing depends on that order.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from imucal_cli.errors import ConfigError, InputError
from imucal_cli.names import name_problem, quoteattr
from imucal_cli.types import Transform


@dataclass(frozen=True)
class SensorExtrinsics:
    name: str
    lidar_frame: str
    imu_topic: str
    T_base_lidar: Transform
    T_base_imu: Transform
    time_offset_s: float
    imu_rate_hz: float | None
    imu_noise: dict[str, float | None] | None = None  # Kalibr's four noise figures
    status: str = "ok"
    time_offset_observable: bool = True


@dataclass(frozen=True)
class Extrinsics:
    """The parts of a calibrate document the exports need."""

    source: str
    base_frame: str
    base_topic: str | None
    base_imu_rate_hz: float | None
    sensors: tuple[SensorExtrinsics, ...]
    base_imu_noise: dict[str, float | None] | None = None
    #: The base IMU's pose in B (the document's ``base.T_base_imu``); None in a document made
    #: before it carried one.
    base_T_base_imu: Transform | None = None

    @staticmethod
    def from_document(document: Any, source: str) -> Extrinsics:
        """Parse a calibrate document; :class:`InputError` naming the file and key if it is not
        one."""
        if (
            not isinstance(document, dict)
            or not isinstance(document.get("sensors"), dict)
            or not document["sensors"]
        ):
            raise InputError(
                f"{source}: not an imucal calibrate output (expected a mapping with 'sensors')"
            )
        sensors = []
        _check_name(document.get("base_frame", "base_link"), "frame", f"{source}: base_frame")
        if document.get("base_topic") is not None:
            _check_name(document["base_topic"], "topic", f"{source}: base_topic")
        for name, s in document["sensors"].items():
            _check_name(name, "sensor", f"{source}: sensors")
            where = f"{source}: sensors.{name}"
            if not isinstance(s, dict):
                raise InputError(f"{where}: expected a mapping")
            for key in ("T_base_lidar", "T_base_imu", "lidar_frame"):
                if key not in s:
                    raise InputError(f"{where}.{key}: missing")
            _check_name(s["lidar_frame"], "frame", f"{where}.lidar_frame")
            if s.get("imu_topic"):
                _check_name(s["imu_topic"], "topic", f"{where}.imu_topic")
            try:
                T_base_lidar = Transform.from_dict(
                    s["T_base_lidar"], source, f"sensors.{name}.T_base_lidar"
                )
                T_base_imu = Transform.from_dict(
                    s["T_base_imu"], source, f"sensors.{name}.T_base_imu"
                )
            except ConfigError as exc:  # names file and key
                raise InputError(str(exc)) from None
            sensors.append(
                SensorExtrinsics(
                    str(name),
                    str(s["lidar_frame"]),
                    str(s.get("imu_topic", "")),
                    T_base_lidar,
                    T_base_imu,
                    _number(s, "time_offset_s", f"{where}.time_offset_s") or 0.0,
                    _number(s, "imu_rate_hz", f"{where}.imu_rate_hz"),
                    s.get("imu_noise"),
                    str(s.get("status", "")),
                    bool(s.get("time_offset_observable", False)),
                )
            )
        return Extrinsics(
            source,
            str(document.get("base_frame", "base_link")),
            document.get("base_topic"),
            _number(document, "base_imu_rate_hz", f"{source}: base_imu_rate_hz"),
            tuple(sensors),
            document.get("base_imu_noise"),
            _base_pose(document.get("base"), source),
        )


def _base_pose(base: Any, source: str) -> Transform | None:
    """The document's ``base.T_base_imu``, None where it has no ``base``."""
    if base is None:
        return None
    if not isinstance(base, dict) or "T_base_imu" not in base:
        raise InputError(f"{source}: base.T_base_imu: missing")
    try:
        return Transform.from_dict(base["T_base_imu"], source, "base.T_base_imu")
    except ConfigError as exc:  # names file and key
        raise InputError(str(exc)) from None


def _check_name(value: Any, kind: str, where: str) -> None:
    """Names go into scripts, launch files and YAML that other programs run or read: refuse
    what ROS would (:mod:`imucal_cli.names`), naming the key."""
    problem = name_problem(value, kind)
    if problem:
        raise InputError(f"{where}: {problem}")


def _number(mapping: dict[str, Any], key: str, where: str) -> float | None:
    value = mapping.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(f"{where}: expected a number, got {value!r}")
    return float(value)


def _f(value: float) -> str:
    """A float that parses back to the same double, in YAML 1.1 too (PyYAML, Kalibr's reader,
    takes ``1e-06`` for a string: its mantissa needs a dot, ``1.0e-06``)."""
    text = repr(float(value))
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text


def autoware(ex: Extrinsics, parent: str) -> str:
    """Autoware's ``sensor_kit_calibration.yaml``: ``parent: {lidar_frame: {x, y, z, roll,
    pitch, yaw}}``."""
    lines = [f"{parent}:"]
    for s in ex.sensors:
        t = s.T_base_lidar.translation
        r = s.T_base_lidar.rpy_rad
        lines.append(f"  {s.lidar_frame}:")
        for key, value in zip(("x", "y", "z", "roll", "pitch", "yaw"), [*t, *r], strict=True):
            lines.append(f"    {key}: {value:.6f}")
    return "\n".join(lines) + "\n"


def urdf(ex: Extrinsics, parent: str) -> str:
    """A URDF fragment: the parent link, one link and one fixed joint per lidar."""
    lines = [
        '<?xml version="1.0"?>',
        '<robot name="imucal_extrinsics">',
        f"  <link name={quoteattr(parent)}/>",
    ]
    for s in ex.sensors:
        t = s.T_base_lidar.translation
        r = s.T_base_lidar.rpy_rad
        lines += [
            f"  <link name={quoteattr(s.lidar_frame)}/>",
            f'  <joint name={quoteattr(f"{parent}_to_{s.lidar_frame}")} type="fixed">',
            f"    <parent link={quoteattr(parent)}/>",
            f"    <child link={quoteattr(s.lidar_frame)}/>",
            f'    <origin xyz="{" ".join(map(_f, t))}" rpy="{" ".join(map(_f, r))}"/>',
            "  </joint>",
        ]
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def _tf_values(T: Transform) -> list[str]:
    return [*map(_f, T.translation), *map(_f, T.quaternion_xyzw)]


def tf_static_ros2(ex: Extrinsics, parent: str) -> tuple[str, str]:
    """``ros2 run tf2_ros static_transform_publisher`` command lines and a ROS 2 XML launch file."""
    commands, nodes = ["#!/bin/sh", "# imucal: one static transform per lidar (ROS 2)"], []
    for s in ex.sensors:
        x, y, z, qx, qy, qz, qw = _tf_values(s.T_base_lidar)
        words = [
            "--x",
            x,
            "--y",
            y,
            "--z",
            z,
            "--qx",
            qx,
            "--qy",
            qy,
            "--qz",
            qz,
            "--qw",
            qw,
            "--frame-id",
            parent,
            "--child-frame-id",
            s.lidar_frame,
        ]
        args = shlex.join(words)  # quoted: nothing a name holds runs
        commands.append(f"ros2 run tf2_ros static_transform_publisher {args} &")
        nodes.append(
            '  <node pkg="tf2_ros" exec="static_transform_publisher" '
            f"name={quoteattr(f'imucal_{s.name}_tf')} args={quoteattr(args)}/>"
        )
    return "\n".join([*commands, "wait"]) + "\n", _launch_file(nodes)


def _launch_file(nodes: list[str]) -> str:
    return "\n".join(['<?xml version="1.0"?>', LAUNCH_MARK, "<launch>", *nodes, "</launch>", ""])


#: The line that tells a launch file imucal wrote (beside ``-o``, a file nobody named) from one
#: a person wrote: only the first is ever replaced.
LAUNCH_MARK = "<!-- imucal export: the lidars' static transforms (imucal replaces this file) -->"


def tf_static_ros1(ex: Extrinsics, parent: str) -> tuple[str, str]:
    """``rosrun tf2_ros static_transform_publisher x y z qx qy qz qw frame child`` lines and a
    roslaunch file (the quaternion form; the Euler form would be ``x y z yaw pitch roll``)."""
    commands, nodes = ["#!/bin/sh", "# imucal: one static transform per lidar (ROS 1)"], []
    for s in ex.sensors:
        args = shlex.join(
            [*_tf_values(s.T_base_lidar), parent, s.lidar_frame]
        )  # quoted: nothing a name holds runs
        commands.append(f"rosrun tf2_ros static_transform_publisher {args} &")
        nodes.append(
            '  <node pkg="tf2_ros" type="static_transform_publisher" '
            f"name={quoteattr(f'imucal_{s.name}_tf')} args={quoteattr(args)}/>"
        )
    return "\n".join([*commands, "wait"]) + "\n", _launch_file(nodes)


def _matrix_rows(M: np.ndarray, indent: str) -> list[str]:
    return [f"{indent}- [{', '.join(_f(v) for v in row)}]" for row in M]


def kalibr(ex: Extrinsics) -> str:
    """A Kalibr IMU chain (``imu_chain.yaml``): ``imu0`` is the base IMU, then one entry per
    sensor IMU, each with ``T_i_b``, the base frame B expressed in that IMU: ``T_base_imu^-1``
    (the base IMU's from the document's ``base.T_base_imu``). ``time_offset`` is added to the
    IMU's stamps to get the base's time (``-time_offset_s``)."""
    if ex.base_T_base_imu is None:
        raise InputError(
            f"{ex.source}: base.T_base_imu: missing (a document of an older imucal): calibrate "
            "again; Kalibr's imu0 needs the base IMU's pose"
        )
    # the YAML directive OpenCV's FileStorage (OpenVINS reads the chain with it) requires; a
    # directive PyYAML (Kalibr) reads too
    lines = [
        "%YAML 1.0",
        "---",
        "# imucal: IMU chain in Kalibr's layout; imu0 is the base IMU",
        "# noise densities: measured above the motion; random walks: from the joint fit's relative "
        "bias",
        "# knots (sensor minus base), upper bounds; the base's, its grade's (ideal: the smallest",
        "# of its sensors')",
        "imu0:",
        "  T_i_b:",
    ]
    lines += _matrix_rows(ex.base_T_base_imu.inverse().as_matrix(), "    ")
    lines += ["  model: calibrated", f"  rostopic: {ex.base_topic or ''}", "  time_offset: 0.0"]
    unused = all(s.status == "unobservable" for s in ex.sensors)  # (no sensor's knots either)
    lines += _kalibr_imu(ex, "base_imu", ex.base_imu_rate_hz, ex.base_imu_noise, unused)
    for k, s in enumerate(ex.sensors, start=1):
        lines += [f"imu{k}:", f"  # {s.name}", "  T_i_b:"]
        lines += _matrix_rows(s.T_base_imu.inverse().as_matrix(), "    ")
        offset = (
            f"{_f(0.0 - s.time_offset_s)}"  # (0.0, not -0.0, where it is 0)
            if s.time_offset_observable
            else "0.0  # not observable from the drive: not estimated"
        )
        lines += ["  model: calibrated", f"  rostopic: {s.imu_topic}", f"  time_offset: {offset}"]
        unused = s.status == "unobservable"
        lines += _kalibr_imu(ex, f"sensors.{s.name}.imu", s.imu_rate_hz, s.imu_noise, unused)
    return "\n".join(lines) + "\n"


KALIBR_NOISE = (
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
)


def _kalibr_imu(
    ex: Extrinsics,
    key: str,
    rate: float | None,
    noise: dict[str, float | None] | None,
    unused: bool = False,
) -> list[str]:
    """The update rate and the four noise figures Kalibr's and OpenVINS's readers require
    (each positive); an error naming the calibrate output's key (``base_imu`` or
    ``sensors.NAME.imu``: its ``_rate_hz`` and ``_noise``) where one is missing, and why
    (``unused``: the sensor is unobservable, no window measured its random walks)."""
    if rate is None or not rate > 0:
        raise InputError(f"{ex.source}: {key}_rate_hz: missing: Kalibr needs the IMU's update_rate")
    lines = [f"  update_rate: {_f(rate)}"]
    if noise is not None and not isinstance(noise, dict):
        raise InputError(
            f"{ex.source}: {key}_noise: expected a mapping of Kalibr's noise figures, got "
            f"{noise!r:.60}"
        )
    for name in KALIBR_NOISE:
        value = (noise or {}).get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            why = (
                "no window of the drive was used (status unobservable), so none measured it"
                if unused and name.endswith("random_walk")
                else "calibrate with this imucal version"
            )
            raise InputError(f"{ex.source}: {key}_noise.{name}: missing ({why}): Kalibr needs it")
        lines.append(f"  {name}: {_f(value)}")
    return lines


def json_matrices(ex: Extrinsics) -> str:
    """Per sensor the 4x4 ``T_base_lidar`` and ``T_base_imu`` matrices (row-major)."""
    document = {
        "base_frame": ex.base_frame,
        "sensors": {
            s.name: {
                "lidar_frame": s.lidar_frame,
                "T_base_lidar": s.T_base_lidar.as_matrix().tolist(),
                "T_base_imu": s.T_base_imu.as_matrix().tolist(),
            }
            for s in ex.sensors
        },
    }
    return json.dumps(document, indent=2) + "\n"


def relative_to(ex: Extrinsics, parent: str, T_base_parent: Transform | None = None) -> Extrinsics:
    """Every ``T_base_lidar`` re-expressed as ``T_parent_lidar = T_base_parent^-1 T_base_lidar``.
    ``parent`` is the base frame, a lidar frame or sensor name of the calibration, or any frame
    whose ``T_base_parent`` is given; anything else is refused (renaming the parent alone would
    publish every transform against the wrong frame)."""
    if T_base_parent is None:
        if parent == ex.base_frame:
            return ex
        found = [s for s in ex.sensors if parent in (s.lidar_frame, s.name)]
        if not found:
            frames = ", ".join([ex.base_frame, *(s.lidar_frame for s in ex.sensors)])
            raise InputError(
                f"--parent {parent}: not a frame of {ex.source} ({frames}); give "
                f"--parent-transform with T_{ex.base_frame}_{parent}"
            )
        T_base_parent, parent = found[0].T_base_lidar, found[0].lidar_frame
    inverse = T_base_parent.inverse()
    sensors = tuple(
        replace(s, T_base_lidar=inverse * s.T_base_lidar, T_base_imu=inverse * s.T_base_imu)
        for s in ex.sensors
        if s.lidar_frame != parent
    )
    base = None if ex.base_T_base_imu is None else inverse * ex.base_T_base_imu
    return replace(ex, base_frame=parent, sensors=sensors, base_T_base_imu=base)


def export(
    ex: Extrinsics,
    fmt: str,
    parent: str | None = None,
    T_base_parent: Transform | None = None,
    allow_not_ok: bool = False,
) -> dict[str, str]:
    """The files of one format: ``{"main": text}`` plus ``{"launch": text}`` for tf-static.
    ``parent``: re-express every transform relative to that frame (:func:`relative_to`). A
    sensor that is not ``ok`` is refused unless ``allow_not_ok`` (its prior would go out as if
    calibrated)."""
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt}: unknown format (expected one of: {', '.join(FORMATS)})")
    weak = [f"{s.name} ({s.status or 'no status'})" for s in ex.sensors if s.status != "ok"]
    if weak and not allow_not_ok:
        raise InputError(
            f"{ex.source}: not calibrated on every axis: {', '.join(weak)}; --allow-not-ok exports "
            "them anyway"
        )
    if parent is not None:
        _check_name(parent, "frame", "--parent")
    if parent is not None and (parent != ex.base_frame or T_base_parent is not None):
        if not FORMATS[fmt].takes_parent:
            raise InputError(
                f"--parent {parent}: a Kalibr IMU chain is relative to its first IMU, the base's: "
                "no other parent"
            )
        ex = relative_to(ex, parent, T_base_parent)
    return FORMATS[fmt].write(ex, ex.base_frame)


@dataclass(frozen=True)
class ExportFormat:
    """One export format: what it is for (the help says it), the files it makes of the
    extrinsics (``{"main": text}``, plus ``{"launch": text}``), and the suffix of its launch
    file beside ``-o``'s, if it has one."""

    what: str
    write: Any  # (Extrinsics, parent frame) -> dict[str, str]
    launch_suffix: str | None = None
    takes_parent: bool = True


def _pair(make: Any) -> Any:
    def write(ex: Extrinsics, parent: str) -> dict[str, str]:
        commands, launch = make(ex, parent)
        return {"main": commands, "launch": launch}

    return write


#: Every export format, by the name ``--format`` takes.
FORMATS = {
    "autoware": ExportFormat(
        "Autoware's sensor_kit_calibration.yaml", lambda ex, p: {"main": autoware(ex, p)}
    ),
    "urdf": ExportFormat("URDF joints", lambda ex, p: {"main": urdf(ex, p)}),
    "tf-static-ros2": ExportFormat(
        "tf2 static publishers, ROS 2", _pair(tf_static_ros2), ".launch.xml"
    ),
    "tf-static-ros1": ExportFormat(
        "tf2 static publishers, ROS 1", _pair(tf_static_ros1), ".launch"
    ),
    "kalibr": ExportFormat("a Kalibr IMU chain", lambda ex, p: {"main": kalibr(ex)}, None, False),
    "json": ExportFormat("4x4 matrices", lambda ex, p: {"main": json_matrices(ex)}),
}


def parse_transform(text: str) -> Transform:
    """A transform given on the command line: a YAML/JSON file, or seven numbers."""
    from pathlib import Path

    from imucal_cli.documents import load_document

    path = Path(text)
    try:
        if path.is_file():
            return Transform.from_dict(load_document(path), str(path), "")
        values = [float(v) for v in text.replace(",", " ").split()]
    except ConfigError as exc:
        raise InputError(str(exc)) from None
    except ValueError:
        values = []
    if len(values) != 7:
        raise InputError(f"--parent-transform {text!r}: expected a file or 'x y z qx qy qz qw'")
    try:
        return Transform.from_dict(
            {"translation": values[:3], "rotation": values[3:]}, "--parent-transform", ""
        )
    except ConfigError as exc:
        raise InputError(str(exc)) from None


def _written_by_export(path: Any) -> bool:
    """Whether ``path`` is a launch file an earlier ``export`` wrote (its mark in its head)."""
    try:
        with path.open("rb") as handle:
            return LAUNCH_MARK.encode() in handle.read(4096)
    except OSError:
        return False


def export_targets(out: Any, fmt: str) -> dict[str, Any]:
    """Where each file of ``fmt`` goes: ``out`` (a Path, ``-o``), and a launch file beside it as
    its stem's, which replaces only a launch file an earlier export wrote."""
    suffix = FORMATS[fmt].launch_suffix
    if out is None:
        return {}
    targets = {"main": out}
    if suffix is not None:
        targets["launch"] = out.with_name((out.name.split(".")[0] or out.name) + suffix)
    launch = targets.get("launch")
    if launch is not None and launch.exists() and not _written_by_export(launch):
        raise InputError(
            f"{launch}: exists, and imucal export did not write it: not replaced (the launch "
            "file goes beside -o OUT as its stem's): move it, or name another OUT"
        )
    return targets
