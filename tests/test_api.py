"""The Python API gives what the command line writes."""

from __future__ import annotations

import yaml
from conftest import SAMPLE_DATA
from typer.testing import CliRunner

import imucal_cli
from imucal_cli.cli import app
from imucal_cli.documents import to_plain


def test_calibrate_log_equals_the_cli(tmp_path):
    log, config = SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    out = tmp_path / "e.yaml"
    assert CliRunner().invoke(app, ["calibrate", str(log), "-c", str(config), "-o", str(out)]).exit_code == 0
    run = imucal_cli.calibrate_log(log, imucal_cli.load_config(config))
    assert yaml.safe_load(yaml.safe_dump(to_plain(run.document))) == yaml.safe_load(out.read_text())
    name = next(iter(run.document["sensors"]))
    T = run.result.T_base_lidar(name)
    assert T.to_dict() == run.document["sensors"][name]["T_base_lidar"]
    assert run.streamed.stats["/gnss/imu"].messages == 8100 and not [x for x in run.streamed.losses if x.lost]
    files = imucal_cli.export_extrinsics(run.document, "urdf")
    assert f'<child link="{run.document["sensors"][name]["lidar_frame"]}"/>' in files["main"]
