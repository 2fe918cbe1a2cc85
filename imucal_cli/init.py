"""``imucal init``: a starting config from what a log holds (SPEC "Inputs").

The log's IMU topics, which one is the base (``--base``, else the one the base frame's
``/tf_static`` chain places without a lidar beside it, else the one in the base frame itself),
every transform the tree gives (written out, marked ``from /tf_static``), a commented
placeholder for each it does not, and every other key at its default with its comment.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from imucal_cli.config import RESERVED_SENSOR_NAME, SECTIONS, BaseConfig, SensorConfig
from imucal_cli.errors import InputError
from imucal_cli.frames import TF_TOPIC, FrameTree, frame_tree, imu_frames
from imucal_cli.names import name_problem, printable, quoted
from imucal_cli.types import Transform

#: Tokens of a topic name that say nothing of which sensor it is.
GENERIC = {"imu", "lidar", "data", "raw", "sensors", "sensor", "points", "ouster", "livox", "os"}
#: What each key is (the comments of ``configs/default.yaml``, short), by section.
COMMENTS = {
    "base.grade": "consumer | industrial | tactical | navigation | ideal: the IMU's prior",
    "accel_units": "auto | mps2 | g",
    "gyro_units": "auto | radps | dps",
    "sensors.translation_bound_m": "search box |t - t_prior| <= bound per axis",
    "sensors.rotation_bound_deg": "the estimate's rotation at most this far from the prior's",
    "sensors.imu_frame": "the IMU messages' frame_id; else the IMU's frame in the tree",
    "sensors.grade": "consumer | industrial | tactical | navigation | ideal: the IMU's prior",
    "sensors.rotation_floor_deg": "systematic std the data cannot see, added to the std",
    "sensors.translation_floor_m": "",
    "rest.accel_tolerance_mps2": "rest detection (paper eq. 5)",
    "gyro_bias.process_noise_dps": "gyro bias Kalman filter (paper eqs. 7-9)",
    "segments.window_s": "observability windows (paper eqs. 18-19)",
    "segments.max_rotation_std_deg": "keep a window whose rotation std is below this",
    "calibration.resample_hz": "the common grid",
    "calibration.max_time_offset_s": "0 disables time-offset estimation",
    "calibration.consistency_alpha": "false-alarm rate of each model-consistency check",
    "stop.max_rotation_std_deg": "calibrate --until-converged: every sensor ok and at most",
    "stop.max_translation_std_m": "this statistical std on every axis",
}

#: The most lines ``init`` says of each kind (names left out, placeholders) before a count.
NOTE_LINES = 20


@dataclass
class Found:
    """What the log says of its IMUs."""

    base_topic: str
    base_frame: str
    sensors: dict[str, str]  # name -> topic
    lidar_frames: dict[str, str] = field(default_factory=dict)
    #: (who, key) -> the transform and where it came from (tf_static, urdf, both)
    transforms: dict[tuple[str, str], tuple[Transform, str]] = field(default_factory=dict)
    missing: list[tuple[str, str]] = field(default_factory=list)
    #: (who, key) -> what was looked for, for each missing one
    looked: dict[tuple[str, str], str] = field(default_factory=dict)
    #: What of the log could not go into a config (a topic or frame outside ROS's naming
    #: rules), one line each, made printable.
    skipped: list[str] = field(default_factory=list)

    def notes(self) -> list[str]:
        """What to tell of it: the names left out, then the placeholders to fill, at most
        :data:`NOTE_LINES` of each and then a count (a log of 60,000 IMU channels)."""
        missing = [
            f"{name}: {key} is not in the log ({self.looked.get((name, key), '')}): fill its "
            "placeholder"
            for name, key in self.missing
        ]
        notes = []
        for lines, what in ((self.skipped, "names left out"), (missing, "placeholders")):
            notes += lines[:NOTE_LINES]
            if len(lines) > NOTE_LINES:
                notes.append(f"... and {len(lines) - NOTE_LINES:,} more {what}")
        return notes


def sensor_name(topic: str, taken: set[str]) -> str:
    """A config name for the sensor of ``topic`` (its distinctive tokens), unique."""
    tokens = [t for t in re.split(r"[/]+", topic) if t and t.lower() not in GENERIC]
    name = re.sub(r"[^A-Za-z0-9_]", "_", "_".join(tokens)) or "lidar"
    name = name if name[0].isalpha() else f"lidar_{name}"
    unique, k = name, 2
    while unique in taken:
        unique, k = f"{name}_{k}", k + 1
    return unique


def _lidar_beside(tree: FrameTree, imu_frame: str) -> str | None:
    """A frame named like a lidar's next to the IMU's (its sibling or its child)."""
    for neighbour, _, _ in tree.edges.get(imu_frame, []):
        for frame in [neighbour, *(f for f, _, _ in tree.edges.get(neighbour, []))]:
            if frame != imu_frame and frame.rsplit("/", 1)[-1].lower().endswith("lidar"):
                return frame
    return None


def _base_topic(
    tree: FrameTree, frames: dict[str, str], base_frame: str, topics: list[str]
) -> str | None:
    """The base IMU's topic: the only one in the base frame itself, or the only one the tree
    places in the base frame's chain with no lidar beside it."""
    in_base = [t for t in topics if frames.get(t) == base_frame]
    if len(in_base) == 1:
        return in_base[0]
    placed = [
        t
        for t in topics
        if t in frames
        and tree.lookup(base_frame, frames[t]) is not None
        and _lidar_beside(tree, frames[t]) is None
    ]
    return placed[0] if len(placed) == 1 else None


