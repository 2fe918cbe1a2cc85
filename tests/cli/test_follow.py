"""calibrate --follow: logs read while they are written (tests/recorder.py writes them)."""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
import yaml
from recorder import SqliteRecorder, record, with_terminal_sigint
from typer.testing import CliRunner

from imucal_cli.api import calibrate
from imucal_cli.cli import app
from imucal_cli.documents import write_document
from imucal_cli.sim import DriveOptions, simulate_drive

runner = CliRunner()
#: The stop: targets of these tests: what an aggressive drive reaches in about a minute and a
#: highway drive does not (its yaw and lever arm need turns).
STOP = {"max_rotation_std_deg": 0.02, "max_translation_std_m": 0.002}


def _config(drive, path):
    document = drive.config_document()
    document["stop"] = STOP
    write_document(path, document)
    return path


@pytest.fixture(scope="module")
def aggressive():
    # the calibrator boots (units, noise, clock offsets) once it has 60 s of data: drives are longer
    return simulate_drive(DriveOptions(scenario="aggressive", duration_s=81.0, seed=31))


@pytest.mark.parametrize("layout", ["mcap", "rosbag2"])
def test_following_a_recording_ends_where_the_batch_calibration_of_the_file_does(
    aggressive, tmp_path, layout
):
    config = _config(aggressive, tmp_path / "c.yaml")  # (stop: the follow lines' targets)
    if layout == "mcap":
        path = target = tmp_path / "live.mcap"
    else:  # a rosbag2 folder being recorded: its mcap storage file, no metadata.yaml yet
        path = tmp_path / "bag"
        path.mkdir()
        target = path / "bag_0.mcap"
    recorder = record(target, aggressive, factor=10.0)
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(path),
            "-c",
            str(config),
            "--follow",
            "--json",
            "-o",
            str(tmp_path / "f.yaml"),
        ],
    )
    assert result.exit_code == 0, result.output
    recorder.join(60)
    updates = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(updates) >= 2 and updates[-1]["windows"] >= updates[0]["windows"]
    _shows_the_estimate_against_stop(updates)
    followed = yaml.safe_load((tmp_path / "f.yaml").read_text())
    batch = calibrate(target, config).document()
    for name, s in batch["sensors"].items():
        f = followed["sensors"][name]
        assert f["status"] == s["status"]
        d_t = np.abs(np.array(f["T_base_imu"]["translation"]) - s["T_base_imu"]["translation"])
        assert np.all(d_t <= 0.05 * np.array(s["translation_std_m"])), (
            name,
            d_t,
            s["translation_std_m"],
        )
        d_r = np.abs(np.array(f["T_base_imu"]["rpy_deg"]) - s["T_base_imu"]["rpy_deg"])
        assert np.all(d_r <= 0.05 * np.array(s["rotation_std_deg"])), (
            name,
            d_r,
            s["rotation_std_deg"],
        )


def _shows_the_estimate_against_stop(updates):
    """Each JSON line of an estimate shows it (``T_base_lidar``) with its statistical std, no
    larger than the total, and lists as missing exactly the axes whose statistical std is over
    the ``stop:`` targets (what ``--until-converged`` tests)."""
    estimated = [
        u for u in updates if u["windows"] and "T_base_lidar" in next(iter(u["sensors"].values()))
    ]
    assert estimated
    for update in estimated:
        for sensor in update["sensors"].values():
            assert (
                len(sensor["T_base_lidar"]["translation"])
                == len(sensor["T_base_lidar"]["rpy_deg"])
                == 3
            )
            std = sensor["statistical_std"]
            if std is None:
                continue
            assert np.all(
                np.array(std["rotation_deg"]) <= np.array(sensor["rotation_std_deg"]) + 1e-12
            )
            over = sum(v > STOP["max_rotation_std_deg"] for v in std["rotation_deg"])
            said = [m for m in sensor["missing"] if "deg, target" in m]
            assert len(said) == over


