"""biases, segments, calibrate and evaluate through the CLI, on the sample data."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from conftest import SAMPLE_DATA
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.types import Transform

runner = CliRunner()
LOG = SAMPLE_DATA / "aggressive.mcap"
CONFIG = SAMPLE_DATA / "aggressive.config.yaml"
TRUTH = SAMPLE_DATA / "aggressive.truth.yaml"


@pytest.fixture(scope="module")
def estimate_path(tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "estimate.yaml"
    result = runner.invoke(app, ["calibrate", str(LOG), "-c", str(CONFIG), "-o", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_calibrate_output_follows_the_spec(estimate_path):
    doc = yaml.safe_load(estimate_path.read_text())
    assert set(doc) >= {"imucal_version", "log", "base_frame", "sensors", "pairs"}
    assert doc["base_frame"] == "base_link"
    truth = yaml.safe_load(TRUTH.read_text())
    for name, sensor in doc["sensors"].items():
        assert set(sensor) >= {
            "status",
            "T_base_imu",
            "T_base_lidar",
            "rotation_std_deg",
            "translation_std_m",
            "translation_observable",
            "time_offset_s",
            "gyro_bias_radps",
            "accel_bias_mps2",
            "segments",
            "residual_rms",
        }
        assert sensor["status"] == "ok" and sensor["translation_observable"] == [True, True, True]
        assert set(sensor["T_base_lidar"]) == {"translation", "rotation", "rpy_deg"}
        T_base_imu = Transform.from_dict(sensor["T_base_imu"])
        T_base_lidar = Transform.from_dict(sensor["T_base_lidar"])
        T_imu_lidar = Transform.from_dict(truth["sensors"][name]["T_imu_lidar"])
        np.testing.assert_allclose(
            (T_base_imu * T_imu_lidar).as_matrix(), T_base_lidar.as_matrix(), atol=1e-9
        )
        assert abs(sensor["time_offset_s"] - truth["sensors"][name]["time_offset_s"]) < 1e-3
    ((pair_name, pair),) = doc["pairs"].items()
    a, b = pair_name.split("/")
    T_a = Transform.from_dict(doc["sensors"][a]["T_base_lidar"])
    T_b = Transform.from_dict(doc["sensors"][b]["T_base_lidar"])
    np.testing.assert_allclose(
        (T_a.inverse() * T_b).as_matrix(), Transform.from_dict(pair).as_matrix(), atol=1e-9
    )


def test_evaluate_passes_and_fails_on_thresholds(estimate_path, tmp_path):
    result = runner.invoke(app, ["evaluate", str(estimate_path), str(TRUTH), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["pass"] is True and doc["thresholds"] == {
        "max_rotation_deg": None,
        "max_translation_m": None,
        "max_time_offset_s": None,
    }
    for row in list(doc["sensors"].values()) + list(doc["pairs"].values()):
        assert row["rotation_error_deg"] < 0.05 and row["translation_error_m"] < 0.02
        assert row["translation_error_eq20_m"] == pytest.approx(row["translation_error_m"] / 3)
    worst = max(r["rotation_error_deg"] for r in doc["sensors"].values())
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate_path),
            str(TRUTH),
            "--max-rotation-deg",
            str(worst / 2),
            "-o",
            str(tmp_path / "ev.json"),
        ],
    )
    assert result.exit_code == 1
    assert json.loads((tmp_path / "ev.json").read_text())["pass"] is False
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate_path),
            str(TRUTH),
            "--max-rotation-deg",
            "0.1",
            "--max-translation-m",
            "0.02",
        ],
    )
    assert result.exit_code == 0


def test_evaluate_compares_clock_offsets_where_the_truth_has_them(estimate_path, tmp_path):
    """Truth files carry ``time_offset_s``: ``time_offset_error_s`` is the estimate's less the
    truth's (null where the truth has none), and ``--max-time-offset-s`` fails a sensor whose
    error is larger, in the document, the table and JUnit."""
    estimate, truth = yaml.safe_load(estimate_path.read_text()), yaml.safe_load(TRUTH.read_text())
    result = runner.invoke(app, ["evaluate", str(estimate_path), str(TRUTH), "--json"])
    doc = json.loads(result.stdout)
    for name, row in doc["sensors"].items():
        expected = (
            estimate["sensors"][name]["time_offset_s"] - truth["sensors"][name]["time_offset_s"]
        )
        assert row["time_offset_error_s"] == pytest.approx(expected, rel=1e-12, abs=0)
    assert all("time_offset_error_s" not in row for row in doc["pairs"].values())
    worst = max(abs(row["time_offset_error_s"]) for row in doc["sensors"].values())
    junit = tmp_path / "e.xml"
    args = ["evaluate", str(estimate_path), str(TRUTH), "--junit", str(junit)]
    result = runner.invoke(app, [*args, "--max-time-offset-s", str(worst / 2)])
    assert result.exit_code == 1 and "time offset s >" in result.stdout
    assert "time_offset_error_s" in junit.read_text() and "max_time_offset_s" in junit.read_text()
    assert runner.invoke(app, [*args, "--max-time-offset-s", str(2 * worst)]).exit_code == 0
    for sensor in truth["sensors"].values():
        del sensor["time_offset_s"]
    (tmp_path / "truth.yaml").write_text(yaml.safe_dump(truth))
    no_offsets = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate_path),
            str(tmp_path / "truth.yaml"),
            "--json",
            "--max-time-offset-s",
            "0",
        ],
    )
    assert no_offsets.exit_code == 0, no_offsets.output
    rows = json.loads(no_offsets.stdout)["sensors"].values()
    assert all(row["time_offset_error_s"] is None for row in rows)


def test_evaluate_against_itself_is_zero(estimate_path):
    result = runner.invoke(app, ["evaluate", str(estimate_path), str(estimate_path), "--json"])
    doc = json.loads(result.stdout)
    assert all(
        r["rotation_error_deg"] == 0.0 and r["translation_error_m"] == 0.0
        for r in doc["sensors"].values()
    )


def test_evaluate_bad_inputs(tmp_path, estimate_path):
    other = tmp_path / "other.yaml"
    other.write_text(
        "sensors: {nobody: {T_base_lidar: {translation: [0, 0, 0], rotation: [0, 0, 0, 1]}}}\n"
    )
    result = runner.invoke(app, ["evaluate", str(estimate_path), str(other)])
    assert result.exit_code == 2 and "no sensor in common" in result.stderr
    broken = tmp_path / "broken.yaml"
    broken.write_text(
        "sensors: {a: {T_base_lidar: {translation: [0, 0], rotation: [0, 0, 0, 1]}}}\n"
    )
    result = runner.invoke(app, ["evaluate", str(broken), str(TRUTH)])
    assert result.exit_code == 2 and "sensors.a.T_base_lidar.translation" in result.stderr


def test_calibrate_require_observable(tmp_path):
    out = tmp_path / "still.mcap"
    assert (
        runner.invoke(
            app, ["simulate", str(out), "--scenario", "stationary", "--duration", "30"]
        ).exit_code
        == 0
    )
    config = tmp_path / "still.config.yaml"
    result = runner.invoke(app, ["calibrate", str(out), "-c", str(config), "--json"])
    assert result.exit_code == 0
    doc = json.loads(result.stdout)
    assert {s["status"] for s in doc["sensors"].values()} == {"unobservable"}
    prior = yaml.safe_load(config.read_text())["sensors"]
    for name, sensor in doc["sensors"].items():
        np.testing.assert_allclose(
            sensor["T_base_imu"]["translation"], prior[name]["prior_T_base_imu"]["translation"]
        )
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(out),
            "-c",
            str(config),
            "--require-observable",
            "-o",
            str(tmp_path / "r.json"),
        ],
    )
    assert result.exit_code == 1 and "not every sensor is ok" in result.stderr
    for name in doc["sensors"]:  # (each named with its status: not all are unobservable)
        assert f"{name} unobservable" in result.stderr
    assert (tmp_path / "r.json").exists()  # the result is written; the check fails


def test_calibrate_missing_topic_and_bad_config(tmp_path):
    text = CONFIG.read_text().replace("/gnss/imu", "/ins/imu")
    config = tmp_path / "c.yaml"
    config.write_text(text)
    result = runner.invoke(
        app, ["calibrate", str(LOG), "-c", str(config), "-o", str(tmp_path / "x.yaml")]
    )
    assert result.exit_code == 2
    assert (
        "/ins/imu" in result.stderr
        and "aggressive.mcap" in result.stderr
        and "/gnss/imu" in result.stderr
    )
    assert not (tmp_path / "x.yaml").exists()
    config.write_text(CONFIG.read_text().replace("calibration:", "calibraton:"))
    result = runner.invoke(app, ["calibrate", str(LOG), "-c", str(config)])
    assert result.exit_code == 2 and "calibraton" in result.stderr and str(config) in result.stderr


def test_segments_report(tmp_path):
    result = runner.invoke(app, ["segments", str(LOG), "-c", str(CONFIG), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["window_s"] == 10.0
    for sensor in doc["sensors"].values():
        assert sensor["total"] == 8 and sensor["selected"] == sum(
            w["selected"] for w in sensor["windows"]
        )
        for k, w in enumerate(sensor["windows"]):
            length = w["end_s"] - w["start_s"]
            if k < len(sensor["windows"]) - 1:  # whole windows, then a last one of at least half
                assert length == pytest.approx(10.0, abs=1e-6)
            else:
                assert 5.0 <= length <= 10.0 + 1e-6
            assert w["selected"] == (w["rotation_std_deg"] < doc["max_rotation_std_deg"])
            # CRLB std is 1/sqrt(sigma_min) (eq. 19)
            assert w["rotation_std_deg"] == pytest.approx(
                np.degrees(1 / np.sqrt(w["min_singular_value"]))
            )
    assert runner.invoke(app, ["segments", str(LOG), "-c", str(CONFIG)]).exit_code == 0


def test_segments_table_shows_a_long_log_in_blocks(monkeypatch):
    """The terminal's table of windows is drawn a block at a time (a day's log has thousands):
    every window once, in order, each block under a title that says which windows it holds."""
    from imucal_cli import tables

    monkeypatch.setattr(tables, "TABLE_ROWS", 3)
    result = runner.invoke(app, ["segments", str(LOG), "-c", str(CONFIG)])
    assert result.exit_code == 0, result.output
    doc = json.loads(runner.invoke(app, ["segments", str(LOG), "-c", str(CONFIG), "--json"]).stdout)
    name = next(iter(doc["sensors"]))
    titles = [line.strip() for line in result.stdout.splitlines() if line.strip().startswith(name)]
    assert titles[1:3] == [f"{name}, windows 4-6", f"{name}, windows 7-8"]
    starts = [float(line.split("│")[1]) for line in result.stdout.splitlines() if "│" in line]
    expected = [w["start_s"] for s in doc["sensors"].values() for w in s["windows"]]
    np.testing.assert_allclose(starts, expected, atol=0.05)


def test_biases_report():
    result = runner.invoke(
        app,
        [
            "biases",
            str(SAMPLE_DATA / "urban.mcap"),
            "-c",
            str(SAMPLE_DATA / "urban.config.yaml"),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    truth = yaml.safe_load((SAMPLE_DATA / "urban.truth.yaml").read_text())
    assert list(doc["imus"]) == ["base", "front_left_top", "front_right_top"]
    for name, imu in doc["imus"].items():
        assert len(imu["rest_periods"]) >= 3 and imu["rest_periods"][0][0] == pytest.approx(
            0.0, abs=0.05
        )
        assert set(imu["gyro_bias_radps"]) == {"initial", "final", "track_std", "final_std"}
        if name != "base":
            true_initial = np.array(truth["sensors"][name]["gyro_bias_radps"]["initial"])
            # the first rest's mean: noise 2.6e-3 rad/s per sample over > 500 samples
            assert np.all(np.abs(np.array(imu["gyro_bias_radps"]["initial"]) - true_initial) < 5e-4)


def test_biases_from_the_command_line_is_the_python_apis_document():
    """``imucal biases --json`` prints the document the Python API returns."""
    import imucal_cli

    log, config = SAMPLE_DATA / "urban.mcap", SAMPLE_DATA / "urban.config.yaml"
    result = runner.invoke(app, ["biases", str(log), "-c", str(config), "--json"])
    assert result.exit_code == 0, result.output
    in_process = imucal_cli.biases(log, imucal_cli.load_config(config))
    assert json.loads(result.stdout) == json.loads(json.dumps(in_process))


def test_calibrate_too_short_log_is_a_clear_error(tmp_path):
    out = tmp_path / "short.mcap"
    assert (
        runner.invoke(
            app, ["simulate", str(out), "--scenario", "aggressive", "--duration", "3"]
        ).exit_code
        == 0
    )
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(out),
            "-c",
            str(tmp_path / "short.config.yaml"),
            "-o",
            str(tmp_path / "e.yaml"),
        ],
    )
    assert result.exit_code == 2
    assert (
        "short.mcap" in result.stderr
        and "too little data" in result.stderr
        and "Traceback" not in result.stderr
    )
    assert not (tmp_path / "e.yaml").exists()


def test_names_and_paths_are_printed_as_they_are(tmp_path):
    """Sensor names and paths with square brackets (rich markup, were it read as such) come
    out whole in the tables; the verdict keeps its word."""
    folder = tmp_path / "[night]"
    folder.mkdir()
    doc = (
        "sensors: {'lidar[front]': "
        "{T_base_lidar: {translation: [1, 0, 0], rotation: [0, 0, 0, 1]}}}\n"
    )
    (folder / "a.yaml").write_text(doc)
    (folder / "b.yaml").write_text(doc.replace("[1, 0, 0]", "[1, 0, 0.5]"))
    result = runner.invoke(
        app,
        ["evaluate", str(folder / "a.yaml"), str(folder / "b.yaml"), "--max-translation-m", "0.1"],
        env={"COLUMNS": "240"},
    )
    assert result.exit_code == 1, result.output  # a failed check
    assert "lidar[front]" in result.stdout and "[night]" in result.stdout
    assert (
        result.stdout.rstrip().splitlines()[-1] == "fail: 1 over a threshold (lidar[front])"
    )  # the verdict names the row


def test_evaluate_fails_on_a_sensor_missing_from_the_truth_unless_allowed(estimate_path, tmp_path):
    import xml.etree.ElementTree as ET

    truth = yaml.safe_load(TRUTH.read_text())
    dropped = sorted(truth["sensors"])[0]
    del truth["sensors"][dropped]
    partial = tmp_path / "partial.truth.yaml"
    partial.write_text(yaml.safe_dump(truth))
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate_path),
            str(partial),
            "--json",
            "--junit",
            str(tmp_path / "e.xml"),
        ],
    )
    assert result.exit_code == 1 and f"sensor {dropped} is in {estimate_path} only" in result.stderr
    doc = json.loads(result.stdout)
    assert doc["pass"] is False and doc["missing"] == {"estimate_only": [dropped], "truth_only": []}
    cases = ET.parse(tmp_path / "e.xml").getroot().iter("testcase")
    missing = [c for c in cases if c.get("classname") == "missing"]
    assert len(missing) == 1 and dropped in missing[0].find("failure").get("message")
    result = runner.invoke(app, ["evaluate", str(estimate_path), str(partial), "--allow-missing"])
    assert result.exit_code == 0


def test_evaluate_junit_names_the_threshold_and_the_value_and_passing_cases_carry_theirs(
    estimate_path, tmp_path
):
    import xml.etree.ElementTree as ET

    doc = json.loads(
        runner.invoke(app, ["evaluate", str(estimate_path), str(TRUTH), "--json"]).stdout
    )
    worst_name, worst = max(doc["sensors"].items(), key=lambda item: item[1]["rotation_error_deg"])
    limit = worst["rotation_error_deg"] * 0.999
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate_path),
            str(TRUTH),
            "--max-rotation-deg",
            repr(limit),
            "--junit",
            str(tmp_path / "e.xml"),
        ],
    )
    assert result.exit_code == 1
    suite = ET.parse(tmp_path / "e.xml").getroot().find("testsuite")
    cases = {(c.get("classname"), c.get("name")): c for c in suite.iter("testcase")}
    failed = cases[("sensors", worst_name)].find("failure").get("message")
    assert (
        f"rotation_error_deg {worst['rotation_error_deg']:.6g}" in failed
        and "max_rotation_deg" in failed
    )
    passing = [c for c in cases.values() if c.find("failure") is None]
    assert passing and all("rotation_error_deg" in c.find("system-out").text for c in passing)
    assert int(suite.get("failures")) == sum(c.find("failure") is not None for c in cases.values())


def test_calibrate_with_an_output_says_each_status_and_warning_on_stderr(tmp_path):
    """With -o (or --json) the summary is not printed: a sensor that is not ok must still show
    in a terminal or a job's log, its status and each warning one line on stderr; --quiet
    silences them."""
    document = yaml.safe_load(CONFIG.read_text())
    for sensor in document["sensors"].values():  # a prior 0.5 m off: the box binds
        sensor["prior_T_base_imu"]["translation"][0] += 0.5
    config = tmp_path / "off.yaml"
    config.write_text(yaml.safe_dump(document))
    out = tmp_path / "out.yaml"
    result = runner.invoke(app, ["calibrate", str(LOG), "-c", str(config), "-o", str(out)])
    assert result.exit_code == 0, result.output
    written = yaml.safe_load(out.read_text())
    lines = result.stderr.splitlines()
    for name, sensor in written["sensors"].items():
        assert sensor["status"] != "ok" and sensor["warnings"]
        assert any(line.startswith(f"imucal: {name}: {sensor['status']}, std ") for line in lines)
        for warning in sensor["warnings"]:
            assert f"imucal: {name}: {warning}" in lines
    quiet = runner.invoke(app, ["calibrate", str(LOG), "-c", str(config), "-o", str(out), "-q"])
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_an_ok_drive_with_the_default_grades_has_no_warnings_and_says_its_notes_apart(tmp_path):
    """Consumer lidar IMUs under a tactical INS (the default grades): the IMUs' own errors the
    fit estimated are information (``notes``), not a warning; an ok drive has no warning in
    the document, on stderr or in batch's summary."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    drive = simulate_drive(
        DriveOptions(
            scenario="urban",
            duration_s=120.0,
            seed=2,
            lidar_grade="consumer",
            base_grade="tactical",
        )
    )
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    write_document(tmp_path / "c.yaml", drive.config_document())
    out = tmp_path / "e.json"
    run = runner.invoke(
        app, ["calibrate", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(out)]
    )
    assert run.exit_code == 0, run.output
    for name, sensor in json.loads(out.read_text())["sensors"].items():
        assert sensor["status"] == "ok" and sensor["warnings"] == [], name
        assert any("axis errors estimated with the extrinsics" in n for n in sensor["notes"])
    assert "estimated with the extrinsics" not in run.stderr
    batch = runner.invoke(
        app, ["batch", str(log), "-c", str(tmp_path / "c.yaml"), "--out-dir", str(tmp_path / "b")]
    )
    assert batch.exit_code == 0, batch.output
    assert "estimated with" not in (tmp_path / "b" / "summary.csv").read_text()


def test_a_clock_offset_not_estimated_is_not_called_observable(tmp_path):
    """With ``max_time_offset_s: 0`` no offset is estimated: the document says it is not
    observable (the SPEC: "kept at 0 (or not estimated)") and Kalibr's ``time_offset`` is 0.0,
    never ``-0.0``."""
    from imucal_cli.documents import load_document, write_document

    config = load_document(CONFIG)
    config["calibration"]["max_time_offset_s"] = 0.0
    write_document(tmp_path / "config.yaml", config)
    out = tmp_path / "estimate.json"
    result = runner.invoke(
        app, ["calibrate", str(LOG), "-c", str(tmp_path / "config.yaml"), "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    assert all(s["time_offset_s"] == 0.0 for s in doc["sensors"].values())
    assert not any(s["time_offset_observable"] for s in doc["sensors"].values())
    result = runner.invoke(app, ["export", str(out), "-f", "kalibr", "--allow-not-ok"])
    assert result.exit_code == 0, result.output
    offsets = [
        line.split(":", 1)[1].strip()
        for line in result.stdout.splitlines()
        if "time_offset:" in line
    ]
    assert len(offsets) == len(doc["sensors"]) + 1
    assert all(offset.startswith("0.0") for offset in offsets)
