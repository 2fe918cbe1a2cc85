"""imucal batch: local processes and a Dask LocalCluster give identical results; JUnit is valid."""

from __future__ import annotations

import csv
import json
import xml.etree.ElementTree as ET
from pathlib import Path

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
    args = [
        "batch",
        *map(str, logs),
        "-c",
        str(root / "config.yaml"),
        "--out-dir",
        str(out),
        "--truth-dir",
        str(root),
        "--max-rotation-deg",
        "0.1",
        "--max-translation-m",
        "0.03",
        "--junit",
        str(out.parent / f"{out.name}.xml"),
        *extra,
    ]
    return runner.invoke(app, args)


def _rows(out):
    with (out / "summary.csv").open() as handle:
        return list(csv.DictReader(handle))


def _knocked_reference(folder, yaw_deg: float) -> str:
    """``folder/reference.yaml``: ``folder/last.yaml`` with its first sensor's lidar turned by
    ``yaw_deg`` about z (a knock since that calibration); returns that sensor's name."""
    reference = yaml.safe_load((folder / "last.yaml").read_text())
    moved = next(iter(reference["sensors"]))
    T = Transform.from_dict(reference["sensors"][moved]["T_base_lidar"])
    turned = Transform.from_rpy(np.radians([0.0, 0.0, yaw_deg]), np.zeros(3)) * T
    reference["sensors"][moved]["T_base_lidar"] = {
        "translation": list(turned.translation),
        "rotation": list(turned.quaternion_xyzw),
    }
    write_document(folder / "reference.yaml", reference)
    return moved


def test_jobs_and_dask_cluster_give_identical_results(fleet, tmp_path):
    pytest.importorskip("dask.distributed")
    from dask.distributed import LocalCluster

    root, logs = fleet
    serial = _run(root, logs, tmp_path / "one", "--jobs", "1")
    assert serial.exit_code == 1, serial.output  # the broken log fails; the others pass
    rows = _rows(tmp_path / "one")
    assert [Path(r["log"]).name for r in rows] == ["d1.mcap"] * 2 + ["d2.mcap"] * 2 + [
        "d3.mcap"
    ] * 2 + ["broken.mcap"]
    assert all(Path(r["log"]).is_absolute() for r in rows)  # the full path, not a trimmed one
    assert (
        all(r["pass"] == "True" for r in rows[:-1])
        and rows[-1]["status"] == "failed"
        and "broken.mcap" in rows[-1]["error"]
    )
    for log in logs[:-1]:  # each calibration written in full
        assert yaml.safe_load((tmp_path / "one" / f"{log.stem}.yaml").read_text())["sensors"]
    parallel = _run(root, logs, tmp_path / "two", "--jobs", "2")
    assert parallel.exit_code == 1
    assert _rows(tmp_path / "two") == rows
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
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
    first = runner.invoke(
        app,
        [
            "calibrate",
            str(logs[0]),
            "-c",
            str(root / "config.yaml"),
            "-o",
            str(tmp_path / "last.yaml"),
        ],
    )
    assert first.exit_code == 0
    moved = _knocked_reference(tmp_path, 1.0)
    result = runner.invoke(
        app,
        [
            "batch",
            str(logs[1]),
            "-c",
            str(root / "config.yaml"),
            "--out-dir",
            str(tmp_path / "r"),
            "--reference",
            str(tmp_path / "reference.yaml"),
            "--max-rotation-deg",
            "0.2",
            "--max-translation-m",
            "0.05",
        ],
    )
    assert result.exit_code == 1
    rows = {r["sensor"]: r for r in _rows(tmp_path / "r")}
    assert rows[moved]["moved"] == "True" and rows[moved]["pass"] == "False"
    assert float(rows[moved]["rotation_error_deg"]) == pytest.approx(1.0, abs=0.05)
    assert all(
        r["moved"] == "False" and r["pass"] == "True" for name, r in rows.items() if name != moved
    )


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """Six short drives in a vehicle/date/drive layout, each with its own config and truth;
    two of them share a file name."""
    root = tmp_path_factory.mktemp("six")
    rows = ["log,config,truth"]
    for k in range(6):
        drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=20.0, seed=20 + k))
        folder = root / f"truck{k % 2}" / f"2026-11-{k + 1:02d}"
        folder.mkdir(parents=True)
        name = "drive.mcap" if k < 2 else f"drive{k}.mcap"
        write_imu_log(folder / name, "mcap", drive.topics())
        write_document(folder / "config.yaml", drive.config_document())
        write_document(folder / "truth.yaml", drive.truth_document())
        rel = folder.relative_to(root)
        rows.append(f"{rel / name},{rel / 'config.yaml'},{rel / 'truth.yaml'}")
    (root / "drives.csv").write_text("\n".join(rows) + "\n")
    return root


