"""Priors from the log (SPEC "Inputs"): ``/tf_static`` stands in for config keys.

A ROS log already says where its sensors are meant to be: the lidar drivers publish their IMU
and lidar frames (Ouster: ``os_sensor``, ``os_imu``, ``os_lidar``) and the vehicle's static
transforms chain them to the base frame. Each IMU message names its frame
(``header.frame_id``). A config key left out is taken from that tree:

- ``sensors.<name>.T_imu_lidar``: the IMU's frame to ``lidar_frame``;
- ``sensors.<name>.prior_T_base_imu``: ``base.frame`` to the IMU's frame;
- ``base.T_base_imu``: ``base.frame`` to the base IMU's frame (identity where the base IMU
  names ``base.frame`` itself or no chain joins them).

A key given in the config wins. What is read is bounded (:data:`MAX_TF_MESSAGES`,
:data:`MAX_TRANSFORMS`): a static tree is small.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from imucal_cli.errors import ConfigError, InputError
from imucal_cli.names import quoted
from imucal_cli.types import Transform, rotation_type

TF_TOPIC = "/tf_static"
TF_MSGTYPES = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage")
STRING_MSGTYPE = "std_msgs/msg/String"
#: Most /tf_static messages and transforms read: a static tree holds tens.
MAX_TF_MESSAGES, MAX_TRANSFORMS = 1000, 10_000
#: The largest /tf_static message deserialised: its 10,000 transforms at 400 bytes each.
MAX_TF_MESSAGE_BYTES = 4 << 20
#: The farthest a static transform's origin may lie (m): no vehicle's tree spans more, and a
#: value beyond (1e308) would overflow the chains composed from it.
MAX_STATIC_M = 1e4
#: tf2's bound on a quaternion's squared norm (``QUATERNION_NORMALIZATION_TOLERANCE``).
TF2_QUATERNION_TOLERANCE = 10e-3
#: Sensor keys a tree may supply, and the base's.
SENSOR_KEYS, BASE_KEY = ("T_imu_lidar", "prior_T_base_imu"), "T_base_imu"


def config_sources() -> dict[str, str]:
    """Where a sensor's transforms come from when the config gives them all (SPEC
    ``priors``): the config, or its default."""
    return dict.fromkeys((*SENSOR_KEYS, f"base.{BASE_KEY}"), "config")


def leaves_out_transforms(error: ConfigError) -> bool:
    """Whether a config's error is a sensor transform it leaves out (that a log's tree may
    supply), rather than a mistake."""
    return error.problem == "missing required key" and error.key.endswith(SENSOR_KEYS)


class FrameTree:
    """Static transforms between named frames, each edge with where it came from
    (``tf_static``, ``urdf``); :meth:`lookup` composes any chain.

    A tree, as tf2 and urdfdom hold one: a frame with a second parent, or an edge that closes
    a loop, is not taken (the first is kept) but noted against the frame, and a chain through
    it is an error naming both (:meth:`chain`): the shortest of two chains would win
    silently. What reading left out (a cap reached, a message that does not decode) is kept
    in :attr:`notes` for the error of a chain not found."""

    def __init__(self) -> None:
        self.edges: dict[str, list[tuple[str, Transform, str]]] = {}
        self.parents: dict[str, tuple[str, str]] = {}  # child -> (parent, origin)
        self.conflicts: dict[str, str] = {}  # frame -> why a chain through it is refused
        self.notes: list[str] = []
        self._roots: dict[str, str] = {}  # union-find: which frames one tree joins

    def _root(self, frame: str) -> str:
        while self._roots.get(frame, frame) != frame:
            frame = self._roots[frame] = self._roots.get(self._roots[frame], self._roots[frame])
        return frame

    def add(self, parent: str, child: str, T_parent_child: Transform, origin: str = "") -> None:
        """An edge; one the tree already holds (from an earlier source) is kept."""
        known = self.parents.get(child)
        if known is not None:
            if known[0] != parent:
                self.conflicts[child] = (
                    f"frame {quoted(child)} has two parents, {quoted(known[0])} ({known[1]}) and "
                    f"{quoted(parent)} ({origin}): tf2 and URDF take one"
                )
            return
        if self._root(parent) == self._root(child):
            self.conflicts[child] = (
                f"the edge {quoted(parent)} -> {quoted(child)} ({origin}) closes a loop: tf2 and "
                "URDF take a tree"
            )
            return
        self._roots[self._root(child)] = self._root(parent)
        self.parents[child] = (parent, origin)
        self.edges.setdefault(parent, []).append((child, T_parent_child, origin))
        self.edges.setdefault(child, []).append((parent, T_parent_child.inverse(), origin))

    def lookup(self, target: str, source: str) -> Transform | None:
        """``T_target_source`` (a point in ``source`` to ``target``), or None: no chain."""
        found = self.chain(target, source)
        return None if found is None else found[0]

    def chain(self, target: str, source: str) -> tuple[Transform, str] | None:
        """``T_target_source`` and where its edges came from (``tf_static``, ``urdf``, or
        both joined by ``+``), or None: no chain. Raises :class:`InputError` where the chain
        passes a frame with two parents or a loop."""
        if target not in self.edges or source not in self.edges:
            return None
        reached: dict[str, tuple[Transform, frozenset[str], tuple[str, ...]]] = {
            target: (Transform.identity(), frozenset(), (target,))
        }
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            for neighbour, T, origin in self.edges[frame]:
                if neighbour not in reached:
                    T_so_far, origins, path = reached[frame]
                    reached[neighbour] = (T_so_far * T, origins | {origin}, (*path, neighbour))
                    queue.append(neighbour)
        if source not in reached:
            return None
        T, origins, path = reached[source]
        refused = [self.conflicts[f] for f in path if f in self.conflicts]
        if refused:
            raise InputError(f"the chain {quoted(target)} -> {quoted(source)}: {refused[0]}")
        return T, "+".join(sorted(o for o in origins if o)) or "tf_static"


#: The topic a ROS log may carry its robot's URDF on, and the most of it read.
DESCRIPTION_TOPIC, MAX_URDF_BYTES = "/robot_description", 16 << 20


def read_urdf(text: str, tree: FrameTree, where: str) -> None:
    """Every joint of a URDF (ROS's parser, ``urdf_parser_py``) into ``tree`` as an edge from
    its parent link to its child link at its origin (a moving joint at its zero position).
    Raises :class:`InputError` naming ``where`` for text that is not a URDF."""
    from urdf_parser_py import xml_reflection
    from urdf_parser_py.urdf import URDF

    if len(text) > MAX_URDF_BYTES:
        raise InputError(f"{where}: larger than {MAX_URDF_BYTES >> 20} MiB: not a URDF")
    xml_reflection.core.on_error = lambda _message: None  # (it prints what it skips)
    try:
        robot = URDF.from_xml_string(text.encode())
    except Exception as exc:  # lxml's and the parser's own errors alike
        raise InputError(f"{where}: not a URDF: {str(exc).splitlines()[0][:200]}") from None
    for joint in robot.joints or []:
        origin = joint.origin
        xyz = np.zeros(3) if origin is None or origin.xyz is None else np.array(origin.xyz)
        rpy = np.zeros(3) if origin is None or origin.rpy is None else np.array(origin.rpy)
        if not (np.all(np.abs(xyz) <= MAX_STATIC_M) and np.all(np.isfinite(rpy))):
            joint_edge = f"{quoted(str(joint.parent))} -> {quoted(str(joint.child))}"
            raise InputError(
                f"{where}: joint {quoted(str(joint.name))} ({joint_edge}) has an origin that is "
                f"not finite or beyond {MAX_STATIC_M:g} m (xyz {xyz.tolist()}, rpy {rpy.tolist()})"
            )
        tree.add(joint.parent, joint.child, Transform.from_rpy(rpy, xyz), "urdf")


def _description(reader: Any) -> str | None:
    """The log's robot description (a ``std_msgs/String``), its first message, or None."""
    if not _has(reader, DESCRIPTION_TOPIC, STRING_MSGTYPE):
        return None
    for batch in reader.batches([DESCRIPTION_TOPIC]):
        ros1 = batch.encoding == "ros1"
        store = tf_typestore(ros1)
        start, length = int(batch.starts[0]), int(batch.lengths[0])
        data = batch.buffer[start : start + min(length, MAX_URDF_BYTES + 64)].tobytes()
        try:
            read = store.deserialize_ros1 if ros1 else store.deserialize_cdr
            return str(read(data, STRING_MSGTYPE).data)
        except Exception:
            return None
    return None


def tf_typestore(ros1: bool) -> Any:
    """The ``rosbags`` type store of the encoding, with ``tf2_msgs/msg/TFMessage`` (the ROS 1
    store lacks it)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if TF_MSGTYPES[0] not in store.types:
        text = "geometry_msgs/TransformStamped[] transforms"
        store.register(get_types_from_msg(text, TF_MSGTYPES[0]))
    return store


def tf_message(store: Any, transforms: list[tuple[str, str, Transform]], stamp_ns: int) -> Any:
    """A ``TFMessage`` of ``(parent, child, T_parent_child)`` stamped ``stamp_ns``."""
    types = store.types
    header = types["std_msgs/msg/Header"]
    time = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    extra = {"seq": 0} if "seq" in header.__dataclass_fields__ else {}
    stamped = [
        types["geometry_msgs/msg/TransformStamped"](
            header=header(stamp=time, frame_id=parent, **extra),
            child_frame_id=child,
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](*map(float, T.translation)),
                rotation=types["geometry_msgs/msg/Quaternion"](*map(float, T.quaternion_xyzw)),
            ),
        )
        for parent, child, T in transforms
    ]
    return types[TF_MSGTYPES[0]](transforms=stamped)


def _has(reader: Any, topic: str, msgtype: str) -> bool:
    """Whether the log holds ``topic`` with messages of ``msgtype`` (ROS 1 or ROS 2 name)."""
    from imucal_cli.io.imu_msg import normalize_msgtype

    info = reader.topics().get(topic)
    return info is not None and normalize_msgtype(info.msgtype) == msgtype


def read_tf_static(reader: Any) -> FrameTree:
    """The log's ``/tf_static`` (ROS 2 or ROS 1 encoding) as a tree; empty without one. What
    is left out (a cap reached, a message that does not decode, a topic of another type) is
    noted in the tree's ``notes``."""
    from imucal_cli.io.imu_msg import normalize_msgtype

    tree = FrameTree()
    where = f"{reader.path} [{TF_TOPIC}]"
    info = reader.topics().get(TF_TOPIC)
    if info is not None and normalize_msgtype(info.msgtype) != TF_MSGTYPES[0]:
        tree.notes.append(f"{TF_TOPIC} holds {info.msgtype}, not {TF_MSGTYPES[0]}: not read")
    if not _has(reader, TF_TOPIC, TF_MSGTYPES[0]):
        return tree
    messages = transforms = undecoded = 0
    for batch in reader.batches([TF_TOPIC]):
        ros1 = batch.encoding == "ros1"
        store = tf_typestore(ros1)
        for start, length in zip(batch.starts.tolist(), batch.lengths.tolist(), strict=True):
            messages += 1
            if messages > MAX_TF_MESSAGES:
                tree.notes.append(f"{TF_TOPIC} read to its first {MAX_TF_MESSAGES:,} messages")
                return tree
            if length > MAX_TF_MESSAGE_BYTES:  # (not deserialised: 200 MiB made 2.5 GB)
                tree.notes.append(
                    f"{where}: a message of {length / 1e6:.0f} MB, larger than a static tree "
                    f"({MAX_TF_MESSAGE_BYTES >> 20} MiB), was left out"
                )
                continue
            data = batch.buffer[start : start + length].tobytes()
            try:
                read = store.deserialize_ros1 if ros1 else store.deserialize_cdr
                message: Any = read(data, "tf2_msgs/msg/TFMessage")
            except Exception:  # (a damaged message: the tree is read from the others)
                undecoded += 1
                if undecoded == 1:
                    tree.notes.append(f"{where}: messages that do not decode were left out")
                continue
            for stamped in message.transforms:
                transforms += 1
                if transforms > MAX_TRANSFORMS:
                    tree.notes.append(f"{TF_TOPIC} read to its first {MAX_TRANSFORMS:,} transforms")
                    return tree
                parent, child = stamped.header.frame_id, stamped.child_frame_id
                T = _tf_transform(stamped.transform, f"{reader.path} [{TF_TOPIC}]", parent, child)
                tree.add(parent.lstrip("/"), child.lstrip("/"), T, "tf_static")
    return tree


def _tf_transform(transform: Any, where: str, parent: str, child: str) -> Transform:
    """A ``geometry_msgs/Transform`` as tf2 takes it: finite, and a quaternion whose squared
    norm is within :data:`TF2_QUATERNION_TOLERANCE` of 1 (tf2 refuses any other; normalising
    ``(1e-8, 0, 0, 0)`` would make a 180 deg roll of it). Raises :class:`InputError` naming
    the frames and the value."""
    t, q = transform.translation, transform.rotation
    xyz, xyzw = np.array([t.x, t.y, t.z], float), np.array([q.x, q.y, q.z, q.w], float)
    edge = f"{where}: the transform {quoted(parent)} -> {quoted(child)}"
    if not (np.all(np.abs(xyz) <= MAX_STATIC_M) and np.all(np.abs(xyzw) <= 2.0)):
        raise InputError(
            f"{edge} is not finite or beyond {MAX_STATIC_M:g} m (translation {xyz.tolist()}, "
            f"rotation {xyzw.tolist()}): give the keys it would supply in the config"
        )
    if abs(float(xyzw @ xyzw) - 1.0) > TF2_QUATERNION_TOLERANCE:
        raise InputError(
            f"{edge} has a quaternion of norm {np.linalg.norm(xyzw):.6g} ({xyzw.tolist()}), not "
            f"a rotation (tf2 refuses a squared norm beyond 1 +- {TF2_QUATERNION_TOLERANCE:g}): "
            "give the keys it would supply in the config"
        )
    return Transform(rotation_type().from_quat(xyzw / np.linalg.norm(xyzw)), xyz)


def imu_frames(reader: Any, topics: list[str]) -> dict[str, str]:
    """Each IMU topic's frame (the ``header.frame_id`` of its first message)."""
    from imucal_cli.reading import decode

    frames: dict[str, str] = {}
    for batch in reader.batches(topics):
        if batch.topic not in frames:
            decoded = decode(reader, batch)  # (damaged data: the log's error, naming the topic)
            if decoded.frame_ids:
                frames[batch.topic] = decoded.frame_ids[0].lstrip("/")
        if len(frames) == len(topics):
            break
    return frames


def _missing(data: Mapping[str, Any]) -> tuple[list[tuple[str, str]], bool]:
    """The sensor keys and whether the base's key the config leaves out."""
    sensors = data.get("sensors")
    missing = [
        (name, key)
        for name, sensor in (sensors.items() if isinstance(sensors, Mapping) else ())
        if isinstance(sensor, Mapping)
        for key in SENSOR_KEYS
        if sensor.get(key) is None
    ]
    base = data.get("base")
    return missing, isinstance(base, Mapping) and base.get(BASE_KEY) is None


def leaves_out(data: Any) -> bool:
    """Whether a config document leaves a transform out for a log's tree to supply (a sensor's,
    or the base IMU's pose)."""
    if not isinstance(data, Mapping):
        return False
    missing, base_missing = _missing(data)
    return bool(missing) or base_missing


def frame_tree(reader: Any, urdf: str | Path | None = None) -> FrameTree:
    """The log's ``/tf_static``, then what a URDF adds: the file ``urdf``, else the log's
    ``/robot_description`` (a transform /tf_static holds is kept)."""
    tree = read_tf_static(reader)
    if urdf is not None:
        from imucal_cli.documents import read_capped

        text = read_capped(Path(urdf), MAX_URDF_BYTES, "a URDF").decode("utf-8", errors="replace")
        read_urdf(text, tree, str(urdf))
    elif (description := _description(reader)) is not None:
        read_urdf(description, tree, f"{reader.path} [{DESCRIPTION_TOPIC}]")
    return tree


def complete_from_log(
    data: Any,
    log: str | Path,
    source: str,
    urdf: str | Path | None = None,
    marked: Collection[tuple[str, str]] = (),
) -> tuple[Any, dict[str, dict[str, str]]]:
    """The config document with the transforms it leaves out taken from ``log``'s
    ``/tf_static`` and a URDF (:func:`frame_tree`), and where each transform came from, per
    sensor (``config``: the config or its default; ``tf_static``, ``urdf`` or both). ``marked``:
    keys (sensor, key; ``("", "T_base_imu")`` the base's) the config gives as ``imucal init``
    took them from the tree: said to come from it where they still are the tree's. Raises
    :class:`ConfigError` naming the key and the frames where the tree cannot supply one."""
    if not isinstance(data, Mapping) or not isinstance(data.get("sensors"), Mapping):
        return data, {}
    missing, base_missing = _missing(data)
    names = [n for n, s in data["sensors"].items() if isinstance(s, Mapping)]
    sources = {name: config_sources() for name in names}
    if not missing and not base_missing and not marked:
        return data, sources
    from imucal_cli.io.logs import open_log

    document = {**data, "base": dict(data["base"]), "sensors": dict(data["sensors"])}
    with open_log(log) as reader:
        tree = frame_tree(reader, urdf)
        if not tree.edges and not missing:  # (the base at the config's default)
            return data, sources
        wanted = [document["base"].get("topic")] + [
            document["sensors"][n].get("imu_topic")
            for n, _ in [*missing, *marked]
            if n in document["sensors"]
        ]
        available = reader.topics()
        topics = [t for t in dict.fromkeys(wanted) if isinstance(t, str) and t in available]
        frames = imu_frames(reader, topics) if topics else {}
    if base_missing:
        ends, base_imu = _ends(document, frames, "", BASE_KEY)
        found = tree.chain(*ends) if base_imu else None
        if found is not None and base_imu != ends[0]:
            document["base"][BASE_KEY] = found[0].to_dict()
            for name in names:
                sources[name][f"base.{BASE_KEY}"] = found[1]
    for name, key in missing:
        sensor = document["sensors"][name] = dict(document["sensors"][name])
        ends, imu = _ends(document, frames, name, key)
        found = tree.chain(*ends) if imu else None
        if found is None:
            raise ConfigError(source, f"sensors.{name}.{key}", _why(log, tree, ends, imu, key))
        sensor[key], sources[name][key] = found[0].to_dict(), found[1]
    for name, key in marked:  # (given as init took them: still the tree's?)
        if name and not isinstance(document["sensors"].get(name), Mapping):
            continue
        ends, imu = _ends(document, frames, name, key)
        found = tree.chain(*ends) if imu else None
        if found is not None and _same(found[0], document, name, key):
            for each in names if not name else [name]:
                sources[each][key if name else f"base.{BASE_KEY}"] = found[1]
    return document, sources


def _ends(
    document: Any, frames: Mapping[str, str], name: str, key: str
) -> tuple[tuple[Any, Any], Any]:
    """The frames sensor ``name``'s ``key`` runs between in the tree (``name`` empty: the
    base IMU's pose in the base frame), and the IMU's frame (None: not known)."""
    base = document["base"]
    base_frame = str(base.get("frame", "base_link"))
    if not name:
        imu = frames.get(str(base.get("topic")))
        return (base_frame, imu), imu
    sensor = document["sensors"][name]
    imu = sensor.get("imu_frame") or frames.get(str(sensor.get("imu_topic")))
    lidar = str(sensor.get("lidar_frame") or f"{name}_lidar")
    return ((imu, lidar) if key == "T_imu_lidar" else (base_frame, imu)), imu


def _same(T: Transform, document: Any, name: str, key: str) -> bool:
    """Whether the config's value of ``key`` is ``T`` to the digits init writes (1e-6 m,
    1e-5 deg)."""
    from imucal_cli.core.so3 import rotation_angle_deg

    given = (document["sensors"][name] if name else document["base"]).get(key)
    try:
        G = Transform.from_dict(given)
    except Exception:  # (a malformed value: parse_config says so, by its key)
        return False
    return bool(
        np.all(np.abs(G.translation - T.translation) < 1e-6)
        and rotation_angle_deg(G.rotation, T.rotation) < 1e-5
    )


def _why(log: str | Path, tree: FrameTree, ends: tuple[Any, Any], imu: str | None, key: str) -> str:
    """Why the tree cannot supply ``key``, and what settles it: the key itself, or the key
    that names the missing frame's place in the tree (``imu_frame``, ``lidar_frame``)."""
    left_out = "".join(f"; {note}" for note in tree.notes)  # (what reading left out)
    if not tree.edges:
        if tree.notes:  # (it has one, and what was read of it gave no transform)
            return f"missing required key, and {log}'s {TF_TOPIC} gave no transform{left_out}"
        return f"missing required key, and {log} has no {TF_TOPIC} to take it from"
    if imu is None:
        return (
            f"missing required key, and the IMU topic's messages in {log} name no frame: give it "
            "in the config, or imu_frame naming the IMU's frame in the tree"
        )
    gap = [f for f in ends if f not in tree.edges]
    naming = {imu: "imu_frame naming the IMU's frame in the tree"}
    if key == "T_imu_lidar":
        naming[ends[1]] = "lidar_frame naming the lidar's frame in the tree"
    settle = "give it in the config" + "".join(
        f", or {words}" for frame, words in naming.items() if frame in gap or not gap
    )
    where = (
        f"frame {gap[0]!r} is not in {TF_TOPIC}"
        if gap
        else f"no chain joins {ends[0]!r} and {ends[1]!r} in {TF_TOPIC}"
    )
    known = ", ".join(sorted(tree.edges)[:12])
    return f"missing required key: {where} of {log} (its frames: {known}){left_out}; {settle}"