def find(
    log: str | Path, base: str | None, base_frame: str, urdf: str | Path | None = None
) -> Found:
    """Read the log's IMU topics, their frames, ``/tf_static`` and a URDF (``urdf``, else the
    log's ``/robot_description``); settle the base and every transform the tree gives."""
    from imucal_cli.io.logs import open_log

    problem = name_problem(base_frame, "frame")
    if problem:
        raise InputError(f"--frame: {problem}")
    skipped: list[str] = []
    with open_log(log) as reader:
        topics = sorted(t for t, info in reader.topics().items() if info.is_imu)
        skipped += [f"IMU topic {quoted(t)} skipped: {p}" for t, p in _invalid(topics, "topic")]
        topics = [t for t in topics if name_problem(t, "topic") is None]
        if len(topics) < 2:
            raise InputError(f"{log}: {len(topics)} IMU topics; a calibration needs two or more")
        tree = frame_tree(reader, urdf)
        frames = imu_frames(reader, topics)
    for topic, problem in _invalid(frames.values(), "frame"):
        skipped.append(f"an IMU's frame_id {quoted(topic)} not used: {problem}")
    frames = {t: f for t, f in frames.items() if name_problem(f, "frame") is None}
    if base is not None and base not in topics:
        raise InputError(f"--base {base}: not an IMU topic of {log}: {', '.join(topics)}")
    base = base or _base_topic(tree, frames, base_frame, topics)
    if base is None:
        raise InputError(
            f"{log}: cannot tell which IMU is the base (its IMU topics: {', '.join(topics)}): "
            "give --base TOPIC"
        )
    taken = {RESERVED_SENSOR_NAME}
    sensors = {}
    for topic in topics:
        if topic != base:
            sensors[sensor_name(topic, taken)] = topic
            taken.add(list(sensors)[-1])
    found = Found(base, base_frame, sensors, skipped=skipped)
    _transforms(found, tree, frames)
    return found


def _invalid(names: Any, kind: str) -> list[tuple[str, str]]:
    """The names a config would refuse (:func:`~imucal_cli.names.name_problem`), with why: a
    log's author must not write keys into the config through them."""
    return [(n, p) for n in dict.fromkeys(names) if (p := name_problem(n, kind))]


def _transforms(found: Found, tree: FrameTree, frames: dict[str, str]) -> None:
    base_imu = frames.get(found.base_topic)
    if base_imu and base_imu != found.base_frame:
        chain = tree.chain(found.base_frame, base_imu)
        if chain is not None:
            found.transforms["base", "T_base_imu"] = chain
    for name, topic in found.sensors.items():
        imu = frames.get(topic)
        lidar = _lidar_beside(tree, imu) if imu else None
        if lidar is not None and (problem := name_problem(lidar, "frame")):
            found.skipped.append(f"{name}: the lidar frame {quoted(lidar)} not used: {problem}")
            lidar = None
        found.lidar_frames[name] = lidar or f"{name}_lidar"
        pairs = {"T_imu_lidar": (imu, lidar), "prior_T_base_imu": (found.base_frame, imu)}
        for key, (a, b) in pairs.items():
            chain = tree.chain(a, b) if a and b else None
            if chain is None:
                found.missing.append((name, key))
                found.looked[name, key] = _looked_for(tree, a, b)
            else:
                found.transforms[name, key] = chain


