"""calibrate --report: every figure is written, the page embeds them and the result table."""

from __future__ import annotations

import base64
import re

import yaml
from conftest import SAMPLE_DATA
from typer.testing import CliRunner

from imucal_cli.cli import app


def test_report_for_the_sample_drive(tmp_path, monkeypatch):
    from imucal_cli import reading

    # how many times the log is opened
    opens = tmp_path / "opened"
    real_open = reading.open_log

    def counted_open(path):
        with opens.open("a") as f:
            f.write(f"{path}\n")
        return real_open(path)

    monkeypatch.setattr(reading, "open_log", counted_open)
    out, report = tmp_path / "e.yaml", tmp_path / "report"
    result = CliRunner().invoke(
        app,
        [
            "calibrate",
            str(SAMPLE_DATA / "aggressive.mcap"),
            "-c",
            str(SAMPLE_DATA / "aggressive.config.yaml"),
            "-o",
            str(out),
            "--report",
            str(report),
        ],
    )
    assert result.exit_code == 0, result.output
    document = yaml.safe_load(out.read_text())
    names = list(document["sensors"])
    opened = opens.read_text().splitlines()
    assert len(opened) == 1  # the report draws from the calibration: no second read of the log
    expected = {
        "excitation.png",
        "biases.png",
        "windows.png",
        "residuals.png",
        "timeline.png",
        "std.png",
        "vehicle.png",
        "report.html",
    }
    assert {p.name for p in report.iterdir()} == expected
    page = (report / "report.html").read_text()
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == len(expected) - 1
    pngs = {p.read_bytes() for p in report.glob("*.png")}
    assert {base64.b64decode(i) for i in images} == pngs and all(
        p.startswith(b"\x89PNG\r\n\x1a\n") for p in pngs
    )
    for name in names:  # the result table: every sensor with its status and estimate
        row = re.search(rf'<tr><td>{name}</td><td class="\w+">(\w+)</td><td>([^<]+)</td>', page)
        assert row and row.group(1) == document["sensors"][name]["status"]
        assert row.group(2) == ", ".join(
            f"{v:.4f}" for v in document["sensors"][name]["T_base_lidar"]["translation"]
        )


def test_report_folder_parent_missing_exits_2(tmp_path):
    result = CliRunner().invoke(
        app,
        [
            "calibrate",
            str(SAMPLE_DATA / "aggressive.mcap"),
            "-c",
            str(SAMPLE_DATA / "aggressive.config.yaml"),
            "--report",
            str(tmp_path / "no" / "r"),
        ],
    )
    assert result.exit_code == 2 and "no/r" in result.stderr


def test_no_figure_the_report_writes_may_replace_an_input(tmp_path):
    """``--report`` refuses a folder where any of its files is an input, before any work: the
    list it guards is the list it draws (excitation.png was drawn and not guarded)."""
    import shutil

    from imucal_cli.report import CAPTIONS

    for name in CAPTIONS:
        folder = tmp_path / name.removesuffix(".png")
        folder.mkdir()
        config = folder / name  # (the config, where the report would write a figure)
        shutil.copy(SAMPLE_DATA / "aggressive.config.yaml", config)
        args = ["calibrate", str(SAMPLE_DATA / "aggressive.mcap"), "-c", str(config)]
        result = CliRunner().invoke(app, [*args, "--report", str(folder)])
        assert result.exit_code == 2 and name in result.stderr, (name, result.output)
        assert config.read_bytes() == (SAMPLE_DATA / "aggressive.config.yaml").read_bytes()


def test_no_legend_covers_a_plot(tmp_path, monkeypatch):
    """Every legend of every figure lies outside every axes' data area (the legends sat at
    the upper right, over the lines)."""
    from imucal_cli import report

    checked = []
    real_save = report._save

    def check(fig, path):
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        areas = [ax.get_window_extent(renderer) for ax in fig.axes]
        legends = [ax.get_legend() for ax in fig.axes] + list(fig.legends)
        for legend in (x for x in legends if x is not None):
            box = legend.get_window_extent(renderer)
            assert not any(box.overlaps(area) for area in areas), path.name
            checked.append(path.name)
        return real_save(fig, path)

    monkeypatch.setattr(report, "_save", check)
    argv = ["calibrate", str(SAMPLE_DATA / "aggressive.mcap"), "-c"]
    argv += [str(SAMPLE_DATA / "aggressive.config.yaml"), "--report", str(tmp_path / "r")]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 0, result.output
    assert {"biases.png", "windows.png", "residuals.png", "std.png", "vehicle.png"} <= set(checked)


