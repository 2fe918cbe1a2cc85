"""Priors from the log (imucal_cli/frames.py): /tf_static stands in for the config's transforms."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from imucal_cli.api import calibrate, load_config
from imucal_cli.documents import write_document
from imucal_cli.errors import ConfigError
from imucal_cli.frames import FrameTree
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.sim.drive import INS_AWAY
from imucal_cli.sim.writers import write_imu_log
from imucal_cli.types import Transform


@pytest.fixture(scope="module")
def drive():
    """A short drive whose INS sits away from B's origin, turned, its log carrying /tf_static."""
    return simulate_drive(
        DriveOptions(
            scenario="aggressive", duration_s=60.0, seed=3, base_T_base_imu=INS_AWAY, tf_static=True
        )
    )


def _minimal(full: dict) -> dict:
    """The config a ROS user writes first: the topics and the frames, no transform."""
    return {
        "base": {k: full["base"][k] for k in ("topic", "frame", "grade")},
        "sensors": {
            name: {k: s[k] for k in ("imu_topic", "lidar_frame", "grade")}
            for name, s in full["sensors"].items()
        },
    }


@pytest.mark.parametrize(("fmt", "suffix"), [("mcap", ".mcap"), ("rosbag1", ".bag")])
def test_a_config_naming_only_topics_and_frames_calibrates_as_the_full_one(
    drive, tmp_path, fmt, suffix
):
    """The Ouster-style tree (``<name>/os_sensor`` at the CAD prior, the IMU's and the lidar's
    frames under it) and the INS's frame in B give every transform the full config gives: the
    same result, and the output says where each came from."""
    log = write_imu_log(
        tmp_path / f"d{suffix}", fmt, drive.topics(), tf_static=drive.static_transforms()
    )
    full = drive.config_document()
    write_document(tmp_path / "full.yaml", full)
    write_document(tmp_path / "min.yaml", _minimal(full))
    with_config = calibrate(log, tmp_path / "full.yaml")
    from_log = calibrate(log, tmp_path / "min.yaml")
    loaded = load_config(tmp_path / "min.yaml", log)
    for sensor in load_config(tmp_path / "full.yaml").sensors:
        mine = loaded.sensor(sensor.name)
        for key in ("T_imu_lidar", "prior_T_base_imu"):
            np.testing.assert_allclose(
                getattr(mine, key).as_matrix(), getattr(sensor, key).as_matrix(), atol=1e-12
            )
        np.testing.assert_allclose(
            from_log.T_base_lidar(sensor.name).as_matrix(),
            with_config.T_base_lidar(sensor.name).as_matrix(),
            atol=1e-9,
        )
        assert from_log.document()["sensors"][sensor.name]["priors"] == dict.fromkeys(
            ("T_imu_lidar", "prior_T_base_imu", "base.T_base_imu"), "tf_static"
        )
        given = with_config.document()["sensors"][sensor.name]["priors"]
        assert given["T_imu_lidar"] == given["prior_T_base_imu"] == "config"
    np.testing.assert_allclose(loaded.base.T_base_imu.as_matrix(), INS_AWAY.as_matrix(), atol=1e-12)


def test_a_frame_the_tree_lacks_is_an_error_naming_the_key_and_the_frame(drive, tmp_path):
    log = write_imu_log(
        tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=drive.static_transforms()
    )
    document = _minimal(drive.config_document())
    name = next(iter(document["sensors"]))
    document["sensors"][name]["lidar_frame"] = "nowhere_lidar"
    write_document(tmp_path / "bad.yaml", document)
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "bad.yaml", log)
    message = str(caught.value)
    assert f"sensors.{name}.T_imu_lidar" in message and "'nowhere_lidar'" in message
    assert "lidar_frame" in message  # what settles it


def test_a_log_without_tf_static_names_the_missing_key(tmp_path):
    plain = simulate_drive(DriveOptions(scenario="aggressive", duration_s=30.0, seed=1))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", plain.topics())
    write_document(tmp_path / "min.yaml", _minimal(plain.config_document()))
    with pytest.raises(
        ConfigError, match=r"T_imu_lidar: missing required key, and .* no /tf_static"
    ):
        load_config(tmp_path / "min.yaml", log)