def _looked_for(tree: FrameTree, a: str | None, b: str | None) -> str:
    """What :func:`_transforms` looked for and did not find, in words (``b`` None: the lidar
    frame beside the IMU's ``a``)."""
    if a is None:
        return "the IMU's messages name no frame"
    if b is None:
        return f"no frame named '...lidar' sits beside the IMU's frame {quoted(a)}"
    gap = [quoted(f) for f in (a, b) if f not in tree.edges]
    if gap:
        return f"frame {gap[0]} is not in {TF_TOPIC} or the URDF"
    return f"no chain joins {quoted(a)} and {quoted(b)}"


def _scalar(value: str) -> str:
    """A string as a YAML scalar, by the emitter (quoted where YAML needs it): nothing a name
    holds can end its line or open another key."""
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 16)
    text = text.removesuffix("\n").removesuffix("\n...").strip()
    return json.dumps(value) if "\n" in text else text  # (a JSON string: YAML's double-quoted)


def _flow(T: Transform) -> str:
    def numbers(values: np.ndarray) -> str:
        return ", ".join(f"{v + 0.0:.9g}" for v in np.round(values, 12))  # (no -0)

    t, r = numbers(T.translation), numbers(np.degrees(T.rpy_rad))
    return f"{{translation: [{t}], rpy_deg: [{r}]}}"


def _default_lines(cls: type, section: str, indent: str, skip: set[str]) -> list[str]:
    out = []
    for f in fields(cls):
        if f.name in skip:
            continue
        comment = COMMENTS.get(f"{section}.{f.name}", COMMENTS.get(f.name, ""))
        line = f"{indent}{f.name}: {f.default}"
        if f.default == "":  # (a name whose default is another's: commented, as a hint)
            line = f"{indent}# {f.name}: NAME"
        out.append(f"{line:<44}# default{': ' + comment if comment else ''}")
    return out


def render(found: Found, log: str | Path, version: str) -> str:
    """The config text: found transforms written out, placeholders commented."""
    lines = [
        f"# imucal config from `imucal init {printable(str(log))}` (imucal {version}).",
        "# Transforms marked 'from tf_static' or 'from urdf' were read; a commented placeholder",
        "# marks one the log does not hold: fill it in (`imucal check-config` names what is",
        "# missing). Every other key is at its default.",
        "base:",
        f"  topic: {_scalar(found.base_topic)}",
        f"  frame: {_scalar(found.base_frame)}",
    ]
    if ("base", "T_base_imu") in found.transforms:
        T, origin = found.transforms["base", "T_base_imu"]
        lines.append(f"  T_base_imu: {_flow(T)}  # from {origin}")
    else:
        lines.append("  # T_base_imu: {translation: [0, 0, 0], rpy_deg: [0, 0, 0]}  # default")
    lines += _default_lines(BaseConfig, "base", "  ", {"topic", "frame", "T_base_imu"})
    lines.append("sensors:")
    hints = {
        "T_imu_lidar": "the supplier's lidar pose in its IMU (datasheet)",
        "prior_T_base_imu": "the CAD pose of the lidar's IMU in the base frame",
    }
    for name, topic in found.sensors.items():
        lines += [f"  {_scalar(name)}:", f"    imu_topic: {_scalar(topic)}"]
        lines.append(f"    lidar_frame: {_scalar(found.lidar_frames[name])}")
        for key in ("T_imu_lidar", "prior_T_base_imu"):
            if (name, key) in found.transforms:
                T, origin = found.transforms[name, key]
                lines.append(f"    {key}: {_flow(T)}  # from {origin}")
            else:
                lines.append(
                    f"    # {key}: {{translation: [0, 0, 0], rpy_deg: [0, 0, 0]}}  # not in the "
                    f"log: {hints[key]}"
                )
        skip = {"name", "imu_topic", "lidar_frame", "T_imu_lidar", "prior_T_base_imu"}
        lines += _default_lines(SensorConfig, "sensors", "    ", skip)
    for section, cls in SECTIONS.items():
        lines.append(f"{section}:")
        lines += _default_lines(cls, section, "  ", set())
    return "\n".join(lines) + "\n"
