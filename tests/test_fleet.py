"""imucal batch: local processes and a Dask LocalCluster give identical results; JUnit is valid."""

from __future__ import annotations

import csv
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.documents import write_document
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.sim.writers import write_imu_log
from imucal_cli.types import Transform

runner = CliRunner()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    logs = []
    for seed in (1, 2, 3):
        drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=40.0, seed=seed))
        logs.append(write_imu_log(root / f"d{seed}.mcap", "mcap", drive.topics()))
        write_document(root / f"d{seed}.truth.yaml", drive.truth_document())
        write_document(root / "config.yaml", drive.config_document())
    broken = root / "broken.mcap"
    broken.write_bytes(b"not a log")
    return root, [*logs, broken]


def _run(root, logs, out, *extra):
    args = ["batch", *map(str, logs), "-c", str(root / "config.yaml"), "--out-dir", str(out), "--truth-dir", str(root),
            "--max-rotation-deg", "0.1", "--max-translation-m", "0.03", "--junit", str(out.parent / f"{out.name}.xml"), *extra]
    return runner.invoke(app, args)


def _rows(out):
    with (out / "summary.csv").open() as handle:
        return list(csv.DictReader(handle))


def test_jobs_and_dask_cluster_give_identical_results(fleet, tmp_path):
    pytest.importorskip("dask.distributed")
    from dask.distributed import LocalCluster

    root, logs = fleet
    serial = _run(root, logs, tmp_path / "one", "--jobs", "1")
    assert serial.exit_code == 1, serial.output  # the broken log fails; the others pass
    rows = _rows(tmp_path / "one")
    assert [r["log"] for r in rows] == ["d1.mcap"] * 2 + ["d2.mcap"] * 2 + ["d3.mcap"] * 2 + ["broken.mcap"]
    assert all(r["pass"] == "True" for r in rows[:-1]) and rows[-1]["status"] == "failed" and "broken.mcap" in rows[-1]["error"]
    for log in logs[:-1]:  # each calibration written in full
        assert yaml.safe_load((tmp_path / "one" / f"{log.stem}.yaml").read_text())["sensors"]
    parallel = _run(root, logs, tmp_path / "two", "--jobs", "2")
    assert parallel.exit_code == 1
    assert _rows(tmp_path / "two") == rows
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None) as cluster:
        distributed = _run(root, logs, tmp_path / "dask", "--scheduler", cluster.scheduler_address)
    assert distributed.exit_code == 1, distributed.output
    assert _rows(tmp_path / "dask") == rows
    summary = json.loads((tmp_path / "dask" / "summary.json").read_text())
    assert summary["failed"] == 1 and len(summary["rows"]) == 7


def test_junit_is_valid_and_counts_failures(fleet, tmp_path):
    root, logs = fleet
    _run(root, logs, tmp_path / "j")
    suite = ET.parse(tmp_path / "j.xml").getroot().find("testsuite")
    assert suite.get("tests") == "7" and suite.get("errors") == "1" and suite.get("failures") == "0"
    cases = suite.findall("testcase")
    assert len(cases) == 7 and cases[-1].find("error") is not None
    assert all(float(c.get("time")) >= 0 for c in cases)


def test_reference_flags_sensors_that_moved(fleet, tmp_path):
    root, logs = fleet
    first = runner.invoke(app, ["calibrate", str(logs[0]), "-c", str(root / "config.yaml"), "-o", str(tmp_path / "last.yaml")])
    assert first.exit_code == 0
    reference = yaml.safe_load((tmp_path / "last.yaml").read_text())
    moved = next(iter(reference["sensors"]))
    T = Transform.from_dict(reference["sensors"][moved]["T_base_lidar"])
    bumped = Transform.from_rpy(np.radians([0.0, 0.0, 1.0]), np.zeros(3)) * T  # knocked by 1 deg
    reference["sensors"][moved]["T_base_lidar"] = {"translation": list(bumped.translation), "rotation": list(bumped.quaternion_xyzw)}
    write_document(tmp_path / "reference.yaml", reference)
    result = runner.invoke(app, ["batch", str(logs[1]), "-c", str(root / "config.yaml"), "--out-dir", str(tmp_path / "r"),
                                 "--reference", str(tmp_path / "reference.yaml"), "--max-rotation-deg", "0.2", "--max-translation-m", "0.05"])
    assert result.exit_code == 1
    rows = {r["sensor"]: r for r in _rows(tmp_path / "r")}
    assert rows[moved]["moved"] == "True" and rows[moved]["pass"] == "False"
    assert float(rows[moved]["rotation_error_deg"]) == pytest.approx(1.0, abs=0.05)
    assert all(r["moved"] == "False" and r["pass"] == "True" for name, r in rows.items() if name != moved)