def test_the_tree_composes_any_chain_both_ways():
    rng = np.random.default_rng(2)

    def random() -> Transform:
        return Transform.from_rpy(rng.normal(size=3), rng.normal(size=3))

    a_b, b_c, c_d = random(), random(), random()
    tree = FrameTree()
    tree.add("a", "b", a_b)
    tree.add("b", "c", b_c)
    tree.add("c", "d", c_d)
    expected = a_b * b_c * c_d
    np.testing.assert_allclose(tree.lookup("a", "d").as_matrix(), expected.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(
        tree.lookup("d", "a").as_matrix(), expected.inverse().as_matrix(), atol=1e-12
    )
    assert tree.lookup("a", "e") is None


@pytest.mark.parametrize("where", ["file", "topic"])
def test_a_urdf_gives_the_transforms_as_tf_static_does(drive, tmp_path, where):
    """The same tree as a URDF, given with --urdf (a log with no /tf_static) or carried on the
    log's /robot_description (a ROS 1 bag): the same result as the full config, and the output
    says the transforms came from the URDF."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    fmt, suffix = ("mcap", ".mcap") if where == "file" else ("rosbag1", ".bag")
    description = drive.urdf() if where == "topic" else None
    log = write_imu_log(tmp_path / f"d{suffix}", fmt, drive.topics(), robot_description=description)
    (tmp_path / "robot.urdf").write_text(drive.urdf())
    full = drive.config_document()
    write_document(tmp_path / "full.yaml", full)
    write_document(tmp_path / "min.yaml", _minimal(full))
    urdf = ["--urdf", str(tmp_path / "robot.urdf")] if where == "file" else []
    runs = {}
    for name in ("full", "min"):
        out = tmp_path / f"{name}.out.yaml"
        result = CliRunner().invoke(
            app,
            ["calibrate", str(log), "-c", str(tmp_path / f"{name}.yaml"), "-o", str(out), *urdf],
        )
        assert result.exit_code == 0, result.output
        runs[name] = yaml.safe_load(out.read_text())
    for sensor, estimate in runs["min"]["sensors"].items():
        np.testing.assert_allclose(
            Transform.from_dict(estimate["T_base_lidar"]).as_matrix(),
            Transform.from_dict(runs["full"]["sensors"][sensor]["T_base_lidar"]).as_matrix(),
            atol=1e-9,
        )
        assert estimate["priors"] == dict.fromkeys(
            ("T_imu_lidar", "prior_T_base_imu", "base.T_base_imu"), "urdf"
        )


def test_text_that_is_not_a_urdf_is_an_error_naming_the_file(drive, tmp_path):
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    (tmp_path / "bad.urdf").write_text("<robot><joint name='j'>")
    from imucal_cli.errors import InputError

    with pytest.raises(InputError, match=r"bad\.urdf: not a URDF"):
        load_config(tmp_path / "min.yaml", log, tmp_path / "bad.urdf")


def test_follow_mode_takes_the_transforms_from_the_recordings_tf_static(drive, tmp_path):
    """A config naming only topics and frames, followed as the log is recorded (the recorder
    writes the latched /tf_static first): the recording's tree gives the transforms."""
    from recorder import record
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    live, out = tmp_path / "live.mcap", tmp_path / "f.yaml"
    recorder = record(live, drive, factor=20.0, tf_static=drive.static_transforms())
    result = CliRunner().invoke(
        app,
        ["calibrate", str(live), "-c", str(tmp_path / "min.yaml"), "--follow", "-o", str(out)],
    )
    recorder.join(60)
    assert result.exit_code == 0, result.output
    document = yaml.safe_load(out.read_text())
    for sensor in document["sensors"].values():
        assert (
            sensor["priors"]["T_imu_lidar"] == sensor["priors"]["prior_T_base_imu"] == "tf_static"
        )


class _RawTransform:
    """What ``tf_message`` writes of a transform, with any quaternion (a log's author's)."""

    def __init__(self, T, quaternion_xyzw):
        self.translation, self.quaternion_xyzw = T.translation, np.asarray(quaternion_xyzw)


@pytest.mark.parametrize(
    ("quaternion", "says"),
    [([1e-8, 0.0, 0.0, 0.0], "norm 1e-08"), ([np.nan, 0.0, 0.0, 1.0], "not finite")],
)
def test_a_tf_static_rotation_that_is_not_one_is_refused_naming_the_frames(
    drive, tmp_path, quaternion, says
):
    """tf2 refuses a quaternion whose norm is not 1: normalising (1e-8, 0, 0, 0) made a 180 deg
    roll, and the sensor ``ok`` 180 deg wrong. The error names the topic, the frames and the
    value; a NaN is named likewise, not dropped to an error that the frame is missing."""
    from imucal_cli.errors import InputError

    transforms = drive.static_transforms()
    parent, child, T = transforms[2]  # a sensor's IMU frame under its os_sensor
    transforms[2] = (parent, child, _RawTransform(T, quaternion))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=transforms)
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with pytest.raises(InputError) as caught:
        load_config(tmp_path / "min.yaml", log)
    message = str(caught.value)
    assert "/tf_static" in message and str(log) in message and says in message
    assert f"{parent!r} -> {child!r}" in message


