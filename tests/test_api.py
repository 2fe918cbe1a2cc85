"""The Python API gives what the command line writes."""

from __future__ import annotations

import itertools

import yaml
from conftest import SAMPLE_DATA
from typer.testing import CliRunner

import imucal_cli
from imucal_cli.cli import app
from imucal_cli.documents import to_plain


def test_calibrate_log_equals_the_cli(tmp_path):
    log, config = SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    out = tmp_path / "e.yaml"
    assert (
        CliRunner()
        .invoke(app, ["calibrate", str(log), "-c", str(config), "-o", str(out)])
        .exit_code
        == 0
    )
    # the config read as the CLI reads it: what it leaves out from the log's /tf_static
    run = imucal_cli.calibrate_log(log, imucal_cli.load_config(config, log))
    assert yaml.safe_load(yaml.safe_dump(to_plain(run.document))) == yaml.safe_load(out.read_text())
    name = next(iter(run.document["sensors"]))
    T = run.result.T_base_lidar(name)
    assert T.to_dict() == run.document["sensors"][name]["T_base_lidar"]
    assert run.streamed.stats["/gnss/imu"].messages == 8100 and not [
        x for x in run.streamed.losses if x.lost
    ]
    files = imucal_cli.export_extrinsics(run.document, "urdf")
    assert f'<child link="{run.document["sensors"][name]["lidar_frame"]}"/>' in files["main"]


def test_the_documented_api_calibrates_with_progress_evaluates_exports_and_reports(tmp_path):
    """The example of docs/usage.md's Python API section, run."""
    log, config, truth = (
        SAMPLE_DATA / "aggressive.mcap",
        SAMPLE_DATA / "aggressive.config.yaml",
        SAMPLE_DATA / "aggressive.truth.yaml",
    )
    seen = []
    run = imucal_cli.calibrate_log(
        log, config, progress=lambda count, total: seen.append((count, total))
    )
    assert seen and seen[-1][0] == seen[-1][1] == sum(
        s.messages for s in run.streamed.stats.values()
    )
    assert all(a[0] <= b[0] for a, b in itertools.pairwise(seen))
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(to_plain(run.document)))
    verdict = imucal_cli.evaluate(
        tmp_path / "e.yaml", truth, max_rotation_deg=0.1, max_translation_m=0.03
    )
    assert verdict["pass"] is True and set(verdict["sensors"]) == set(run.document["sensors"])
    assert "base_link" in imucal_cli.export_extrinsics(run.document, "autoware")["main"]
    written = imucal_cli.write_report(tmp_path / "report", run)
    assert written[-1].name == "report.html" and all(p.is_file() for p in written)


def test_documents_are_plain_and_evaluate_takes_them_in_memory(tmp_path):
    """``run.document`` holds plain values (it held numpy arrays: neither yaml.safe_dump nor
    json.dumps took it); evaluate takes a document as well as a file; the public writer writes
    what calibrate -o writes (issue 32, item 8)."""
    import json

    import yaml
    from conftest import SAMPLE_DATA

    import imucal_cli

    run = imucal_cli.calibrate_log(
        SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml"
    )
    assert yaml.safe_load(yaml.safe_dump(run.document)) == run.document
    assert json.loads(json.dumps(run.document)) == run.document
    truth = SAMPLE_DATA / "aggressive.truth.yaml"
    in_memory = imucal_cli.evaluate(run.document, truth, max_rotation_deg=0.1)
    imucal_cli.write_document(tmp_path / "estimate.yaml", run.document)
    from_file = imucal_cli.evaluate(tmp_path / "estimate.yaml", truth, max_rotation_deg=0.1)
    assert in_memory == from_file and json.loads(json.dumps(in_memory)) == in_memory
    assert yaml.safe_load(
        yaml.safe_dump(
            imucal_cli.stream_biases(
                SAMPLE_DATA / "aggressive.mcap",
                imucal_cli.load_config(SAMPLE_DATA / "aggressive.config.yaml"),
            )
        )
    )