def test_the_page_says_why_each_sensor_has_its_status(tmp_path):
    """An inconsistent sensor's warnings and failed checks, with their figures, are on the page;
    an unobservable one gets 'not shown' for its clock and says it has no checks."""
    import html

    from imucal_cli.api import calibrate
    from imucal_cli.report import html_page

    document = yaml.safe_load((SAMPLE_DATA / "aggressive.config.yaml").read_text())
    first = next(iter(document["sensors"].values()))
    first["prior_T_base_imu"]["translation"][0] += 0.5  # the box binds: not ok
    config = tmp_path / "off.yaml"
    config.write_text(yaml.safe_dump(document))
    run = calibrate(SAMPLE_DATA / "aggressive.mcap", config)
    page = html_page("t", run.document(), [])
    for name, sensor in run.document()["sensors"].items():
        assert f"<h2>{name}: {sensor['status']}</h2>" in page
        for warning in sensor["warnings"]:
            assert f"<li>{html.escape(warning)}</li>" in page
        for check, figures in sensor["checks"].items():
            verdict = "pass" if figures["pass"] else "FAIL"
            assert f"<tr><td>{check}</td><td>{verdict}</td>" in page
    assert any(
        not c["pass"] for s in run.document()["sensors"].values() for c in s["checks"].values()
    )
    unobservable = {**run.document()}
    name = next(iter(unobservable["sensors"]))
    unobservable["sensors"] = {
        name: {**run.document()["sensors"][name], "status": "unobservable", "checks": {}}
    }
    page = html_page("t", unobservable, [])
    assert "not shown" in page and "No checks" in page


def test_a_report_ended_midway_leaves_nothing_of_it(tmp_path, monkeypatch):
    """A SIGTERM during --report left a folder with 1 figure of 5; a full disk left a partial
    figure and matplotlib's traceback. The report is made aside and moved in whole: a failed
    figure leaves no file of it (and, on a full disk, one line and exit 2)."""
    import errno

    from imucal_cli import report as report_module

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report_module, "vehicle_figure", full_disk)  # the fifth figure
    out, report = tmp_path / "e.yaml", tmp_path / "report"
    argv = ["calibrate", str(SAMPLE_DATA / "aggressive.mcap")]
    argv += ["-c", str(SAMPLE_DATA / "aggressive.config.yaml"), "--report", str(report)]
    result = CliRunner().invoke(app, [*argv, "-o", str(out)])
    assert result.exit_code == 2, result.output
    assert "cannot write the report: No space left on device" in result.stderr
    assert result.stderr.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no report, no partial, no -o