def test_a_urdf_joint_that_is_not_finite_is_refused_naming_the_joint(drive, tmp_path):
    from imucal_cli.errors import InputError

    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    urdf = drive.urdf()
    first = urdf.split('<origin xyz="', 1)[1].split('"', 1)[0]
    urdf = urdf.replace(f'xyz="{first}"', 'xyz="nan 0 0"', 1)
    (tmp_path / "robot.urdf").write_text(urdf)
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with pytest.raises(InputError, match=r"robot.urdf: joint 'joint_0' .* not finite"):
        load_config(tmp_path / "min.yaml", log, tmp_path / "robot.urdf")


def test_an_imu_frame_id_not_in_the_tree_is_settled_by_imu_frame(drive, tmp_path):
    """A driver whose IMU messages name a frame the tree does not hold (``imu_link`` against the
    tree's ``os_imu``): the error names the frame and suggests ``imu_frame`` (not
    ``lidar_frame``, which cannot help); ``imu_frame`` then gives the same transforms."""
    from dataclasses import replace

    from imucal_cli.sim.writers import TopicData

    topics = drive.topics()
    mount = drive.mounts[0]
    data = topics[mount.imu_topic]
    stream = replace(data.stream, frame_id="imu_link")
    topics[mount.imu_topic] = TopicData(stream, data.log_time_ns)
    log = write_imu_log(tmp_path / "d.mcap", "mcap", topics, tf_static=drive.static_transforms())
    document = _minimal(drive.config_document())
    write_document(tmp_path / "min.yaml", document)
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "min.yaml", log)
    message = str(caught.value)
    assert "'imu_link' is not in /tf_static" in message and "imu_frame naming" in message
    assert "lidar_frame" not in message.split("; ")[-1]
    document["sensors"][mount.name]["imu_frame"] = mount.imu_frame
    write_document(tmp_path / "fixed.yaml", document)
    loaded = load_config(tmp_path / "fixed.yaml", log).sensor(mount.name)
    np.testing.assert_allclose(
        loaded.T_imu_lidar.as_matrix(), mount.T_imu_lidar.as_matrix(), atol=1e-12
    )


@pytest.mark.parametrize(
    ("edges", "lookups", "says"),
    [
        (
            [("a", "b"), ("b", "c"), ("x", "c")],
            (("a", "c"), ("a", "b")),
            "frame 'c' has two parents, 'b' (tf_static) and 'x' (tf_static)",
        ),
        (
            [("a", "b"), ("b", "c"), ("c", "a")],
            (("a", "b"), ("b", "c")),
            "the edge 'c' -> 'a' (tf_static) closes a loop",
        ),
    ],
)
def test_a_frame_with_two_parents_or_a_loop_is_refused_on_the_chain_through_it(
    edges, lookups, says
):
    """urdfdom and tf2 refuse a second parent; the shortest chain won silently (both sensors
    inconsistent, 14.7 deg and 173 mm from the bogus edge). A chain through such a frame is an
    error naming it; a chain that does not pass it is unaffected."""
    from imucal_cli.errors import InputError

    tree = FrameTree()
    tree.add("b", "elsewhere", Transform.identity(), "tf_static")
    for parent, child in edges:
        tree.add(parent, child, Transform.identity(), "tf_static")
    through, elsewhere = lookups
    with pytest.raises(InputError, match=re.escape(says)):
        tree.lookup(*through)
    assert tree.lookup(*elsewhere) is not None
    assert tree.lookup("b", "elsewhere") is not None


def test_a_tf_static_cap_reached_is_said_where_a_frame_is_then_missing(drive, tmp_path):
    """10,001 junk transforms before the real tree: reading stops at its cap, and the error
    said the frame was not in /tf_static, blaming the tree. It now says the cap was reached."""
    from imucal_cli.frames import MAX_TRANSFORMS

    junk = [(f"junk{k}", f"junk{k}_child", Transform.identity()) for k in range(MAX_TRANSFORMS)]
    tree = junk + drive.static_transforms()
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=tree)
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with pytest.raises(ConfigError, match="/tf_static read to its first 10,000 transforms"):
        load_config(tmp_path / "min.yaml", log)