def test_following_a_rosbag2_recording_to_sqlite3_ends_where_the_batch_calibration_does(
    aggressive, tmp_path
):
    from imucal_cli.sim.writers import write_imu_log

    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    recorder = SqliteRecorder(tmp_path / "bag", aggressive.topics(), factor=10.0)
    recorder.start()
    recorder.started_writing.wait(30)
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(tmp_path / "bag"),
            "-c",
            str(config),
            "--follow",
            "-o",
            str(tmp_path / "f.yaml"),
        ],
    )
    recorder.join(60)
    assert result.exit_code == 0, result.output
    followed = yaml.safe_load((tmp_path / "f.yaml").read_text())
    batch = calibrate(
        write_imu_log(tmp_path / "done", "rosbag2-sqlite3", aggressive.topics()), config
    ).document()
    for name, s in batch["sensors"].items():
        d_t = np.abs(
            np.array(followed["sensors"][name]["T_base_imu"]["translation"])
            - s["T_base_imu"]["translation"]
        )
        assert followed["sensors"][name]["status"] == s["status"] and np.all(
            d_t <= 0.05 * np.array(s["translation_std_m"])
        ), (name, d_t)


def test_until_converged_exits_0_before_the_writer_is_done_on_an_aggressive_drive(
    aggressive, tmp_path
):
    config = _config(aggressive, tmp_path / "c.yaml")
    recorder = record(tmp_path / "live.mcap", aggressive, factor=4.0)
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(tmp_path / "live.mcap"),
            "-c",
            str(config),
            "--follow",
            "--until-converged",
            "--timeout",
            "60",
            "-o",
            str(tmp_path / "f.yaml"),
        ],
    )
    still_writing = not recorder.finished.is_set()
    recorder.join(60)
    assert result.exit_code == 0, result.output
    assert still_writing
    document = yaml.safe_load((tmp_path / "f.yaml").read_text())
    assert document["converged"] is True
    # (on stderr, not a terminal: a line per sensor and update, the estimate and the
    # statistical std shown, not only the status)
    said = [line for line in result.stderr.splitlines() if " windows: " in line]
    assert said and all(" xyz [" in line and "statistical std [" in line for line in said)
    last = [line for line in said if said[-1].split(" windows: ")[0] in line]
    assert len(last) == len(document["sensors"])
    for s in document["sensors"].values():
        assert s["status"] == "ok" and not s["missing"]
        assert (
            max(s["rotation_std_deg"]) <= STOP["max_rotation_std_deg"]
            and max(s["translation_std_m"]) <= STOP["max_translation_std_m"]
        )


def test_a_highway_drive_times_out_with_exit_1_and_names_what_is_missing(tmp_path):
    drive = simulate_drive(DriveOptions(scenario="highway", duration_s=120.0, seed=32))
    config = _config(drive, tmp_path / "c.yaml")
    recorder = record(tmp_path / "live.mcap", drive, factor=10.0)
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(tmp_path / "live.mcap"),
            "-c",
            str(config),
            "--follow",
            "--until-converged",
            "--timeout",
            "9",
            "-o",
            str(tmp_path / "f.yaml"),
        ],
    )
    recorder.join(60)
    assert result.exit_code == 1, result.output
    assert "not converged before --timeout" in result.stderr and "missing" in result.stderr
    document = yaml.safe_load((tmp_path / "f.yaml").read_text())
    assert document["converged"] is False and any(
        s["missing"] for s in document["sensors"].values()
    )
    assert any(
        "turns in both directions" in line
        for s in document["sensors"].values()
        for line in s["missing"]
    )


def test_a_writer_that_dies_mid_record_ends_at_the_timeout_with_what_was_read(aggressive, tmp_path):
    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    recorder = record(tmp_path / "dead.mcap", aggressive, factor=20.0, die_after_s=70.0)
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(tmp_path / "dead.mcap"),
            "-c",
            str(config),
            "--follow",
            "--timeout",
            "6",
            "-o",
            str(tmp_path / "f.yaml"),
        ],
    )
    recorder.join(60)
    assert result.exit_code == 0, result.output
    assert "Traceback" not in result.output
    document = yaml.safe_load((tmp_path / "f.yaml").read_text())
    assert all(s["segments"]["total"] >= 1 for s in document["sensors"].values())