def test_the_vehicle_figure_sets_each_lidar_beside_its_own_prior(tmp_path, monkeypatch):
    """The whole-vehicle views compare like with like: each lidar as estimated (solid) against
    the lidar its CAD prior places (dashed), not against the IMU's prior, which on the sample's
    Ouster-style mounts (the IMU turned 180 deg about z in the housing) points the other way
    and made a right result look 180 deg off."""
    from imucal_cli import report
    from imucal_cli.api import calibrate
    from imucal_cli.core.so3 import rotation_angle_deg

    calibration = calibrate(SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml")
    drawn = []
    real = report._draw_axes
    monkeypatch.setattr(
        report,
        "_draw_axes",
        lambda ax, T, i, j, *rest: drawn.append((T, rest[1])) or real(ax, T, i, j, *rest),
    )
    poses = report._poses(calibration)
    report.vehicle_figure(report.pyplot(), poses, tmp_path / "vehicle.png")
    per_view = 1 + 2 * len(poses)  # (the base, then each sensor: its prior, then its lidar)
    for view in (drawn[:per_view], drawn[per_view : 2 * per_view]):
        for (prior, dashed), (lidar, solid), sensor in zip(
            view[1::2], view[2::2], poses.values(), strict=True
        ):
            assert (dashed, solid) == ("--", "-") and lidar is sensor["lidar"]
            assert rotation_angle_deg(prior.rotation, lidar.rotation) < 10.0
            assert rotation_angle_deg(sensor["prior_imu"].rotation, lidar.rotation) > 170.0


def test_the_std_figure_of_an_unobservable_sensor_has_no_negative_std(tmp_path, monkeypatch):
    """A sensor without a std is said "not observable" in its place; the axes start at 0 (a
    std is never negative) and, where no sensor has one, show no scale at all."""
    import numpy as np

    from imucal_cli import report

    figures = []
    monkeypatch.setattr(report, "_save", lambda fig, path: figures.append(fig) or path)
    plt = report.pyplot()
    some = {"a": (np.array([0.01, 0.02, 0.03]), np.array([0.001, 0.002, 0.003])), "b": (None, None)}
    for stds in (some, {"b": (None, None)}):
        report.std_figure(plt, stds, tmp_path / "std.png")
    for fig, stds in zip(figures, (some, {"b": (None, None)}), strict=True):
        for ax in fig.axes:
            assert ax.get_ylim()[0] == 0.0
            assert [t.get_text() for t in ax.texts] == ["not observable"]
            assert (len(ax.get_yticks()) == 0) == (stds is not some)
        plt.close(fig)


def test_the_page_answers_the_next_question(tmp_path):
    """The report's page is the one an engineer keeps open: per sensor the estimate less the
    lidar its CAD prior places, the total and the statistical std, the clock's offset and
    drift, the moves; the pairs; where each prior came from and the grades; and what to drive
    next where an axis is short of the stop: targets."""
    import html as html_module

    from imucal_cli.api import calibrate
    from imucal_cli.core.so3 import rotation_angle_deg
    from imucal_cli.documents import load_document, write_document
    from imucal_cli.report import write_report

    config = load_document(SAMPLE_DATA / "aggressive.config.yaml")
    config["stop"] = {"max_rotation_std_deg": 0.001, "max_translation_std_m": 0.0001}  # unmet
    write_document(tmp_path / "c.yaml", config)
    cal = calibrate(SAMPLE_DATA / "aggressive.mcap", tmp_path / "c.yaml")
    write_report(tmp_path / "report", cal)
    page = html_module.unescape((tmp_path / "report" / "report.html").read_text())
    for heading in ("Summary", "Pairs", "Where each prior came from", "What to drive next"):
        assert f"<h2>{heading}</h2>" in page
    document = cal.document()
    for s in cal.config.sensors:
        prior = s.prior_T_base_imu * s.T_imu_lidar
        angle = rotation_angle_deg(prior.rotation, cal.T_base_lidar(s.name).rotation)
        assert f"<td>{angle:.3f}</td>" in page  # (the CAD prior's lidar, not its IMU: not 180)
        assert angle < 10.0
        statistical = document["sensors"][s.name]["statistical_std"]["rotation_deg"]
        assert ", ".join(f"{v:.4f}" for v in statistical) in page
        assert f"<td>{s.grade}</td>" in page
    for pair in document["pairs"]:
        assert f"<td>{pair}</td>" in page
    assert "<td>tf_static</td>" in page  # (the sample's base pose: from its /tf_static)
    assert "rotation z (yaw)" in page.split("What to drive next")[1]


def test_the_summary_says_the_prior_and_the_driving_as_they_are(tmp_path):
    """An unobservable sensor's pose is the prior's: no difference from it is shown (0.000 read
    as a measurement); an offset the config does not estimate is "not estimated", not "not
    shown"; an inconsistent sensor is not told to drive more (it would not mend it)."""
    import yaml

    from imucal_cli.report import _summary_row, _what_to_drive

    sensor = yaml.safe_load((SAMPLE_DATA / "aggressive.truth.yaml").read_text())["sensors"]
    s = {
        "T_base_lidar": next(iter(sensor.values()))["T_base_lidar"],
        "status": "unobservable",
        "rotation_std_deg": None,
        "translation_std_m": None,
        "time_offset_s": 0.0,
        "time_offset_observable": False,
        "segments": {"selected": 0, "total": 6},
    }
    extra = {"prior_angle_deg": 0.0, "prior_shift_m": [0.0, 0.0, 0.0], "offset_estimated": False}
    row = _summary_row("a", s, extra)
    assert "- (the prior)" in row and "0.000" not in row and "not estimated" in row
    missing = ["rotation z (yaw): turns in both directions (std 0.1 deg, target 0.02)"]
    assert "turns in both directions" in _what_to_drive("partial", missing)
    assert "turns" not in _what_to_drive("inconsistent", missing)