def _batch(manifest, out, *extra):
    return runner.invoke(
        app,
        [
            "batch",
            "--manifest",
            str(manifest),
            "--out-dir",
            str(out),
            "--junit",
            str(out / "junit.xml"),
            *extra,
        ],
    )


def test_logs_of_one_name_in_other_folders_and_a_fresh_out_folder(six, tmp_path):
    result = _batch(
        six / "drives.csv", tmp_path / "fresh"
    )  # the README's example: out and its junit made here
    assert result.exit_code in (0, 1), result.output
    names = [r["log"] for r in _rows(tmp_path / "fresh")]
    assert (
        str(six / "truck0/2026-11-01/drive.mcap") in names
        and str(six / "truck1/2026-11-02/drive.mcap") in names
    )
    # DIR/STEM.yaml, with as many folders before the stem as tell two logs of one name apart
    assert (tmp_path / "fresh" / "2026-11-01_drive.yaml").is_file() and (
        tmp_path / "fresh" / "2026-11-02_drive.yaml"
    ).is_file()
    assert (tmp_path / "fresh" / "drive3.yaml").is_file()
    assert ET.parse(tmp_path / "fresh" / "junit.xml").getroot().find("testsuite").get(
        "tests"
    ) == str(len(names))


def test_a_damaged_log_fails_its_rows_and_says_what_was_lost_everywhere(six, tmp_path):
    import shutil

    work = tmp_path / "logs"
    shutil.copytree(six, work)
    log = work / "truck0" / "2026-11-01" / "drive.mcap"
    log.write_bytes(
        log.read_bytes()[: int(log.stat().st_size * 0.4)]
    )  # cut at 40%, as a killed recorder leaves it
    result = _batch(work / "drives.csv", tmp_path / "out")
    assert result.exit_code == 1
    rows = [r for r in _rows(tmp_path / "out") if r["log"] == str(log)]
    assert rows and all(
        r["pass"] == "False" and "cut off" in r["warnings"] and "read lost" in r["error"]
        for r in rows
    )
    assert all(
        r["lost_s"] == "" for r in rows
    )  # a cut's span is not known: never passes for a number
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert all("cut off" in r["warnings"] for r in summary["rows"] if r["log"] == rows[0]["log"])
    document = yaml.safe_load((tmp_path / "out" / "2026-11-01_drive.yaml").read_text())
    assert (
        document["losses"]
        and "cut off" in document["losses"][0]["reason"]
        and document["lost_s"] is None
    )
    cases = [
        c
        for c in ET.parse(tmp_path / "out" / "junit.xml").getroot().iter("testcase")
        if c.get("classname") == rows[0]["log"]
    ]
    assert cases and all(
        c.find("failure") is not None and "cut off" in c.find("system-out").text for c in cases
    )
    intact = [r for r in _rows(tmp_path / "out") if r["log"] != rows[0]["log"]]
    assert all(r["lost_s"] == "0.0" and "cut off" not in r["warnings"] for r in intact)


