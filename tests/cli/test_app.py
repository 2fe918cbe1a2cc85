"""The command line through Typer's CliRunner: outputs, formats, exit codes, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml
from conftest import SAMPLE_DATA, log_name, without_summary
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.config import load_config
from imucal_cli.io.formats import FORMATS
from imucal_cli.reading import read_imu

runner = CliRunner()


def assert_bad_input(result, *needles):
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_simulate_then_inspect_every_format(tmp_path, fmt):
    out = tmp_path / log_name(fmt)
    result = runner.invoke(
        app,
        [
            "simulate",
            str(out),
            "--scenario",
            "parking",
            "--duration",
            "12",
            "--seed",
            "4",
            "--format",
            fmt,
            "--sensors",
            "3",
        ],
    )
    assert result.exit_code == 0, result.output
    truth = yaml.safe_load((tmp_path / "drive.truth.yaml").read_text())
    config = load_config(tmp_path / "drive.config.yaml")
    assert len(config.sensors) == 3 and set(truth["sensors"]) == {s.name for s in config.sensors}

    result = runner.invoke(app, ["inspect", str(out), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    topics = report["topics"]
    assert set(topics) == {config.base.topic} | {s.imu_topic for s in config.sensors}
    reads = read_imu(out, list(topics))
    for topic, info in topics.items():
        assert info["count"] == len(reads[topic].stream)
        assert info["rate_hz"] == pytest.approx(100.0, rel=1e-3)
        assert info["duration_s"] == pytest.approx(12.0, abs=0.02)
        assert info["backwards"] == 0 and info["duplicates"] == 0
    assert report["t0_ns"] == min(int(r.stream.t_ns[0]) for r in reads.values())


def test_inspect_writes_yaml_and_json(tmp_path, short_drive):
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    for name in ("report.yaml", "report.json"):
        result = runner.invoke(app, ["inspect", str(log), "-o", str(tmp_path / name)])
        assert result.exit_code == 0, result.output
    from_yaml = yaml.safe_load((tmp_path / "report.yaml").read_text())
    from_json = json.loads((tmp_path / "report.json").read_text())
    assert from_yaml == from_json
    assert from_yaml["topics"]["/gnss/imu"]["count"] == len(short_drive.base.stream)
    result = runner.invoke(app, ["inspect", str(log)])
    assert result.exit_code == 0 and "/gnss/imu" in result.stdout


def test_inspect_lists_as_losses_only_what_was_lost(tmp_path, short_drive):
    """A summary-less MCAP (a recorder that was stopped hard) is read whole: a note on stderr,
    no loss. A cut-off one lists the lost part as calibrate's document does, from its byte."""
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    no_summary = without_summary(log, tmp_path / "nosummary.mcap")
    result = runner.invoke(app, ["inspect", str(no_summary), "--json"])
    assert result.exit_code == 0, result.output
    assert "losses" not in json.loads(result.stdout)
    assert "note" in result.stderr and "record by record" in result.stderr
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: len(no_summary.read_bytes()) // 2])  # in the data
    result = runner.invoke(app, ["inspect", str(cut), "--json"])
    assert result.exit_code == 0, result.output
    (loss,) = json.loads(result.stdout)["losses"]
    # (cut inside a chunk: what decodes of it is read, and the loss is named from the byte
    # where reading stopped, the file's end: not "from" the chunk's first byte)
    assert loss["reason"].startswith(f"not read from byte {cut.stat().st_size} ")
    assert loss["offset"] == cut.stat().st_size and loss["bytes"] > 0
    assert "the chunk from byte" in loss["reason"] and "is cut off after" in loss["reason"]
    counts = json.loads(result.stdout)["topics"]
    assert 0 < counts["/gnss/imu"]["count"] < len(short_drive.base.stream)
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(short_drive.config_document()))
    result = runner.invoke(app, ["biases", str(cut), "-c", str(config), "--json"])
    assert result.exit_code == 0, result.output
    biases = json.loads(result.stdout)
    assert biases["losses"] == [loss] and biases["lost_s"] is None  # (where the cut ends: unknown)
    assert biases["dropped"] == {}  # a cut drops no sample of what it reads


def test_inspect_bad_inputs(tmp_path, short_drive):
    assert_bad_input(
        runner.invoke(app, ["inspect", str(tmp_path / "missing.mcap")]),
        "missing.mcap",
        "no such file",
    )
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 64)
    assert_bad_input(runner.invoke(app, ["inspect", str(junk)]), "junk.mcap")
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    result = runner.invoke(app, ["inspect", str(log), "-o", str(tmp_path / "nope" / "r.yaml")])
    assert_bad_input(result, "does not exist")
    result = runner.invoke(app, ["inspect", str(log), "-o", str(tmp_path / "r.txt")])
    assert_bad_input(result, "r.txt")
    assert not (tmp_path / "r.txt").exists()