@pytest.mark.parametrize("kind", ["dev_zero", "fifo", "sparse"])
def test_a_urdf_that_is_no_regular_file_or_too_large_is_refused_at_once(drive, tmp_path, kind):
    """``--urdf /dev/zero`` (or a sparse file) was read whole until killed, a FIFO nobody
    writes hung forever: a URDF is a regular file, read to its cap and no further."""
    import os
    import time

    from imucal_cli.errors import InputError

    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    urdf = tmp_path / "robot.urdf"
    if kind == "dev_zero":
        urdf = Path("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(urdf)
    else:
        with urdf.open("wb") as handle:
            handle.truncate(1 << 40)  # a terabyte, sparse
    start = time.monotonic()
    says = "larger than 16 MiB" if kind == "sparse" else "not a regular file"
    with pytest.raises(InputError, match=says):
        load_config(tmp_path / "min.yaml", log, urdf)
    assert time.monotonic() - start < 5.0


def test_a_tf_static_message_larger_than_a_tree_is_left_out_and_said(drive, tmp_path, monkeypatch):
    """One /tf_static message of 200 MiB (2.38 M transforms, 1.6 MB compressed) was
    deserialised whole before the transform cap counted: 2.5 GB. A message larger than any
    static tree (MAX_TF_MESSAGE_BYTES, lowered here to the test's tree) is not deserialised,
    and a frame then missing says so."""
    import imucal_cli.frames as frames

    monkeypatch.setattr(frames, "MAX_TF_MESSAGE_BYTES", 100)
    log = write_imu_log(
        tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=drive.static_transforms()
    )
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with pytest.raises(
        ConfigError, match=r"a message of 0 MB, larger than a static tree"
    ) as caught:
        load_config(tmp_path / "min.yaml", log)
    assert "/tf_static gave no transform" in str(caught.value)  # (not: "has no /tf_static")


def test_follow_mode_takes_the_transforms_from_urdf(drive, tmp_path):
    """``calibrate --follow --urdf`` dropped the URDF, waited the whole --timeout and blamed
    the log: the URDF now gives the transforms as it does without --follow, and a file that is
    no URDF is said at once."""
    from recorder import record
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    (tmp_path / "robot.urdf").write_text(drive.urdf())
    live, out = tmp_path / "live.mcap", tmp_path / "f.yaml"
    recorder = record(live, drive, factor=20.0)
    argv = ["calibrate", str(live), "-c", str(tmp_path / "min.yaml"), "--follow"]
    result = CliRunner().invoke(
        app, [*argv, "--urdf", str(tmp_path / "robot.urdf"), "-o", str(out), "--timeout", "60"]
    )
    recorder.join(60)
    assert result.exit_code == 0, result.output
    for sensor in yaml.safe_load(out.read_text())["sensors"].values():
        assert sensor["priors"]["T_imu_lidar"] == sensor["priors"]["prior_T_base_imu"] == "urdf"
    (tmp_path / "bad.urdf").write_text("<robot")
    bad = CliRunner().invoke(app, [*argv, "--urdf", str(tmp_path / "bad.urdf"), "--timeout", "60"])
    assert bad.exit_code == 2 and "bad.urdf: not a URDF" in bad.stderr


def test_a_value_the_tree_supplies_is_judged_as_the_trees_not_the_files(drive, tmp_path):
    """A /tf_static lidar frame 5 m from its IMU: the error named
    ``min.yaml: sensors.X.T_imu_lidar.translation``, a key the file leaves out. It now says the
    value came from the log's tree."""
    transforms = drive.static_transforms()
    parent, child, T = transforms[3]  # a sensor's lidar frame under its os_sensor
    moved = Transform(T.rotation, T.translation + np.array([5.0, 0.0, 0.0]))
    transforms[3] = (parent, child, moved)
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=transforms)
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "min.yaml", log)
    message = str(caught.value)
    assert ".T_imu_lidar.translation" in message and "more than 1 m" in message
    assert f"leaves out, taken from tf_static in {log}" in message


def test_a_static_transform_beyond_any_vehicle_is_refused_without_numpy_warnings(drive, tmp_path):
    """A /tf_static translation of 1e308 m: numpy's overflow warnings reached stderr before
    the error. It is refused where it is read, naming the frames, and nothing warns."""
    import warnings

    from imucal_cli.errors import InputError

    transforms = drive.static_transforms()
    parent, child, T = transforms[3]
    transforms[3] = (parent, child, Transform(T.rotation, np.array([1e308, 1e308, 0.0])))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics(), tf_static=transforms)
    write_document(tmp_path / "min.yaml", _minimal(drive.config_document()))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=f"{re.escape(repr(parent))} -> .* beyond 10000 m"):
            load_config(tmp_path / "min.yaml", log)
