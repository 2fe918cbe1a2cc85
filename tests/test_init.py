"""`imucal init` (imucal_cli/init.py): a starting config from what a log holds."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.api import calibrate
from imucal_cli.config import load_config
from imucal_cli.errors import ConfigError
from imucal_cli.init import sensor_name
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.sim.writers import write_imu_log


def test_sensor_names_come_from_the_topics_distinctive_tokens():
    taken: set[str] = set()
    assert sensor_name("/lidar/front_left_top/imu", taken) == "front_left_top"
    assert sensor_name("/ouster/imu", taken) == "lidar"
    assert sensor_name("/livox/imu", {"lidar"}) == "lidar_2"
    assert sensor_name("/os1-64/imu", taken) == "os1_64"
    assert sensor_name("/3d/imu", taken) == "lidar_3d"


@pytest.mark.parametrize("name", ["aggressive", "urban"])
def test_init_on_a_sample_log_writes_a_config_that_checks_and_calibrates(tmp_path, name):
    """The sample logs carry /tf_static: `imucal init` finds the base, every transform, and
    its config passes check-config and calibrates as the shipped one does, the priors read
    from the log equal to the shipped config's to the digits it writes."""
    from conftest import SAMPLE_DATA
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    runner = CliRunner()
    log, config = SAMPLE_DATA / f"{name}.mcap", tmp_path / "init.yaml"
    made = runner.invoke(app, ["init", str(log), "-o", str(config)])
    assert made.exit_code == 0, made.output
    assert "not in the log" not in made.stderr
    assert runner.invoke(app, ["check-config", str(config)]).exit_code == 0
    written, shipped = load_config(config), load_config(SAMPLE_DATA / f"{name}.config.yaml")
    assert written.base.topic == shipped.base.topic
    for sensor in shipped.sensors:
        mine = written.sensor(sensor.name)
        assert mine.imu_topic == sensor.imu_topic and mine.lidar_frame == sensor.lidar_frame
        for key in ("T_imu_lidar", "prior_T_base_imu"):
            np.testing.assert_allclose(
                getattr(mine, key).as_matrix(), getattr(sensor, key).as_matrix(), atol=1e-8
            )
    run = calibrate(log, written)
    assert all(s["status"] == "ok" for s in run.document()["sensors"].values())


def test_init_on_a_log_without_transforms_writes_placeholders_and_says_which(tmp_path):
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    plain = simulate_drive(DriveOptions(scenario="aggressive", duration_s=30.0, seed=1))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", plain.topics())
    made = CliRunner().invoke(app, ["init", str(log), "-o", str(tmp_path / "c.yaml")])
    assert made.exit_code == 0, made.output
    text = (tmp_path / "c.yaml").read_text()
    for name in plain.config_document()["sensors"]:
        for key in ("T_imu_lidar", "prior_T_base_imu"):
            assert f"imucal: {name}: {key} is not in the log (" in made.stderr
        assert (
            f"{name}: prior_T_base_imu is not in the log (frame 'base_link' is not in /tf_static "
            "or the URDF): fill its placeholder"
        ) in made.stderr
        assert f"{name}: T_imu_lidar is not in the log (no frame named '...lidar'" in made.stderr
    assert text.count("# T_imu_lidar: {translation: [0, 0, 0]") == 2
    with pytest.raises(ConfigError, match="T_imu_lidar: missing required key"):
        load_config(tmp_path / "c.yaml")