def test_a_real_dask_cluster_started_in_another_folder_gives_the_local_summary(
    six, tmp_path, monkeypatch
):
    """A scheduler and two workers as their own processes, started in a folder that is not the
    logs'; the batch given relative paths (resolved and read before submitting)."""
    import shutil
    import subprocess
    import sys
    import time

    pytest.importorskip("dask.distributed")
    dask = shutil.which("dask", path=str(Path(sys.executable).parent))
    if dask is None:
        pytest.skip("Dask's `dask` command (pip install 'imucal[fleet]') is not installed")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(six)
    local = _batch(Path("drives.csv"), tmp_path / "local")
    scheduler_file = elsewhere / "scheduler.json"
    processes = [
        subprocess.Popen(
            [
                dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(scheduler_file),
            ],
            cwd=elsewhere,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())["address"]
        for _ in range(2):
            processes.append(
                subprocess.Popen(
                    [
                        dask,
                        "worker",
                        address,
                        "--nworkers",
                        "1",
                        "--nthreads",
                        "1",
                        "--no-dashboard",
                    ],
                    cwd=elsewhere,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        from dask.distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        remote = _batch(Path("drives.csv"), tmp_path / "dask", "--scheduler", address)
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            process.wait(timeout=30)
    assert remote.exit_code == local.exit_code, remote.output
    assert _rows(tmp_path / "dask") == _rows(tmp_path / "local")
    assert all("not found" not in r["error"] for r in _rows(tmp_path / "dask"))


def test_reference_without_thresholds_flags_a_move_past_three_combined_std(fleet, tmp_path):
    root, logs = fleet
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(logs[0]),
                "-c",
                str(root / "config.yaml"),
                "-o",
                str(tmp_path / "last.yaml"),
            ],
        ).exit_code
        == 0
    )
    moved = _knocked_reference(tmp_path, 0.47)  # the 0.47 deg
    result = runner.invoke(
        app,
        [
            "batch",
            str(logs[0]),
            "-c",
            str(root / "config.yaml"),
            "--out-dir",
            str(tmp_path / "r"),
            "--reference",
            str(tmp_path / "reference.yaml"),
        ],
    )
    assert result.exit_code == 1 and "3 combined std" in result.stderr
    rows = {r["sensor"]: r for r in _rows(tmp_path / "r")}
    assert (
        rows[moved]["moved"] == "True"
        and rows[moved]["pass"] == "False"
        and "limit" in rows[moved]["error"]
    )
    assert all(
        r["moved"] == "False" and r["pass"] == "True" for name, r in rows.items() if name != moved
    )


def test_plan_takes_each_reference_std_from_its_own_file(tmp_path):
    """A manifest's per-log reference gives that log's "moved" test the std of that reference
    (not of another); a truth folder without the log's file compares nothing; a named truth
    file that is missing is an error naming it."""
    from imucal_cli.errors import InputError
    from imucal_cli.fleet import plan_tasks

    sample = Path(__file__).resolve().parents[2] / "sample_data"
    config = sample / "urban.config.yaml"
    refs = {}
    for std in (0.01, 0.5):
        doc = {
            "sensors": {
                "front_left_top": {
                    "T_base_lidar": Transform.identity().to_dict(),
                    "rotation_std_deg": [std, std / 2, std / 4],
                    "translation_std_m": [std / 10] * 3,
                }
            }
        }
        refs[std] = tmp_path / f"ref{std}.yaml"
        write_document(refs[std], doc)
    logs = [sample / "urban.mcap", sample / "aggressive.mcap"]
    entries = [
        {"log": str(logs[0]), "reference": str(refs[0.01])},
        {"log": str(logs[1]), "reference": str(refs[0.5])},
    ]
    tasks = plan_tasks(entries, config, tmp_path / "out")
    assert [t.reference_std["front_left_top"] for t in tasks] == [(0.01, 0.001), (0.5, 0.05)]
    assert all(t.reference and set(t.against) == {"front_left_top"} for t in tasks)
    (tmp_path / "truths").mkdir()
    task = plan_tasks(
        [{"log": str(logs[0])}], config, tmp_path / "out", truth_dir=tmp_path / "truths"
    )[0]
    assert task.against == {} and not task.reference
    with pytest.raises(InputError, match=r"nope\.truth\.yaml"):
        plan_tasks(
            [{"log": str(logs[0]), "truth": str(tmp_path / "nope.truth.yaml")}],
            config,
            tmp_path / "out",
            truth_dir=tmp_path / "truths",
        )


