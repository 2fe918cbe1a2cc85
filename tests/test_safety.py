"""A user's files are never lost, and a name never smuggles in a command or a terminal escape.

Each test reproduces one finding of the reliability probe (issue 28, items 1-5).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.documents import write_document
from imucal_cli.sim.writers import write_imu_log

runner = CliRunner()


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file below ``folder`` with the hash of its content."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture()
def bags(tmp_path, short_drive):
    """Two rosbag2 folders of the short drive, and its config, side by side."""
    for name in ("d1", "d2"):
        write_imu_log(tmp_path / name, "rosbag2-mcap", short_drive.topics())
    config = tmp_path / "config.yaml"
    write_document(config, short_drive.config_document())
    return tmp_path, config


# ------------------------------------------------------------------ 1. simulate over a folder


def test_simulate_refuses_an_existing_folder_and_keeps_its_files(tmp_path):
    folder = tmp_path / "work"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    before = _snapshot(tmp_path)
    result = runner.invoke(app, ["simulate", str(folder), "--duration", "2"])
    assert result.exit_code == 2
    assert "exists" in result.stderr and str(folder) in result.stderr and "--force" in result.stderr
    assert _snapshot(tmp_path) == before
    # --force replaces only what it recognises as a log: a folder of notes is not one
    result = runner.invoke(app, ["simulate", str(folder), "--duration", "2", "--force"])
    assert result.exit_code == 2 and "not a log" in result.stderr
    assert _snapshot(tmp_path) == before


def test_simulate_of_the_parent_folder_changes_nothing(tmp_path, monkeypatch):
    inner = tmp_path / "inner"
    inner.mkdir()
    (tmp_path / "keep.txt").write_text("mine")
    monkeypatch.chdir(inner)
    before = _snapshot(tmp_path)
    for target in ("..", "."):
        result = runner.invoke(app, ["simulate", target, "--duration", "2", "--force"])
        assert result.exit_code == 2, result.output
        assert len(result.stderr.strip().splitlines()) == 1
    assert _snapshot(tmp_path) == before


def test_simulate_force_replaces_a_log_it_wrote_but_not_other_files(tmp_path):
    log = tmp_path / "drive.mcap"
    assert runner.invoke(app, ["simulate", str(log), "--duration", "2"]).exit_code == 0
    first = log.read_bytes()
    assert (
        runner.invoke(app, ["simulate", str(log), "--duration", "2", "--seed", "1"]).exit_code == 2
    )
    assert log.read_bytes() == first
    assert (
        runner.invoke(
            app, ["simulate", str(log), "--duration", "2", "--seed", "1", "--force"]
        ).exit_code
        == 0
    )
    assert log.read_bytes() != first
    other = tmp_path / "thesis.mcap"
    other.write_text("not a log")
    result = runner.invoke(app, ["simulate", str(other), "--duration", "2", "--force"])
    assert result.exit_code == 2 and "not a log" in result.stderr
    assert other.read_text() == "not a log"
    # a rosbag2 folder it recognises is replaced whole
    bag = tmp_path / "bag"
    assert runner.invoke(app, ["simulate", str(bag), "--duration", "2"]).exit_code == 0
    assert (
        runner.invoke(
            app, ["simulate", str(bag), "--duration", "2", "--seed", "2", "--force"]
        ).exit_code
        == 0
    )
    assert (bag / "metadata.yaml").is_file()


def test_simulate_refuses_to_overwrite_a_truth_or_config_beside_it(tmp_path):
    (tmp_path / "drive.truth.yaml").write_text("mine: 1\n")
    result = runner.invoke(app, ["simulate", str(tmp_path / "drive.mcap"), "--duration", "2"])
    assert result.exit_code == 2 and "drive.truth.yaml" in result.stderr
    assert not (tmp_path / "drive.mcap").exists()
    assert (tmp_path / "drive.truth.yaml").read_text() == "mine: 1\n"


# ------------------------------------------------------------------ 2. batch into the bags' folder


def test_batch_of_bags_given_as_metadata_leaves_the_bags_readable(bags):
    root, config = bags
    before = _snapshot(root)
    result = runner.invoke(
        app,
        [
            "batch",
            str(root / "d1" / "metadata.yaml"),
            str(root / "d2" / "metadata.yaml"),
            "-c",
            str(config),
            "--out-dir",
            str(root),
        ],
    )
    assert result.exit_code in (0, 1), result.output
    after = _snapshot(root)
    assert {k: v for k, v in after.items() if k in before} == before  # nothing the user had changed
    assert (root / "d1.yaml").is_file() and (root / "d2.yaml").is_file()  # named after the bags
    assert runner.invoke(app, ["inspect", str(root / "d1")]).exit_code == 0


def test_batch_names_outputs_by_the_whole_stem(tmp_path, short_drive):
    config = tmp_path / "config.yaml"
    write_document(config, short_drive.config_document())
    for day in ("2024.01.05", "2024.01.06"):
        write_imu_log(tmp_path / f"{day}.mcap", "mcap", short_drive.topics())
    out = tmp_path / "out"
    result = runner.invoke(
        app,
        [
            "batch",
            str(tmp_path / "2024.01.05.mcap"),
            str(tmp_path / "2024.01.06.mcap"),
            "-c",
            str(config),
            "--out-dir",
            str(out),
        ],
    )
    assert result.exit_code in (0, 1), result.output
    assert (out / "2024.01.05.yaml").is_file() and (out / "2024.01.06.yaml").is_file()


def test_a_second_batch_into_the_same_folder_does_not_overwrite_the_first(tmp_path, short_drive):
    config = tmp_path / "config.yaml"
    write_document(config, short_drive.config_document())
    log = write_imu_log(tmp_path / "a.mcap", "mcap", short_drive.topics())
    out = tmp_path / "out"
    assert runner.invoke(
        app, ["batch", str(log), "-c", str(config), "--out-dir", str(out)]
    ).exit_code in (0, 1)
    before = _snapshot(out)
    result = runner.invoke(app, ["batch", str(log), "-c", str(config), "--out-dir", str(out)])
    assert result.exit_code == 2 and "--force" in result.stderr and str(out) in result.stderr
    assert _snapshot(out) == before
    assert runner.invoke(
        app, ["batch", str(log), "-c", str(config), "--out-dir", str(out), "--force"]
    ).exit_code in (0, 1)


# ------------------------------------------------------------------ 3. an output that is an input


@pytest.mark.parametrize("which", ["metadata", "config", "storage"])
def test_calibrate_refuses_an_output_that_is_one_of_its_inputs(bags, which):
    root, config = bags
    bag = root / "d1"
    target = {
        "metadata": bag / "metadata.yaml",
        "config": config,
        "storage": next(bag.glob("*.mcap")).with_suffix(".yaml"),
    }[which]
    before = _snapshot(root)
    for command in ("calibrate", "segments", "biases"):
        result = runner.invoke(
            app, [command, str(bag / "metadata.yaml"), "-c", str(config), "-o", str(target)]
        )
        assert result.exit_code == 2, (command, result.output)
        assert str(target) in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert _snapshot(root) == before


def test_evaluate_and_inspect_refuse_to_write_over_their_inputs(tmp_path, short_drive):
    truth = tmp_path / "truth.yaml"
    write_document(truth, short_drive.truth_document())
    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    before = _snapshot(tmp_path)
    assert runner.invoke(app, ["evaluate", str(truth), str(truth), "-o", str(truth)]).exit_code == 2
    assert (
        runner.invoke(app, ["evaluate", str(truth), str(truth), "--junit", str(truth)]).exit_code
        == 2
    )
    assert (
        runner.invoke(app, ["inspect", str(log), "-o", str(truth.with_name("d.mcap"))]).exit_code
        == 2
    )
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------ 4. names in scripts


def _document() -> dict:
    """A calibrate document of one sensor, as ``imucal calibrate`` writes it."""
    T = {"translation": [1.0, 0.5, 2.0], "rotation": [0.0, 0.0, 0.0, 1.0]}
    noise = {
        "accelerometer_noise_density": 2e-3,
        "accelerometer_random_walk": 3e-3,
        "gyroscope_noise_density": 2e-4,
        "gyroscope_random_walk": 2e-5,
    }
    sensor = {
        "status": "ok",
        "lidar_frame": "front_lidar",
        "imu_topic": "/front/imu",
        "T_base_lidar": T,
        "T_base_imu": T,
        "time_offset_s": 0.0,
        "time_offset_observable": True,
        "imu_rate_hz": 100.0,
        "imu_noise": noise,
    }
    return {
        "base_frame": "base_link",
        "base_topic": "/gnss/imu",
        "base_imu_rate_hz": 100.0,
        "base_imu_noise": noise,
        "sensors": {"front": sensor},
    }


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("base.frame", "x; touch /tmp/p"),
        ("lidar_frame", "lidar$(id)"),
        ("lidar_frame", "a b"),
        ("sensor", "front\nleft"),
        ("base.topic", "/imu`id`"),
    ],
)
def test_a_config_with_a_name_ros_would_refuse_is_an_error_naming_the_key(
    tmp_path, short_drive, key, value
):
    document = short_drive.config_document()
    first = next(iter(document["sensors"]))
    if key == "base.frame":
        document["base"]["frame"] = value
    elif key == "base.topic":
        document["base"]["topic"] = value
    elif key == "lidar_frame":
        document["sensors"][first]["lidar_frame"] = value
    else:
        document["sensors"][value] = document["sensors"].pop(first)
    config = tmp_path / "config.yaml"
    write_document(config, document)
    result = runner.invoke(app, ["check-config", str(config)])
    assert result.exit_code == 2
    line = result.stderr.strip()
    assert len(line.splitlines()) == 1 and str(config) in line
    assert (key.split(".")[-1] if key != "sensor" else "sensors") in line


@pytest.mark.parametrize(
    ("where", "value"),
    [
        ("lidar_frame", "x; touch {pwned}"),
        ("base_frame", "b$(touch {pwned})"),
        ("name", "s\nimu9: {{}}"),
        ("imu_topic", "/a\nimu9: 1"),
    ],
)
def test_export_refuses_a_document_whose_names_ros_would_refuse(tmp_path, where, value):
    """A calibrate document edited by hand or written by another tool: nothing is written."""
    document = _document()
    value = value.format(pwned=tmp_path / "pwned")
    if where == "base_frame":
        document["base_frame"] = value
    elif where == "name":
        document["sensors"][value] = document["sensors"].pop("front")
    else:
        document["sensors"]["front"][where] = value
    path = tmp_path / "estimate.yaml"
    write_document(path, document)
    for fmt in ("tf-static-ros2", "tf-static-ros1", "kalibr"):
        out = tmp_path / "out.txt"
        result = runner.invoke(app, ["export", str(path), "-f", fmt, "-o", str(out)])
        assert result.exit_code == 2, (fmt, result.output)
        assert len(result.stderr.strip().splitlines()) == 1 and str(path) in result.stderr
        assert not out.exists()
    assert not (tmp_path / "pwned").exists()


def test_tf_static_scripts_shell_quote_every_value(tmp_path):
    """Below the validation, a script quotes what it holds: run with ``echo`` in place of ROS,
    it prints the frames back as they are and runs nothing they hold."""
    import dataclasses

    from imucal_cli.exports import Extrinsics, tf_static_ros1, tf_static_ros2

    ex = Extrinsics.from_document(_document(), "x")
    pwned = tmp_path / "pwned"
    hostile = dataclasses.replace(
        ex, sensors=(dataclasses.replace(ex.sensors[0], lidar_frame=f"a; touch {pwned}"),)
    )
    for make in (tf_static_ros2, tf_static_ros1):
        script = tmp_path / "s.sh"
        text = make(hostile, f"base$(touch {pwned})")[0]
        script.write_text(text.replace("ros2 run", "echo").replace("rosrun", "echo"))
        done = subprocess.run(
            ["sh", str(script)], capture_output=True, text=True, check=True, timeout=10
        )
        assert not pwned.exists()
        assert f"a; touch {pwned}" in done.stdout and f"base$(touch {pwned})" in done.stdout


# ------------------------------------------------------------------ 5. names on the terminal and in
# XML


def _hostile_topic_log(tmp_path: Path, short_drive) -> tuple[Path, Path, str]:
    """A log whose base topic name carries terminal escapes, and a config asking for another."""
    evil = "/imu\x1b]0;owned\x07\x1b[2K\rcalibration ok\n"
    topics = short_drive.topics()
    base = next(iter(topics))
    renamed = {(evil if topic == base else topic): data for topic, data in topics.items()}
    log = write_imu_log(tmp_path / "evil.mcap", "mcap", renamed)
    config = tmp_path / "config.yaml"
    write_document(config, short_drive.config_document())
    return log, config, evil


def test_control_characters_in_topic_names_never_reach_the_terminal(tmp_path, short_drive):
    log, config, _ = _hostile_topic_log(tmp_path, short_drive)
    for argv in (["inspect", str(log)], ["calibrate", str(log), "-c", str(config)]):
        result = runner.invoke(app, argv)
        for text in (result.stdout, result.stderr):
            assert "\x1b" not in text and "\x07" not in text and "\r" not in text, argv
        if result.exit_code == 2:
            assert len(result.stderr.strip().splitlines()) == 1
            assert "calibration ok" not in result.stderr.splitlines()[0][:20]


def test_junit_with_hostile_names_is_well_formed_xml(tmp_path, short_drive):
    from imucal_cli.fleet import Row, junit_xml

    text = junit_xml(
        [
            Row(
                "log\x1b[2K\x00<&>.mcap",
                "s\x07",
                "failed",
                error="topic /imu\x1b]0;x\x07 missing\x0c",
            )
        ]
    )
    root = ET.fromstring(text)
    assert root.find(".//error") is not None
    assert "\x1b" not in text and "\x00" not in text


def test_printable_keeps_plain_text_and_shows_what_it_removed():
    from imucal_cli.names import printable

    assert printable("front_left_top: ok, 3.2 deg, é ü") == "front_left_top: ok, 3.2 deg, é ü"
    assert printable("a\x1b[2Kb\rc\nd\x9b") == "a\\x1b[2Kb\\rc\\nd\\x9b"
    assert os.linesep not in printable("x\ny")


# ------------------------------------------------------------------ 13. crashes become one line


def test_mcap_without_statistics_whose_message_index_offset_is_off_is_read_from_its_records(
    tmp_path, short_drive
):
    """An indexed MCAP with no Statistics record whose chunk index points 3 bytes past its
    message index: counted from the records themselves (it was a traceback, exit 1)."""
    import struct

    from mcap.data_stream import RecordBuilder
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from imucal_cli.reading import read_imu

    topics = short_drive.topics()
    good = write_imu_log(tmp_path / "good.mcap", "mcap", topics)
    plain = tmp_path / "plain.mcap"
    with good.open("rb") as handle, plain.open("wb") as out:
        reader = make_reader(handle)
        writer = Writer(out, use_statistics=False)
        writer.start(profile="ros2", library="test")
        ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in ids:
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id
                )
            writer.add_message(
                ids[channel.id],
                message.log_time,
                message.data,
                message.publish_time,
                message.sequence,
            )
        writer.finish()
    with plain.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary.statistics is None
    data = plain.read_bytes()
    (summary_start,) = struct.unpack_from("<QQI", data, len(data) - 8 - 20)[:1]
    builder = RecordBuilder()
    for record in (*summary.schemas.values(), *summary.channels.values()):
        record.write(builder)
    for k, index in enumerate(summary.chunk_indexes):
        if k == 0:
            index.message_index_offsets = {c: o + 3 for c, o in index.message_index_offsets.items()}
        index.write(builder)
    footer = struct.pack("<BQ", 0x02, 20) + struct.pack("<QQI", summary_start, 0, 0)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data[:summary_start] + bytes(builder.end()) + footer + b"\x89MCAP0\r\n")
    result = runner.invoke(app, ["inspect", str(bad), "--json"])
    assert result.exit_code == 0, result.output
    got = read_imu(bad, list(topics))
    assert all(len(got[t].stream) == len(topics[t].stream) for t in topics)


def test_a_full_disk_at_the_end_is_one_line_and_leaves_no_file(tmp_path, monkeypatch):
    import errno

    from conftest import SAMPLE_DATA

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "e.yaml"
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(SAMPLE_DATA / "aggressive.mcap"),
            "-c",
            str(SAMPLE_DATA / "aggressive.config.yaml"),
            "-o",
            str(out),
        ],
    )
    assert (
        result.exit_code == 2
        and "No space left on device" in result.stderr
        and str(out) in result.stderr
    )
    assert len(result.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------ 6 (issue 48). files nobody named this run


def test_init_keeps_an_existing_config_without_force(tmp_path, short_drive):
    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    mine = tmp_path / "vehicle.yaml"
    mine.write_text("# my hand-written config\n")
    result = runner.invoke(app, ["init", str(log), "-o", str(mine)])
    assert result.exit_code == 2 and "--force" in result.stderr
    assert mine.read_text() == "# my hand-written config\n"
    assert runner.invoke(app, ["init", str(log), "-o", str(mine), "--force"]).exit_code == 0
    assert mine.read_text().startswith("# imucal config from")


@pytest.mark.parametrize("command", ["init", "calibrate"])
def test_no_output_goes_into_a_bag_that_is_not_an_input(bags, command):
    """``-o otherbag/metadata.yaml`` replaced the metadata of a bag the run never read (that
    bag no longer opened); a log file is never an output either."""
    root, config = bags
    before = _snapshot(root)
    mcap = next((root / "d2").glob("*.mcap"))
    for target in (root / "d2" / "metadata.yaml", root / "d2" / "result.yaml", mcap):
        args = [command, str(root / "d1"), "-o", str(target)]
        args += ["--force"] if command == "init" else ["-c", str(config)]
        result = runner.invoke(app, args)
        assert result.exit_code == 2, (target, result.output)
        assert str(target) in result.stderr
    assert _snapshot(root) == before


def test_export_never_replaces_a_launch_file_nobody_named(tmp_path, short_drive):
    """``-f tf-static-ros2 -o robot.sh`` writes robot.launch.xml beside it: a hand-written
    one there is kept (and the run refused); one an earlier export wrote is replaced."""
    from imucal_cli.api import calibrate_streams
    from imucal_cli.outputs import calibration_document

    result = calibrate_streams(short_drive.streams(), short_drive.config())
    estimate = tmp_path / "estimate.yaml"
    write_document(estimate, calibration_document(result, "sim.mcap"))
    launch = tmp_path / "robot.launch.xml"
    launch.write_text("<launch><!-- mine --></launch>\n")
    args = ["export", str(estimate), "-f", "tf-static-ros2", "-o", str(tmp_path / "robot.sh")]
    args += ["--allow-not-ok"]
    refused = runner.invoke(app, args)
    assert refused.exit_code == 2 and str(launch) in refused.stderr
    assert launch.read_text() == "<launch><!-- mine --></launch>\n"
    assert not (tmp_path / "robot.sh").exists()
    launch.unlink()
    assert runner.invoke(app, args).exit_code == 0
    written = launch.read_text()
    assert runner.invoke(app, args).exit_code == 0  # its own: replaced
    assert launch.read_text() == written


def test_a_batch_into_a_folder_another_batch_holds_is_refused(tmp_path, short_drive):
    """Two batches into one --out-dir at once both passed the "exists" check, and the first's
    results were gone: the folder is now held for one batch at a time."""
    import fcntl

    config = tmp_path / "config.yaml"
    write_document(config, short_drive.config_document())
    log = write_imu_log(tmp_path / "a.mcap", "mcap", short_drive.topics())
    out = tmp_path / "out"
    out.mkdir()
    held = os.open(out, os.O_RDONLY)  # what a running batch holds
    fcntl.flock(held, fcntl.LOCK_EX)
    try:
        result = runner.invoke(app, ["batch", str(log), "-c", str(config), "--out-dir", str(out)])
    finally:
        os.close(held)
    assert result.exit_code == 2 and "another imucal run" in result.stderr
    assert list(out.iterdir()) == []
    done = runner.invoke(app, ["batch", str(log), "-c", str(config), "--out-dir", str(out)])
    assert done.exit_code in (0, 1) and (out / "summary.csv").exists()


@pytest.fixture()
def small_disk(tmp_path):
    """A 1 MiB tmpfs (root only: skipped elsewhere), unmounted after."""
    disk = tmp_path / "small"
    disk.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1M", "tmpfs", str(disk)], capture_output=True
    )
    if made.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (not root)")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)


@pytest.mark.parametrize("fmt", ["mcap", "rosbag2-sqlite3"])
def test_simulate_on_a_full_disk_is_one_line_and_leaves_nothing(small_disk, fmt):
    """simulate on a full disk escaped as a traceback (ENOSPC, and sqlite3's "database or
    disk is full"): one line naming the log, exit 2, no partial folder."""
    out = small_disk / ("d.mcap" if fmt == "mcap" else "d")
    result = runner.invoke(
        app, ["simulate", str(out), "--duration", "60", "--format", fmt, "--sensors", "4"]
    )
    assert result.exit_code == 2, result.output
    assert f"{out}: cannot write the log" in result.stderr
    assert result.stderr.count("\n") == 1
    assert list(small_disk.iterdir()) == []