def test_init_on_a_drive_whose_ins_sits_away_finds_it_in_the_tree(tmp_path):
    """The INS upside down, turned and 1.6 m from B's origin, its frame in /tf_static: init
    names it the base and writes its pose; the config checks and calibrates."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.sim.drive import INS_AWAY

    drive = simulate_drive(
        DriveOptions(
            scenario="aggressive", duration_s=60.0, seed=3, base_T_base_imu=INS_AWAY, tf_static=True
        )
    )
    log = write_imu_log(
        tmp_path / "d.bag", "rosbag1", drive.topics(), tf_static=drive.static_transforms()
    )
    runner = CliRunner()
    made = runner.invoke(app, ["init", str(log), "-o", str(tmp_path / "c.yaml")])
    assert made.exit_code == 0, made.output
    assert runner.invoke(app, ["check-config", str(tmp_path / "c.yaml")]).exit_code == 0
    config = load_config(tmp_path / "c.yaml")
    assert config.base.topic == drive.config_document()["base"]["topic"]
    np.testing.assert_allclose(config.base.T_base_imu.as_matrix(), INS_AWAY.as_matrix(), atol=1e-8)
    run = calibrate(log, config)
    assert all(s["status"] == "ok" for s in run.document()["sensors"].values())


def test_init_refuses_an_output_that_is_its_urdf_and_damaged_imu_data_is_one_line(tmp_path):
    """-o never overwrites an input (the URDF too); a log whose IMU messages do not decode is
    one line naming it, exit 2, no traceback."""
    from mcap.writer import Writer
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.sim.writers import _msgdef

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=30.0, seed=1))
    urdf = tmp_path / "robot.yaml"  # (a URDF under a name -o would take)
    text = '<robot name="r"><link name="base_link"/></robot>'
    urdf.write_text(text)
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    runner = CliRunner()
    made = runner.invoke(app, ["init", str(log), "--urdf", str(urdf), "-o", str(urdf)])
    assert made.exit_code == 2 and "an input of this run" in made.stderr
    assert urdf.read_text() == text
    bad = tmp_path / "bad.mcap"
    with bad.open("wb") as handle:  # IMU channels whose messages are a few garbage bytes
        writer = Writer(handle)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(
            name="sensor_msgs/msg/Imu", encoding="ros2msg", data=_msgdef(False)[0].encode()
        )
        for topic in ("/gnss/imu", "/lidar/a/imu"):
            channel = writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
            for i in range(50):
                stamp = 10**9 + i * 10**7
                data = b"\x00\x01\x00\x00" + b"\x07" * (20 + i % 7)
                writer.add_message(
                    channel_id=channel, log_time=stamp, data=data, publish_time=stamp
                )
        writer.finish()
    result = runner.invoke(app, ["init", str(bad)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert len(result.stderr.strip().splitlines()) == 1 and str(bad) in result.stderr


def test_a_log_cannot_write_keys_into_inits_config_nor_escapes_onto_the_terminal(tmp_path):
    """A frame name in /tf_static holding a newline was pasted raw into the YAML: the log's
    author set the user's prior_T_base_imu, check-config passed. A topic name with an OSC
    sequence reached the terminal raw. Names a config would refuse are now left out, each
    said in one printable line, and every value goes through the YAML emitter."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app

    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=30.0, seed=1, tf_static=True)
    )
    evil_frame = "x\n    prior_T_base_imu: {translation: [9, 9, 9], rpy_deg: [0, 0, 0]}\n    lidar"
    transforms = [  # (one evil frame per sensor: a frame has one parent)
        (parent, parent.split("/")[0] + evil_frame if child.endswith("lidar") else child, T)
        for parent, child, T in drive.static_transforms()
    ]
    topics = drive.topics()
    topics["/evil\x1b]0;pwned\x07/imu"] = next(iter(topics.values()))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", topics, tf_static=transforms)
    made = CliRunner().invoke(app, ["init", str(log)])
    assert made.exit_code == 0, made.output
    assert "\x1b" not in made.stdout and "\x1b" not in made.stderr
    assert "IMU topic '/evil\\x1b]0;pwned\\x07/imu' skipped" in made.stderr
    assert "the lidar frame 'front_left_topx\\n    prior_T_base_imu" in made.stderr
    import yaml

    document = yaml.safe_load(made.stdout)
    assert len(document["sensors"]) == len(drive.mounts)
    for name, sensor in document["sensors"].items():
        assert sensor["lidar_frame"] == f"{name}_lidar"
        prior = sensor["prior_T_base_imu"]  # from the tree, not from the frame's name
        assert prior["translation"] != [9, 9, 9]


def test_check_config_with_the_log_marks_each_key_the_log_supplied(tmp_path):
    """``check-config --log`` fills in what the config leaves out from the log's /tf_static:
    each such key's line says so (the YAML reads as the config it is), and a note on stderr
    names each key, for --json too; the keys the config gives are not marked."""
    import yaml
    from conftest import SAMPLE_DATA
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.documents import load_document, write_document

    runner = CliRunner()
    config = load_document(SAMPLE_DATA / "aggressive.config.yaml")
    first, second = list(config["sensors"])
    del config["sensors"][first]["T_imu_lidar"], config["sensors"][first]["prior_T_base_imu"]
    write_document(tmp_path / "c.yaml", config)
    args = ["check-config", str(tmp_path / "c.yaml"), "--log", str(SAMPLE_DATA / "aggressive.mcap")]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    marked = [line.strip() for line in result.stdout.splitlines() if "# from" in line]
    assert marked == [
        "T_base_imu:  # from tf_static",
        "T_imu_lidar:  # from tf_static",
        "prior_T_base_imu:  # from tf_static",
    ]
    filled = yaml.safe_load(result.stdout)
    assert filled["sensors"][second]["T_imu_lidar"]["rpy_deg"] == pytest.approx(
        config["sensors"][second]["T_imu_lidar"]["rpy_deg"]
    )
    for key in (f"sensors.{first}.T_imu_lidar", f"sensors.{first}.prior_T_base_imu"):
        assert f"{key}: from" in result.stderr
    assert f"sensors.{second}" not in result.stderr
    as_json = runner.invoke(app, [*args, "--json"])
    assert as_json.exit_code == 0 and f"sensors.{first}.T_imu_lidar: from" in as_json.stderr


def test_a_config_init_wrote_says_its_priors_came_from_the_log_while_they_still_do(tmp_path):
    """Transforms ``init`` took from /tf_static came back as ``priors: config`` (the config
    gives them): they are said to come from tf_static while the config's value is still the
    tree's, calibrated or followed alike, and ``config`` once a user has changed one."""
    from conftest import SAMPLE_DATA
    from typer.testing import CliRunner

    from imucal_cli.api import load_config as load_for_log
    from imucal_cli.cli import app
    from imucal_cli.pipeline import recording_config

    log, config = SAMPLE_DATA / "aggressive.mcap", tmp_path / "init.yaml"
    assert CliRunner().invoke(app, ["init", str(log), "-o", str(config)]).exit_code == 0
    for loaded in (load_for_log(config, log), recording_config(config, log, 0.0, None)[0]):
        assert all(set(sources.values()) == {"tf_static"} for sources in loaded.priors.values()), (
            loaded.priors
        )
    document = calibrate(log, load_for_log(config, log)).document()
    assert {s["priors"]["T_imu_lidar"] for s in document["sensors"].values()} == {"tf_static"}
    text = config.read_text().splitlines()
    first = next(k for k, line in enumerate(text) if line.strip().startswith("T_imu_lidar:"))
    text[first] = text[first].replace("0.028535", "0.038535")  # (a centimetre: the user's own)
    config.write_text("\n".join(text) + "\n")
    edited = load_for_log(config, log).priors
    assert sorted(s["T_imu_lidar"] for s in edited.values()) == ["config", "tf_static"]
    assert all(s["prior_T_base_imu"] == "tf_static" for s in edited.values())