def test_a_worker_killed_fails_its_own_log_by_name_and_no_other(fleet, tmp_path, monkeypatch):
    """As the out-of-memory killer would: one log's worker dies; the others are calibrated, and
    the failed row names the log and the signal (it used to fail every unfinished log as
    "BrokenProcessPool")."""
    import os
    import signal

    import imucal_cli.fleet as fleet_module

    root, logs = fleet
    victim = logs[1]
    real = fleet_module.run_one

    def dies_on_the_victim(task):
        if task.log == str(victim):
            os.kill(os.getpid(), signal.SIGKILL)
        return real(task)

    monkeypatch.setattr(fleet_module, "run_one", dies_on_the_victim)  # (the fork inherits it)
    out = tmp_path / "out"
    result = _run(root, logs[:3], out, "--jobs", "2")
    assert result.exit_code == 1, result.output
    rows = {Path(r["log"]).name: r for r in _rows(out)}
    killed = rows[victim.name]
    assert (
        killed["status"] == "failed"
        and str(victim) in killed["error"]
        and "SIGKILL" in killed["error"]
    )
    for log in (logs[0], logs[2]):
        assert rows[log.name]["status"] == "ok", rows[log.name]
    assert not (out / f"{victim.stem}.yaml").exists()


def test_ctrl_c_during_a_batch_stops_it_and_starts_no_other_log(fleet, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    from recorder import with_terminal_sigint

    root, logs = fleet
    many = [logs[k % 3] for k in range(3)]
    copies = []
    for k, log in enumerate(many * 3):
        copies.append(tmp_path / f"c{k}.mcap")
        copies[-1].write_bytes(log.read_bytes())
    out = tmp_path / "out"
    argv = [
        sys.executable,
        "-m",
        "imucal_cli.cli",
        "batch",
        *map(str, copies),
        "-c",
        str(root / "config.yaml"),
        "--out-dir",
        str(out),
        "--jobs",
        "2",
    ]
    process = subprocess.Popen(
        with_terminal_sigint(argv),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out.is_dir() and any(out.glob("*.yaml"))):
        time.sleep(0.02)
    os.killpg(process.pid, signal.SIGINT)
    started = time.monotonic()
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert time.monotonic() - started < 10  # not the rest of the queue
    assert b"interrupted" in stderr and b"Traceback" not in stderr
    finished = sorted(p.stem for p in out.glob("c*.yaml"))
    assert len(finished) < len(copies)
    # the logs finished before the Ctrl-C are summarised (they had no summary)
    summary = (out / "summary.csv").read_text()
    assert all(f"{name}.mcap" in summary for name in finished)
    assert "interrupted" in (out / "summary.json").read_text()


def test_sigterm_during_a_batch_ends_it_as_a_ctrl_c_does_with_exit_143(fleet, tmp_path):
    """SIGTERM (a CI runner's timeout) to batch's main process left its --jobs workers
    computing their logs. It now ends as a Ctrl-C does: workers ended, the finished logs
    summarised, exit 143."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root, logs = fleet
    copies = []
    for k in range(9):
        copies.append(tmp_path / f"c{k}.mcap")
        copies[-1].write_bytes(logs[k % 3].read_bytes())
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "imucal_cli.cli", "batch", *map(str, copies)]
    argv += ["-c", str(root / "config.yaml"), "--out-dir", str(out), "--jobs", "2"]
    process = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out.is_dir() and any(out.glob("*.yaml"))):
        time.sleep(0.02)
    process.send_signal(signal.SIGTERM)  # the main process alone
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 143, stderr
    assert b"terminated" in stderr and b"Traceback" not in stderr
    assert (out / "summary.csv").exists()
    deadline = time.monotonic() + 10  # and no process of its group left
    while time.monotonic() < deadline:
        left = [p for p in os.listdir("/proc") if p.isdigit() and _in_group(p, process.pid)]
        if not left:
            break
        time.sleep(0.05)
    assert left == []


def _in_group(pid: str, group: int) -> bool:
    import os

    try:
        return os.getpgid(int(pid)) == group
    except OSError:
        return False


def test_a_scheduler_without_workers_is_an_error_not_a_hang(fleet, tmp_path, monkeypatch):
    pytest.importorskip("dask.distributed")
    import asyncio

    from distributed import Scheduler

    import imucal_cli.fleet as fleet_module

    monkeypatch.setattr(fleet_module, "DASK_WORKERS_S", 2.0)
    root, logs = fleet

    async def scheduler_alone():
        async with Scheduler(host="127.0.0.1", port=0, dashboard_address=None) as scheduler:
            result = await asyncio.to_thread(
                runner.invoke,
                app,
                [
                    "batch",
                    str(logs[0]),
                    "-c",
                    str(root / "config.yaml"),
                    "--out-dir",
                    str(tmp_path / "out"),
                    "--scheduler",
                    scheduler.address,
                ],
            )
            return result

    result = asyncio.run(scheduler_alone())
    assert result.exit_code == 2, result.output
    assert "no worker joined" in result.stderr
    assert not (tmp_path / "out" / "summary.csv").exists()


def test_a_scheduler_killed_mid_batch_fails_the_rest_and_nothing_is_written_for_them(
    fleet, tmp_path
):
    """The scheduler dies (SIGKILL) while the batch runs: the logs not done are failed rows
    that say so, the batch exits 1 without a traceback, and no output exists for a failed log
    (workers write nothing: the batch's own process writes each document)."""
    import shutil
    import signal
    import subprocess
    import sys
    import time

    pytest.importorskip("dask.distributed")
    dask = shutil.which("dask", path=str(Path(sys.executable).parent))
    if dask is None:
        pytest.skip("Dask's `dask` command (pip install 'imucal[fleet]') is not installed")
    root, logs = fleet
    copies = []
    for k in range(40):
        copies.append(tmp_path / f"c{k}.mcap")
        copies[-1].write_bytes(logs[k % 3].read_bytes())
    scheduler_file = tmp_path / "scheduler.json"
    processes = [
        subprocess.Popen(
            [
                dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(scheduler_file),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())["address"]
        processes.append(
            subprocess.Popen(
                [dask, "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        out = tmp_path / "out"
        batch = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "imucal_cli.cli",
                "batch",
                *map(str, copies),
                "-c",
                str(root / "config.yaml"),
                "--out-dir",
                str(out),
                "--scheduler",
                address,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (
            out.is_dir() and len(list(out.glob("c*.yaml"))) >= 2
        ):
            time.sleep(0.05)
        processes[0].send_signal(signal.SIGKILL)
        _, stderr = batch.communicate(timeout=120)
    finally:
        for process in reversed(processes):
            process.kill()
            process.wait(timeout=30)
    assert batch.returncode == 1, stderr
    assert "Traceback" not in stderr and "ERROR" not in stderr, stderr[-3000:]
    rows = {Path(r["log"]).name: r for r in _rows(out)}
    failed = [log for log, r in rows.items() if r["status"] == "failed"]
    assert failed and all(
        "scheduler" in rows[log]["error"] and "lost" in rows[log]["error"] for log in failed
    )
    assert all(not (out / log.replace(".mcap", ".yaml")).exists() for log in failed)


def test_thresholds_without_truth_or_reference_are_refused(fleet, tmp_path):
    """A threshold with nothing to compare against did nothing (exit 0); a negative one was
    accepted. Both exit 2 naming the option, before any work."""
    root, logs = fleet
    base = [
        "batch",
        str(logs[0]),
        "-c",
        str(root / "config.yaml"),
        "--out-dir",
        str(tmp_path / "out"),
    ]
    result = runner.invoke(app, [*base, "--max-rotation-deg", "0.0001"])
    assert (
        result.exit_code == 2
        and "--max-rotation-deg" in result.stderr
        and "--truth-dir or --reference" in result.stderr
    )
    assert not (tmp_path / "out").exists()
    result = runner.invoke(app, [*base, "--truth-dir", str(root), "--max-translation-m", "-1"])
    assert result.exit_code == 2 and "--max-translation-m" in result.stderr


def test_failures_name_what_failed(fleet, tmp_path):
    """A batch JUnit failure names the threshold exceeded (as evaluate's do), a log without a
    truth file says so (it said 'no entry for sensor'), and evaluate's table marks each row over
    a threshold (issue 32, item 7)."""
    root, logs = fleet
    truths = tmp_path / "truths"
    truths.mkdir()
    (truths / f"{logs[0].stem}.truth.yaml").write_text(
        (root / f"{logs[0].stem}.truth.yaml").read_text()
    )
    out = tmp_path / "out"
    result = runner.invoke(
        app,
        [
            "batch",
            str(logs[0]),
            str(logs[1]),
            "-c",
            str(root / "config.yaml"),
            "--out-dir",
            str(out),
            "--truth-dir",
            str(truths),
            "--max-rotation-deg",
            "0.000001",
            "--junit",
            str(tmp_path / "j.xml"),
        ],
    )
    assert result.exit_code == 1, result.output
    failures = [f.get("message") for f in ET.parse(tmp_path / "j.xml").getroot().iter("failure")]
    over = [m for m in failures if "rotation_error_deg" in m]
    assert over and all("> --max-rotation-deg 1e-06" in m for m in over)
    assert any("no such truth file for this log" in m for m in failures)
    estimate = out / f"{logs[0].stem}.yaml"
    shown = runner.invoke(
        app,
        [
            "evaluate",
            str(estimate),
            str(truths / f"{logs[0].stem}.truth.yaml"),
            "--max-rotation-deg",
            "0.000001",
        ],
    )
    assert shown.exit_code == 1
    assert shown.stdout.count("rotation deg > 1e-06") == 3  # two sensors and their pair
    assert "fail: 3 over a threshold" in shown.stdout


def test_absolute_manifest_paths_give_flat_outputs_and_full_paths(six, tmp_path):
    """A manifest of absolute paths: each output is DIR/STEM.yaml (it was nested under the
    paths' folders), and the summary keeps each log's full path (issue 32, item 6)."""
    manifest = tmp_path / "absolute.csv"
    lines = (six / "drives.csv").read_text().splitlines()
    manifest.write_text(
        "\n".join(
            [lines[0], *(",".join(str(six / v) for v in line.split(",")) for line in lines[1:]), ""]
        )
    )
    out = tmp_path / "out"
    result = runner.invoke(app, ["batch", "--manifest", str(manifest), "--out-dir", str(out)])
    assert result.exit_code in (0, 1), result.output
    assert sorted(p.name for p in out.glob("*.yaml")) == [
        "2026-11-01_drive.yaml",
        "2026-11-02_drive.yaml",
        "drive2.yaml",
        "drive3.yaml",
        "drive4.yaml",
        "drive5.yaml",
    ]
    assert not [p for p in out.iterdir() if p.is_dir()]
    assert {r["log"] for r in _rows(out)} == {str(six / line.split(",")[0]) for line in lines[1:]}


def test_a_batch_with_a_config_that_leaves_transforms_out_reads_each_logs_tf(tmp_path):
    """A config naming only topics and frames: each log's /tf_static gives its transforms (a
    vehicle per log); a log without them is that log's failed row, naming the key."""
    import csv

    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=60.0, seed=4, tf_static=True)
    )
    with_tf = write_imu_log(
        tmp_path / "a.mcap", "mcap", drive.topics(), tf_static=drive.static_transforms()
    )
    without = write_imu_log(tmp_path / "b.mcap", "mcap", drive.topics())
    full = drive.config_document()
    minimal = {
        "base": {k: full["base"][k] for k in ("topic", "frame", "grade")},
        "sensors": {
            n: {k: s[k] for k in ("imu_topic", "lidar_frame", "grade")}
            for n, s in full["sensors"].items()
        },
    }
    write_document(tmp_path / "min.yaml", minimal)
    out = tmp_path / "out"
    result = runner.invoke(
        app,
        [
            "batch",
            str(with_tf),
            str(without),
            "-c",
            str(tmp_path / "min.yaml"),
            "--out-dir",
            str(out),
        ],
    )
    assert result.exit_code == 1, result.output  # the log without transforms fails
    rows = list(csv.DictReader((out / "summary.csv").open()))
    by_log = {}
    for row in rows:
        by_log.setdefault(Path(row["log"]).name, []).append(row)
    assert {r["status"] for r in by_log["a.mcap"]} == {"ok"}
    (failed,) = by_log["b.mcap"]
    assert failed["status"] == "failed" and "T_imu_lidar: missing required key" in failed["error"]


def test_a_used_out_dir_is_refused_naming_every_file_it_would_replace(fleet, tmp_path):
    """Outputs of an earlier batch are not replaced without --force; the message names the
    files (up to three, then a count), not one of them."""
    root, logs = fleet
    out = tmp_path / "out"
    out.mkdir()
    taken = [out / "d1.yaml", out / "d2.yaml", out / "summary.csv", out / "summary.json"]
    for path in taken:
        path.write_text("earlier\n")
    result = _run(root, logs[:2], out)
    assert result.exit_code == 2, result.output
    message = " ".join(result.stderr.split())
    assert "these 4 files" in message and "and 1 more" in message
    assert sum(str(path) in message for path in taken) == 3
    assert all(path.read_text() == "earlier\n" for path in taken)
