"""The Python API gives what the command line writes."""

from __future__ import annotations

import yaml
from conftest import SAMPLE_DATA
from typer.testing import CliRunner

import imucal_cli
from imucal_cli.cli import app
from imucal_cli.documents import to_plain


def test_the_api_calibration_equals_the_cli(tmp_path):
    log, config = SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    out = tmp_path / "e.yaml"
    assert (
        CliRunner()
        .invoke(app, ["calibrate", str(log), "-c", str(config), "-o", str(out)])
        .exit_code
        == 0
    )
    # the config read as the CLI reads it: what it leaves out from the log's /tf_static
    run = imucal_cli.calibrate(log, imucal_cli.load_config(config, log))
    assert yaml.safe_load(yaml.safe_dump(to_plain(run.document()))) == yaml.safe_load(
        out.read_text()
    )
    name = next(iter(run.document()["sensors"]))
    T = run.T_base_lidar(name)
    assert T.to_dict() == run.document()["sensors"][name]["T_base_lidar"]
    assert run.reading.counts["/gnss/imu"]["messages"] == 8100 and not [
        x for x in run.reading.losses if x.lost
    ]
    files = imucal_cli.export(run.document(), "urdf")
    assert f'<child link="{run.document()["sensors"][name]["lidar_frame"]}"/>' in files["main"]


def test_the_python_api_section_of_the_usage_guide_runs_as_written(tmp_path, monkeypatch):
    """The code of docs/usage.md's Python API section, run as it is written (from a folder
    holding sample_data/): it calibrates, writes, exports, reports, evaluates and follows."""
    import re

    guide = (SAMPLE_DATA.parent / "docs" / "usage.md").read_text()
    section = guide[guide.index("## Python API") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "sample_data").symlink_to(SAMPLE_DATA)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(code, "docs/usage.md", "exec"), scope)
    cal, verdict = scope["cal"], scope["verdict"]
    assert verdict["pass"] is True and (tmp_path / "estimate.yaml").is_file()
    assert (tmp_path / "report" / "report.html").is_file()
    assert "<robot" in scope["files"]["main"] and set(scope["biases"]["imus"]) >= {"base"}
    assert scope["windows"].segments_document()["sensors"]
    assert not scope["interrupted"] and scope["latest"].followed
    assert cal.reading.counts["/gnss/imu"]["messages"] == 8100


def test_documents_are_plain_and_evaluate_takes_them_in_memory(tmp_path):
    """``run.document()`` holds plain values (it held numpy arrays: neither yaml.safe_dump nor
    json.dumps took it); evaluate takes a document as well as a file; the public writer writes
    what calibrate -o writes (issue 32, item 8)."""
    import json

    import yaml
    from conftest import SAMPLE_DATA

    import imucal_cli

    run = imucal_cli.calibrate(
        SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    )
    assert yaml.safe_load(yaml.safe_dump(run.document())) == run.document()
    assert json.loads(json.dumps(run.document())) == run.document()
    truth = SAMPLE_DATA / "aggressive.truth.yaml"
    in_memory = imucal_cli.evaluate(run.document(), truth, max_rotation_deg=0.1)
    imucal_cli.write_document(tmp_path / "estimate.yaml", run.document())
    from_file = imucal_cli.evaluate(tmp_path / "estimate.yaml", truth, max_rotation_deg=0.1)
    assert in_memory == from_file and json.loads(json.dumps(in_memory)) == in_memory
    assert yaml.safe_load(
        yaml.safe_dump(
            imucal_cli.biases(
                SAMPLE_DATA / "aggressive.mcap",
                imucal_cli.load_config(SAMPLE_DATA / "aggressive.config.yaml"),
            )
        )
    )