def test_the_live_table_shows_status_std_windows_and_what_is_missing():
    from dataclasses import replace
    from pathlib import Path

    from conftest import SAMPLE_DATA
    from rich.console import Console

    from imucal_cli import tables

    run = calibrate(SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml")
    stop = run.config.stop.__class__(
        max_rotation_std_deg=0.001, max_translation_std_m=0.0001
    )  # out of reach
    run = replace(run, config=replace(run.config, stop=stop))
    for width in (200, 80):  # (a table where it fits, each sensor stacked where it does not)
        console = Console(width=width, record=True)
        console.print(tables.follow(Path("live.mcap"), run.follow_line(7), run.config.stop, width))
        text = console.export_text()
        assert "following live.mcap: 7 windows" in text and "…" not in text
        for name, estimate in run.estimates.items():
            T = run.T_base_lidar(name)
            assert name in text and tables.fmt(T.translation, 4) in text
            assert tables.fmt(estimate.statistical_rotation_std_deg, 4) in text
            assert f"{sum(w.selected for w in estimate.windows)}/{len(estimate.windows)}" in text
        assert "roll pitch yaw tx ty tz" in text and "std rpy deg (stop 0.001)" in text


@pytest.mark.parametrize(
    ("sent", "code", "said"), [("SIGINT", 130, b"interrupted"), ("SIGTERM", 143, b"terminated")]
)
def test_ctrl_c_while_following_writes_the_last_estimate_and_exits_130(
    aggressive, tmp_path, sent, code, said
):
    """A Ctrl-C, or a SIGTERM (which wrote no estimate: 19 windows lost), ends follow mode
    with the last estimate written."""
    import os
    import signal
    import subprocess
    import sys

    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    recorder = record(tmp_path / "live.mcap", aggressive, factor=8.0)
    out = tmp_path / "f.yaml"
    argv = [
        sys.executable,
        "-m",
        "imucal_cli.cli",
        "calibrate",
        str(tmp_path / "live.mcap"),
        "-c",
        str(config),
        "--follow",
        "--json",
        "-o",
        str(out),
    ]
    process = subprocess.Popen(
        with_terminal_sigint(argv),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    first = process.stdout.readline()  # what it has and waits for, then the first estimate
    while first and '"waiting"' in first.decode():
        first = process.stdout.readline()
    assert first, process.stderr.read()
    os.killpg(process.pid, getattr(signal, sent))
    _, stderr = process.communicate(timeout=60)
    recorder.join(60)
    assert process.returncode == code, stderr
    assert b"Traceback" not in stderr and said in stderr
    assert yaml.safe_load(out.read_text())["sensors"]


def _kinds(warnings):
    """A warning's sentence up to its first figure (the figures are compared apart)."""
    return [w.split(next((c for c in w if c.isdigit()), "\0"))[0] for w in warnings]


def test_one_document_from_the_api_the_cli_batch_and_follow_on_a_finished_log(tmp_path):
    """One process layout, one pipeline: the calibrate document of the sample drive is the
    same, to the bit, from ``imucal_cli.calibrate``, ``imucal calibrate -o``, ``imucal batch``
    and ``calibrate --follow`` of the finished file (which adds only each sensor's ``missing``
    axes and ``converged``)."""
    from conftest import SAMPLE_DATA

    from imucal_cli.api import follow, load_config
    from imucal_cli.cli import app
    from imucal_cli.documents import load_document, to_plain

    log = (SAMPLE_DATA / "aggressive.mcap").resolve()  # (as batch names it)
    path = SAMPLE_DATA / "aggressive.config.yaml"
    config = load_config(path, log)  # (what it leaves out: the log's /tf_static)
    api = to_plain(calibrate(log, path).document())
    followed, interrupted = follow(log, config)
    assert not interrupted
    from_follow = to_plain(followed.document())
    assert from_follow.pop("converged") is followed.converged
    for sensor in from_follow["sensors"].values():
        assert isinstance(sensor.pop("missing"), list)
    runner = CliRunner()
    result = runner.invoke(
        app, ["calibrate", str(log), "-c", str(path), "-o", str(tmp_path / "c.yaml")]
    )
    assert result.exit_code == 0, result.output
    result = runner.invoke(
        app, ["batch", str(log), "-c", str(path), "--out-dir", str(tmp_path / "b")]
    )
    assert result.exit_code == 0, result.output
    result = runner.invoke(
        app,
        ["calibrate", str(log), "-c", str(path), "--follow", "-o", str(tmp_path / "f.yaml")],
    )
    assert result.exit_code == 0, result.output
    cli_follow = load_document(tmp_path / "f.yaml")
    del cli_follow["converged"]
    for sensor in cli_follow["sensors"].values():
        del sensor["missing"]
    documents = {
        "cli": load_document(tmp_path / "c.yaml"),
        "batch": load_document(tmp_path / "b" / "aggressive.yaml"),
        "follow": from_follow,
        "cli --follow": cli_follow,
    }
    for name, document in documents.items():
        assert document == api, name


@pytest.mark.parametrize("follow", [False, True])
def test_a_sensor_on_another_clock_stops_calibrate_and_follow_alike(tmp_path, aggressive, follow):
    """The clock comparison runs in the one read loop: ``--follow`` refuses a sensor stamped
    from power-on as ``calibrate`` does."""
    from imucal_cli.sim.writers import TopicData, write_imu_log
    from imucal_cli.types import ImuStream

    topics = aggressive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    boot = data.stream.t_ns - data.stream.t_ns[0] + 12_345_000_000
    stream = ImuStream(boot, data.stream.gyro, data.stream.accel, data.stream.frame_id)
    topics[name] = TopicData(stream, data.log_time_ns)
    log = write_imu_log(tmp_path / "p.mcap", "mcap", topics)
    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    argv = ["calibrate", str(log), "-c", str(config), "-o", str(tmp_path / "e.yaml")]
    result = runner.invoke(app, argv + (["--follow", "--timeout", "5"] if follow else []))
    assert result.exit_code == 2, result.output
    assert name in result.stderr and "max_time_offset_s" in result.stderr
    assert not (tmp_path / "e.yaml").exists()


def test_follow_talks_from_the_first_data_and_stops_when_the_recording_ends(aggressive, tmp_path):
    """Started before the recorder creates the log, follow mode waits for it; a JSON line
    within 2 s of the first message says per sensor what it has and waits for (before any
    window completes); when the recording ends it says so and exits within 2 s."""
    import subprocess
    import sys
    import time

    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    live = tmp_path / "live.mcap"
    argv = [sys.executable, "-m", "imucal_cli.cli", "calibrate", str(live), "-c", str(config)]
    process = subprocess.Popen(
        [*argv, "--follow", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    waiting = process.stderr.readline()  # imucal is up before the recorder starts
    assert b"waiting for" in waiting and b"to be created" in waiting, waiting
    recorder = record(live, aggressive, factor=2.0)
    recorder.started_writing.wait(30)
    started = time.monotonic()
    first = json.loads(process.stdout.readline())
    assert time.monotonic() - started < 2.0 + 1.0  # (a message is flushed with its chunk)
    assert first["windows"] == 0
    assert first["base_samples"] + sum(s["samples"] for s in first["sensors"].values()) > 0
    for sensor in first["sensors"].values():
        assert sensor["status"] == "waiting" and "data: starting" in sensor["waiting_for"]
    recorder.finished.wait(120)
    ended = time.monotonic()
    _, stderr = process.communicate(timeout=60)
    assert time.monotonic() - ended < 2.0 + 1.0, stderr
    assert process.returncode == 0, stderr
    assert b"the recording" in stderr and b"ended" in stderr


def test_a_weak_drive_says_what_is_missing_while_it_records(tmp_path):
    """A highway drive (little turning) followed as it is recorded: before the recording ends,
    the JSON lines name the missing axes and the driving that supplies them."""
    import subprocess
    import sys

    drive = simulate_drive(DriveOptions(scenario="highway", duration_s=120.0, seed=32))
    config = _config(drive, tmp_path / "c.yaml")
    live = tmp_path / "live.mcap"
    recorder = record(live, drive, factor=4.0)
    argv = [sys.executable, "-m", "imucal_cli.cli", "calibrate", str(live), "-c", str(config)]
    process = subprocess.Popen(
        [*argv, "--follow", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    line = json.loads(process.stdout.readline())
    assert not recorder.finished.is_set()  # still recording
    for sensor in line["sensors"].values():
        assert sensor["missing"] and any("turns" in m for m in sensor["missing"])
    process.communicate(timeout=120)
    recorder.join(60)


def test_garbage_appended_to_a_recording_is_said_damaged_not_waited_for(aggressive, tmp_path):
    """Garbage appended to a followed MCAP was taken for a record cut off, waited for (500 MB
    re-read on every poll: 2 GB) until --timeout, and nothing said the file was damaged. A
    record of a reserved opcode is damage, said on stderr; the estimate is of what came
    before."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.sim.writers import write_imu_log

    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    log = write_imu_log(tmp_path / "d.mcap", "mcap", aggressive.topics())
    data = log.read_bytes()
    footer = data.rindex(b"\x02" + (20).to_bytes(8, "little"))  # the footer record
    summary = int.from_bytes(data[footer + 9 : footer + 17], "little") or footer
    end = data.rindex(b"\x0f", 0, summary)  # the data-end record, then the summary
    garbage = bytes([0x42]) + (10**12).to_bytes(8, "little") + b"\x00" * 4096
    log.write_bytes(data[:end] + garbage)  # (what a recorder left, garbage after its chunks)
    argv = ["calibrate", str(log), "-c", str(config), "--follow", "--timeout", "30"]
    started = time.monotonic()
    result = CliRunner().invoke(app, [*argv, "-o", str(tmp_path / "f.yaml")])
    assert time.monotonic() - started < 25  # (not the whole --timeout)
    assert "damaged" in result.stderr and "reserved opcode 0x42" in result.stderr, result.stderr


def test_a_recording_that_stalls_is_said_with_how_long_it_has_waited(
    aggressive, tmp_path, monkeypatch
):
    """A recording that stalls (a recorder that hangs: no footer, no new record) was waited
    for in silence after its last window, forever without --timeout. The wait is said, with
    how long it has lasted."""
    from typer.testing import CliRunner

    from imucal_cli.cli import app
    from imucal_cli.cli import follow as following
    from imucal_cli.sim.writers import write_imu_log

    monkeypatch.setattr(following, "FOLLOW_STALL_S", 1.0)
    config = tmp_path / "c.yaml"
    write_document(config, aggressive.config_document())
    log = write_imu_log(tmp_path / "d.mcap", "mcap", aggressive.topics())
    data = log.read_bytes()
    footer = data.rindex(b"\x02" + (20).to_bytes(8, "little"))
    end = data.rindex(b"\x0f", 0, int.from_bytes(data[footer + 9 : footer + 17], "little"))
    log.write_bytes(data[:end])  # the recorder hung: no data end, no summary, no footer
    argv = ["calibrate", str(log), "-c", str(config), "--follow", "--timeout", "4"]
    result = CliRunner().invoke(app, argv)
    assert re.search(r"nothing new for \d+ s; still waiting", result.stderr), result.stderr


def test_follow_waits_for_data_while_it_starts_and_asks_for_motion_only_when_it_lacks(tmp_path):
    """Before the start (its first 60 s of data) follow said it waited for "motion that places
    the clock offsets" on a slalom from the first second, and a driver would start weaving for
    nothing: it says how much of the start it has read; only once an attempt found too little
    motion does it ask for turns and changes of speed."""
    from imucal_cli.config import parse_config
    from imucal_cli.pipeline import feed, make_calibrator, waiting

    said = {}
    for scenario in ("aggressive", "stationary"):
        drive = simulate_drive(DriveOptions(scenario=scenario, duration_s=90.0, seed=3))
        config = parse_config(drive.config_document(), "c.yaml")
        streams = drive.streams()
        for until_s in (20.0, 90.0):
            calibrator = make_calibrator(config)
            feed(calibrator, _until(streams, until_s))
            said[scenario, until_s] = {
                s["waiting_for"] for s in waiting(calibrator, config, {})["sensors"].values()
            }
    (early,) = said["aggressive", 20.0]
    assert early.startswith("data: starting, ") and early.endswith(" s read")
    read, needs = (float(x) for x in early.split("starting, ")[1].split(" s read")[0].split(" of "))
    assert 15 <= read <= 21 and needs == pytest.approx(62, abs=1)
    assert said["stationary", 20.0] == said["aggressive", 20.0]
    (late,) = said["stationary", 90.0]
    assert late.startswith("motion that places the clock offsets: turns and changes of speed")
    assert all("motion" not in what for what in said["aggressive", 90.0])


def _until(streams, until_s):
    """``streams`` from their start up to ``until_s``."""
    from dataclasses import replace

    def cut(stream):
        keep = stream.t_ns < stream.t_ns[0] + int(until_s * 1e9)
        return replace(
            stream, t_ns=stream.t_ns[keep], gyro=stream.gyro[keep], accel=stream.accel[keep]
        )

    return replace(
        streams, base=cut(streams.base), sensors={k: cut(v) for k, v in streams.sensors.items()}
    )