@pytest.mark.parametrize(
    ("name", "args", "needle"),
    [
        ("x.bag", ["--format", "mcap"], ".mcap"),
        ("x.mcap", ["--format", "rosbag2-sqlite3"], "rosbag2 directory"),
        ("nodir/x.mcap", [], "does not exist"),
    ],
)
def test_simulate_bad_output(tmp_path, name, args, needle):
    result = runner.invoke(app, ["simulate", str(tmp_path / name), "--duration", "5", *args])
    assert_bad_input(result, needle)
    assert list(tmp_path.iterdir()) == []


def test_simulate_usage_errors_exit_2(tmp_path):
    result = runner.invoke(app, ["simulate", str(tmp_path / "x.mcap"), "--scenario", "moon"])
    assert result.exit_code == 2
    result = runner.invoke(app, ["simulate", str(tmp_path / "x.mcap"), "--sensors", "9"])
    assert result.exit_code == 2


def test_simulate_noise_free_and_offsets(tmp_path):
    out = tmp_path / "ideal.mcap"
    result = runner.invoke(
        app,
        [
            "simulate",
            str(out),
            "--scenario",
            "aggressive",
            "--duration",
            "6",
            "--noise-scale",
            "0",
            "--time-offset-s",
            "0.03",
            "--time-offset-s",
            "-0.02",
        ],
    )
    assert result.exit_code == 0, result.output
    truth = yaml.safe_load((tmp_path / "ideal.truth.yaml").read_text())
    offsets = [truth["sensors"][n]["time_offset_s"] for n in ("front_left_top", "front_right_top")]
    assert offsets == [0.03, -0.02]
    assert truth["noise_scale"] == 0.0
    assert np.all(np.array(truth["sensors"]["front_left_top"]["gyro_bias_radps"]["mean"]) == 0.0)


def test_version_and_help():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and "imucal" in result.stdout
    for command in ("inspect", "simulate", "check-config"):
        assert runner.invoke(app, [command, "--help"]).exit_code == 0


@pytest.mark.parametrize(
    ("command", "extra"), [("calibrate", "imucal[report]"), ("batch", "imucal[fleet]")]
)
def test_help_names_the_extras_to_install(command, extra):
    """Square brackets in help text are rich markup unless escaped: the extra's name shows."""
    result = runner.invoke(app, [command, "--help"], env={"COLUMNS": "240"})
    assert result.exit_code == 0
    assert f"needs {extra}" in result.output


def test_the_console_entry_point_ends_with_the_command_s_code_and_its_outputs_whole(
    tmp_path, short_drive
):
    """The console script's entry point (``imucal_cli.cli:main``): the output file is whole,
    what was printed reaches a pipe, and the exit code is the command's (0, 2 on bad input)."""

    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import write_imu_log

    log = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    write_document(tmp_path / "c.yaml", short_drive.config_document())
    command = [
        sys.executable,
        "-m",
        "imucal_cli.cli",
        "calibrate",
        str(log),
        "-c",
        str(tmp_path / "c.yaml"),
    ]
    written = subprocess.run(
        [*command, "-o", str(tmp_path / "e.json")], capture_output=True, timeout=300
    )
    assert written.returncode == 0, written.stderr
    printed = subprocess.run([*command, "--json"], capture_output=True, timeout=300)
    assert printed.returncode == 0, printed.stderr
    assert json.loads(printed.stdout) == json.loads((tmp_path / "e.json").read_text())
    bad = subprocess.run(
        [*command[:-1], str(tmp_path / "missing.yaml")], capture_output=True, timeout=300
    )
    assert bad.returncode == 2 and b"missing.yaml" in bad.stderr and b"Traceback" not in bad.stderr


def test_help_has_its_short_flag_and_shell_completion_and_flows_as_prose(monkeypatch):
    """``-h`` is ``--help`` on every page; ``--show-completion`` prints a script for the shell
    asked for; the commands' help is prose, not the docstrings' line breaks (``init``'s
    "the transforms in its / /tf_static" broke mid-sentence)."""
    top = runner.invoke(app, ["-h"], env={"COLUMNS": "200"})
    assert (
        top.exit_code == 0
        and top.stdout == runner.invoke(app, ["--help"], env={"COLUMNS": "200"}).stdout
    )
    assert "--install-completion" in top.stdout
    assert "the transforms in its /tf_static, a commented placeholder" in top.stdout
    assert "rotation std, selected or not." in top.stdout
    calibrate = runner.invoke(app, ["calibrate", "-h"], env={"COLUMNS": "200"})
    assert calibrate.exit_code == 0 and "--follow" in calibrate.stdout
    # (the shell named, as Typer's own tests do: a test has no shell to detect)
    monkeypatch.setenv("_TYPER_COMPLETE_TEST_DISABLE_SHELL_DETECTION", "1")
    script = runner.invoke(app, ["--show-completion", "bash"], prog_name="imucal")
    assert script.exit_code == 0 and "complete " in script.stdout and "COMP_WORDS" in script.stdout


def test_plain_flags_show_no_metavar_in_help():
    for command in ("calibrate", "inspect", "evaluate"):
        result = runner.invoke(app, [command, "--help"], env={"COLUMNS": "200"})
        flags = [
            line
            for line in result.stdout.splitlines()
            if "--json" in line or "--require-observable" in line or "--allow-missing" in line
        ]
        assert flags and all("<bool>" not in line for line in flags), (command, flags)


def test_no_help_page_shows_a_bool_metavar():
    """Typer's own ``--help`` showed ``<bool>`` on every page (the flags of this program did
    not): no page shows one, the program's and each command's."""
    commands = [
        [],
        *(
            [c]
            for c in app.registered_commands
            and [
                (cmd.name or cmd.callback.__name__.replace("_", "-"))
                for cmd in app.registered_commands
            ]
        ),
    ]
    assert len(commands) > 5
    for command in commands:
        result = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "200"})
        assert result.exit_code == 0, (command, result.output)
        assert "--help" in result.stdout and "<bool>" not in result.stdout, command


def test_a_ctrl_c_that_passed_through_a_library_s_exec_still_exits_130(tmp_path):
    """A KeyboardInterrupt raised inside an ``exec`` of a string (as a library that makes its
    functions while it is imported) marks CPython's interpreter, which then killed a program run
    with ``-m`` (as ``imucal`` is) with SIGINT at exit (-2) although the CLI had handled it: the
    exit a Ctrl-C landing in the first second of a run got about one time in six. Handled as
    the CLI handles it, the exit is 130."""
    import subprocess
    import sys

    (tmp_path / "interrupted_main.py").write_text(
        "import sys\n"
        "from imucal_cli.cli.app import interrupted\n"
        "try:\n"
        "    exec('raise KeyboardInterrupt')\n"
        "except KeyboardInterrupt as exc:\n"
        "    sys.exit(interrupted(exc).exit_code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-m", "interrupted_main"], cwd=tmp_path, capture_output=True, timeout=60
    )
    assert done.returncode == 130, done.stderr
    assert done.stderr.strip() == b"imucal: interrupted"


def test_tables_never_cut_a_digit_at_80_columns(monkeypatch):
    """At 80 columns rich cut the result table's numbers short (``[4.348…``, ``-43.99…``,
    ``front_…``): every value the table holds is printed whole, the table stacked where it
    does not fit, and left a table where it does."""
    from rich.console import Console

    from imucal_cli import tables
    from imucal_cli.cli import render

    monkeypatch.setattr(render, "console", lambda: Console(width=80, highlight=False, markup=False))
    log, config = SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    result = runner.invoke(app, ["calibrate", str(log), "-c", str(config)])
    assert result.exit_code == 0, result.output
    doc = json.loads(
        runner.invoke(app, ["calibrate", str(log), "-c", str(config), "--json"]).stdout
    )
    assert "…" not in result.stdout and max(map(len, result.stdout.splitlines())) <= 80
    for name, sensor in doc["sensors"].items():
        assert name in result.stdout
        for values, digits in (
            (sensor["T_base_lidar"]["translation"], 4),
            (sensor["T_base_lidar"]["rpy_deg"], 3),
        ):
            assert tables.fmt(values, digits) in result.stdout
    narrow = tables.fitted("t", ("a", "b"), [("1.5", "2.5")], 80)
    assert type(narrow).__name__ == "Table"  # (a table that fits stays one)


def test_the_progress_bar_says_its_count_or_what_it_waits_for():
    """The bar said ``0/? messages`` until the first batch: the summary's count is shown as
    soon as it is known; before, what is being done."""
    from imucal_cli.cli.render import count_text

    assert count_text(0, None, None, "messages") == "opening the log"
    assert count_text(12345, 67890, 3.4, "messages") == "12,345 of 67,890 messages, 0:00:03 left"
    assert count_text(67890, 67890, 0.0, "messages") == "all 67,890 messages read"
