"""Damaged logs: every intact message is recovered, bit-exact, and what was lost is said."""

from __future__ import annotations

import shutil
import struct
import time
import tracemalloc

import numpy as np
import pytest
from conftest import log_name
from recorder import with_terminal_sigint
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.io.logs import open_log
from imucal_cli.reading import read_imu
from imucal_cli.sim.writers import FORMATS, write_imu_log

runner = CliRunner()


@pytest.fixture(scope="module")
def logs(tmp_path_factory, short_drive):
    """The short drive in every format, and its messages as read from the intact logs."""
    root = tmp_path_factory.mktemp("faults")
    out = {}
    for fmt in FORMATS:
        (root / fmt).mkdir()
        log = write_imu_log(root / fmt / log_name(fmt, "d"), fmt, short_drive.topics())
        topics = list(short_drive.topics())
        out[fmt] = (log, topics, read_imu(log, topics))
    return out


def _storage(log):
    """The file holding the messages (the storage file of a rosbag2 directory)."""
    if log.is_dir():
        return next(p for p in log.iterdir() if p.suffix in (".db3", ".mcap"))
    return log


def _copy(log, name):
    target = log.parent / name
    if log.is_dir():
        shutil.copytree(log, target)
    else:
        target = target.with_suffix(log.suffix)
        shutil.copy(log, target)
    return target


def _assert_subset_exact(full, got):
    """Every recovered sample is the written one, bit for bit."""
    for topic, read in got.items():
        ref = full[topic].stream
        index = np.searchsorted(ref.t_ns, read.stream.t_ns)
        assert np.all(index < len(ref.t_ns))
        assert np.array_equal(ref.t_ns[index], read.stream.t_ns), topic
        assert ref.gyro[index].tobytes() == read.stream.gyro.tobytes()
        assert ref.accel[index].tobytes() == read.stream.accel.tobytes()


#: The containers a recorder killed mid-write leaves readable up to the cut (SQLite's pages
#: are not written in log order: a cut-off .db3 is damage that `sqlite3 .recover` handles).
CUT_READABLE = [f for f in FORMATS if f != "rosbag2-sqlite3"]


@pytest.mark.parametrize("fraction", [0.5, 0.9])
@pytest.mark.parametrize("fmt", CUT_READABLE)
def test_cut_off_log_keeps_the_messages_before_the_cut(logs, fmt, fraction):
    log, topics, full = logs[fmt]
    cut = _copy(log, f"cut{int(fraction * 100)}")
    storage = _storage(cut)
    data = storage.read_bytes()
    storage.write_bytes(data[: int(len(data) * fraction)])
    losses = []
    got = read_imu(cut, topics, losses=losses)
    _assert_subset_exact(full, got)
    recovered = sum(len(r.stream) for r in got.values())
    total = sum(len(r.stream) for r in full.values())
    # Compressed chunks hold the messages evenly: what is before the cut is about `fraction`
    # of them; one partly written chunk and the headers (a few per cent here) may be lost.
    assert recovered >= (fraction - 0.05) * total, (recovered, total)
    assert recovered < total
    assert losses, "a cut-off log must say what it lost"


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1"])
def test_corrupt_chunk_is_skipped_and_counted_exactly(logs, fmt):
    log, topics, full = logs[fmt]
    bad = _copy(log, "corrupt")
    with open_log(log) as reader:
        assert reader.format_name in ("mcap", "rosbag1")
    data = bytearray(bad.read_bytes())
    # damage the middle of the file: inside the compressed data of a chunk
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)
    bad.write_bytes(bytes(data))
    losses = []
    got = read_imu(bad, topics, losses=losses)
    _assert_subset_exact(full, got)
    lost = sum(len(full[t].stream) - len(got[t].stream) for t in topics)
    assert lost > 0 and len(losses) >= 1
    counted = sum(sum(x.messages.values()) for x in losses if x.messages)
    if counted:  # from the container's index: exact
        assert counted == lost


def test_rosbag1_without_index_is_read_whole(logs):
    log, topics, full = logs["rosbag1"]
    bag = _copy(log, "noindex")
    data = bytearray(bag.read_bytes())
    # the bag header record's index_pos field: what a recorder killed before closing leaves (0)
    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = struct.unpack_from("<Q", data, at)[0]
    data[at : at + 8] = struct.pack("<Q", 0)
    bag.write_bytes(bytes(data[:index_pos]))
    got = read_imu(bag, topics)
    _assert_subset_exact(full, got)
    assert all(len(got[t].stream) == len(full[t].stream) for t in topics)


def test_cut_off_sqlite3_storage_is_one_error_naming_the_bag_and_the_repair(logs):
    from imucal_cli.errors import LogError

    log, topics, _ = logs["rosbag2-sqlite3"]
    cut = _copy(log, "cut_sqlite")
    storage = _storage(cut)
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    with pytest.raises(LogError) as caught:
        read_imu(cut, topics)
    assert str(cut) in str(caught.value) and ".recover" in str(caught.value)


@pytest.mark.parametrize("damage", ["missing", "broken"])
def test_rosbag2_sqlite3_without_usable_metadata_says_reindex(logs, damage):
    from imucal_cli.errors import LogError

    log, topics, _ = logs["rosbag2-sqlite3"]
    copy = _copy(log, f"meta_sqlite_{damage}")
    if damage == "missing":
        (copy / "metadata.yaml").unlink()
    else:
        (copy / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: [")
    with pytest.raises(LogError) as caught:
        read_imu(copy, topics)
    message = str(caught.value)
    assert str(copy) in message and "ros2 bag reindex" in message
    assert ("no metadata.yaml" if damage == "missing" else "does not read") in message


@pytest.mark.parametrize("fmt", ["rosbag2-mcap"])
@pytest.mark.parametrize("damage", ["missing", "broken"])
def test_rosbag2_without_usable_metadata_reads_the_storage(logs, fmt, damage):
    log, topics, full = logs[fmt]
    copy = _copy(log, f"meta_{damage}")
    if damage == "missing":
        (copy / "metadata.yaml").unlink()
    else:
        (copy / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: [")
    got = read_imu(copy, topics)
    _assert_subset_exact(full, got)
    assert all(len(got[t].stream) == len(full[t].stream) for t in topics)


def test_calibrate_goes_on_after_a_cut_and_stops_when_too_little_remains(
    logs, tmp_path, short_drive
):
    from imucal_cli.documents import write_document

    log = logs["mcap"][0]
    config = tmp_path / "c.yaml"
    write_document(config, short_drive.config_document())
    for fraction, code in ((0.9, 0), (0.02, 2)):
        cut = _copy(log, f"cli{fraction}")
        data = cut.read_bytes()
        cut.write_bytes(data[: int(len(data) * fraction)])
        out = tmp_path / f"e{fraction}.yaml"
        result = runner.invoke(app, ["calibrate", str(cut), "-c", str(config), "-o", str(out)])
        assert result.exit_code == code, result.output
        assert "Traceback" not in result.output
        assert str(cut) in result.stderr
        if code == 0:
            assert "not read" in result.stderr and out.exists()
        else:
            assert not out.exists() and len(result.stderr.strip().splitlines()) == 1


def _with(stream, gyro=None, accel=None, t_ns=None):
    from imucal_cli.types import ImuStream

    return ImuStream(
        stream.t_ns if t_ns is None else t_ns,
        stream.gyro if gyro is None else gyro,
        stream.accel if accel is None else accel,
        stream.frame_id,
    )


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1"])
def test_non_finite_and_clipped_samples_are_dropped_and_counted(tmp_path, short_drive, fmt):
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    gyro, accel = data.stream.gyro.copy(), data.stream.accel.copy()
    gyro[[10, 500]] = np.nan
    accel[700, 2] = np.inf
    accel[900, 0] = -np.inf
    gyro[1000:1006, 1] = 4.3633  # 250 deg/s: a part at the end of its range, six samples
    accel[1500:1503, 0] = -2 * 9.80665  # a +-2 g part, three samples
    topics[name] = TopicData(_with(data.stream, gyro, accel), data.log_time_ns)
    log = write_imu_log(tmp_path / log_name(fmt, "d"), fmt, topics)
    from imucal_cli.reading import ImuBatches

    reader = ImuBatches(log, list(topics))
    kept = [t for topic, t, *_ in reader if topic == name]
    stats = reader.stats[name]
    assert stats.non_finite == 4
    assert stats.saturated == 9
    dropped = set(
        data.stream.t_ns[[10, 500, 700, 900, *range(1000, 1006), *range(1500, 1503)]].tolist()
    )
    got = set(np.concatenate(kept).tolist())
    assert not got & dropped
    assert len(got) == len(data.stream) - 13
    # the other topics (the same motion, no clipping) lose nothing
    for other in topics:
        if other != name:
            assert reader.stats[other].saturated == 0 and reader.stats[other].non_finite == 0


def test_clock_jump_is_counted(tmp_path, short_drive):
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = "/gnss/imu"
    data = topics[name]
    t = data.stream.t_ns.copy()
    t[1000:] += 300 * 10**9  # the clock leaps five minutes
    topics[name] = TopicData(_with(data.stream, t_ns=t), data.log_time_ns)
    log = write_imu_log(tmp_path / "j.mcap", "mcap", topics)
    reader = ImuBatches(log, list(topics))
    for _ in reader:
        pass
    assert reader.stats[name].clock_jumps == 1
    assert all(reader.stats[t].clock_jumps == 0 for t in topics if t != name)


def test_sensor_on_another_clock_exits_2_with_the_measured_offset(tmp_path, short_drive):
    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    boot = data.stream.t_ns - data.stream.t_ns[0] + 12_345_000_000  # stamped from power-on
    topics[name] = TopicData(_with(data.stream, t_ns=boot), data.log_time_ns)
    log = write_imu_log(tmp_path / "p.mcap", "mcap", topics)
    config = tmp_path / "c.yaml"
    write_document(config, short_drive.config_document())
    out = tmp_path / "e.yaml"
    result = runner.invoke(app, ["calibrate", str(log), "-c", str(config), "-o", str(out)])
    assert result.exit_code == 2, result.output
    line = result.stderr.strip()
    assert (
        len(line.splitlines()) == 1
        and str(log) in line
        and name in line
        and "max_time_offset_s" in line
    )
    expected = (int(boot[0]) - int(data.stream.t_ns[0])) * 1e-9
    measured = float(line.split("stamps are ")[1].split(" s")[0])
    assert measured == pytest.approx(expected, abs=0.05)
    assert not out.exists()


@pytest.mark.parametrize("rate", [100.0, 200.0, 400.0])
def test_sensor_rates_up_to_400_hz(tmp_path, rate):
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(
        DriveOptions(scenario="aggressive", duration_s=40.0, seed=3, lidar_rate_hz=rate)
    )
    log = write_imu_log(tmp_path / "r.mcap", "mcap", drive.topics())
    from imucal_cli.documents import write_document

    config = tmp_path / "c.yaml"
    write_document(config, drive.config_document())
    truth = tmp_path / "t.yaml"
    write_document(truth, drive.truth_document())
    out = tmp_path / "e.json"
    result = runner.invoke(app, ["calibrate", str(log), "-c", str(config), "-o", str(out)])
    assert result.exit_code == 0, result.output
    result = runner.invoke(
        app,
        [
            "evaluate",
            str(out),
            str(truth),
            "--max-rotation-deg",
            "0.1",
            "--max-translation-m",
            "0.03",
        ],
    )
    assert result.exit_code == 0, result.output


def test_gap_is_counted_and_windows_across_it_are_not_used(tmp_path, short_drive):
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    t = data.stream.t_ns
    keep = (t < t[0] + 8 * 10**9) | (t > t[0] + 11 * 10**9)  # 3 s without data
    from imucal_cli.types import ImuStream

    topics[name] = TopicData(
        ImuStream(t[keep], data.stream.gyro[keep], data.stream.accel[keep], data.stream.frame_id),
        data.log_time_ns[keep],
    )
    log = write_imu_log(tmp_path / "g.mcap", "mcap", topics)
    reader = ImuBatches(log, list(topics))
    for _ in reader:
        pass
    assert reader.stats[name].gaps == 1
    assert all(reader.stats[o].gaps == 0 for o in topics if o != name)
    from imucal_cli.api import segments
    from imucal_cli.config import load_config
    from imucal_cli.documents import write_document

    write_document(tmp_path / "c.yaml", short_drive.config_document())
    config = load_config(tmp_path / "c.yaml")
    streamed = segments(log, config)
    sensor = next(s.name for s in config.sensors if s.imu_topic == name)
    windows = streamed.windows[sensor]
    gap = (8.0, 11.0)
    t_ref = (streamed.t_ref_ns - int(t[0])) * 1e-9
    for w in windows:
        start, end = w.start_s + t_ref, w.end_s + t_ref
        if start < gap[1] and end > gap[0]:
            assert not w.valid
    assert any(w.valid for w in windows)


def test_damaged_stamp_runs_and_absurd_values_are_dropped_and_counted(tmp_path, short_drive):
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim.writers import TopicData
    from imucal_cli.types import ImuStream

    topics = short_drive.topics()
    name = "/gnss/imu"
    data = topics[name]
    t = data.stream.t_ns.copy()
    t[700:740] -= 15 * 365 * 86400 * 10**9  # a run of 40 stamps 15 years off, then back
    t[1200] += 10**18  # one stamp decades ahead
    gyro = data.stream.gyro.copy()
    gyro[300] = [1e300, 0.0, 0.0]  # finite, but no IMU measures it
    raw = ImuStream.__new__(ImuStream)
    for key, value in (
        ("t_ns", t),
        ("gyro", gyro),
        ("accel", data.stream.accel),
        ("frame_id", data.stream.frame_id),
    ):
        object.__setattr__(raw, key, value)
    topics[name] = TopicData(raw, data.log_time_ns)
    log = write_imu_log(tmp_path / "s.mcap", "mcap", topics)
    reader = ImuBatches(log, list(topics))
    kept = np.concatenate([st for topic, st, *_ in reader if topic == name])
    stats = reader.stats[name]
    assert stats.stamp_outliers == 41 and stats.implausible == 1
    assert len(kept) == len(t) - 42
    assert np.all(np.abs(np.diff(np.sort(kept))) < 10**9)  # what is left is one clock, no leaps


def test_wrong_message_type_exits_2_naming_both_types(tmp_path, short_drive):
    from conftest import DATA

    from imucal_cli.documents import write_document

    document = short_drive.config_document()
    document["base"]["topic"] = "/imu/data"
    first = next(iter(document["sensors"]))
    document["sensors"] = {first: dict(document["sensors"][first], imu_topic="/chatter")}
    write_document(tmp_path / "c.yaml", document)
    log = DATA / "ros2_mcap_ros2_writer.mcap"
    result = runner.invoke(
        app, ["calibrate", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(tmp_path / "e.yaml")]
    )
    assert result.exit_code == 2
    line = result.stderr.strip()
    assert len(line.splitlines()) == 1
    assert (
        str(log) in line
        and "/chatter" in line
        and "std_msgs/msg/String" in line
        and "sensor_msgs/msg/Imu" in line
    )
    assert not (tmp_path / "e.yaml").exists()


def test_ctrl_c_leaves_no_partial_file_and_keeps_the_old_one(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(DriveOptions(scenario="urban", duration_s=900.0, seed=2, sensors=4))
    log = write_imu_log(tmp_path / "long.mcap", "mcap", drive.topics())
    write_document(tmp_path / "c.yaml", drive.config_document())
    out = tmp_path / "e.yaml"
    out.write_text("previous: calibration\n")
    process = subprocess.Popen(
        with_terminal_sigint(
            [
                sys.executable,
                "-m",
                "imucal_cli.cli",
                "calibrate",
                str(log),
                "-c",
                str(tmp_path / "c.yaml"),
                "-o",
                str(out),
            ]
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )

    # interrupted once it has the log open (the command, or the child process it reads in):
    # seconds of work remain, however fast the machine (a fixed delay raced the end of the work)
    def opened(pid: str) -> bool:
        try:
            return os.getpgid(int(pid)) == process.pid and any(
                os.readlink(f"/proc/{pid}/fd/{fd}") == str(log)
                for fd in os.listdir(f"/proc/{pid}/fd")
            )
        except OSError:
            return False

    def reading() -> bool:
        return any(opened(pid) for pid in os.listdir("/proc") if pid.isdigit())

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and process.poll() is None and not reading():
        time.sleep(0.005)
    time.sleep(0.1)
    os.killpg(process.pid, signal.SIGINT)  # what Ctrl-C sends: the whole process group
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert b"Traceback" not in stderr and b"interrupted" in stderr
    assert out.read_text() == "previous: calibration\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "c.yaml",
        "e.yaml",
        "long.mcap",
    ]  # no temp files left
    deadline = time.monotonic() + 10  # and no process of its group left
    while time.monotonic() < deadline:
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        raise AssertionError("a child of the interrupted command is still running")


def test_damaged_stamp_run_after_a_clock_jump_is_still_found():
    from imucal_cli.reading import _stamp_outliers

    t = np.arange(1000, dtype=np.int64) * 10_000_000 + 1_700_000_000 * 10**9
    t[300:] += 300 * 10**9  # a real jump: the clock stays moved
    t[600:620] -= 15 * 365 * 86400 * 10**9  # then a damaged run that comes back
    out = _stamp_outliers(t)
    assert np.flatnonzero(out).tolist() == list(range(600, 620))


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1"])
def test_groups_of_any_size_read_the_same_and_lose_the_same_chunks(logs, fmt, monkeypatch):
    """Chunks decoded in groups (one chunk each, or many): the same samples, bit for bit, and
    the same losses in the same order."""
    from imucal_cli.io import mcap_log, rosbag1

    log, topics, _ = logs[fmt]
    bad = _copy(log, "corrupt-twice")
    data = bytearray(bad.read_bytes())
    for at in (len(data) // 3, 2 * len(data) // 3):  # two chunks damaged, far apart
        data[at : at + 64] = bytes(64)
    bad.write_bytes(bytes(data))
    results = []
    for small in (True, False):
        monkeypatch.setattr(mcap_log, "GROUP_BYTES", 1 if small else 64 << 20)
        monkeypatch.setattr(rosbag1, "GROUP_CHUNKS", 1 if small else 1000)
        losses = []
        got = read_imu(bad, topics, losses=losses)
        results.append(
            (
                {
                    t: (
                        r.stream.t_ns.tobytes(),
                        r.stream.gyro.tobytes(),
                        r.stream.accel.tobytes(),
                        r.stats.to_dict(),
                    )
                    for t, r in got.items()
                },
                [(x.offset, x.reason, x.messages) for x in losses],
            )
        )
    assert len(results[0][1]) >= 2
    assert results[1] == results[0]


def test_a_lively_sensor_past_the_saturation_floors_loses_nothing(tmp_path, short_drive):
    """Values past the clipping floors (2 rad/s, 1.5 g) that never sit at their extreme for a
    run are measurements, kept whole; a run at the extreme among them is still dropped."""
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    n = len(data.stream)
    gyro, accel = data.stream.gyro.copy(), data.stream.accel.copy()
    spikes = np.arange(50, n, 97)
    accel[spikes, 2] += np.linspace(8.0, 9.0, len(spikes))  # past 1.5 g, each value once
    gyro[spikes[::2], 0] = np.linspace(2.1, 2.6, len(spikes[::2]))  # past 2 rad/s, each once
    k = spikes[-1]
    accel[k : k + 2, 2] = 30.0  # the batch's extreme twice in a row: no run
    topics[name] = TopicData(_with(data.stream, gyro, accel), data.log_time_ns)
    log = write_imu_log(tmp_path / "lively.mcap", "mcap", topics)
    reader = ImuBatches(log, list(topics))
    kept = np.concatenate([t for topic, t, *_ in reader if topic == name])
    assert reader.stats[name].saturated == 0 and len(kept) == n

    accel[k + 2, 2] = 30.0  # now three in a row at the extreme
    topics[name] = TopicData(_with(data.stream, gyro, accel), data.log_time_ns)
    log = write_imu_log(tmp_path / "clipped.mcap", "mcap", topics)
    reader = ImuBatches(log, list(topics))
    kept = np.concatenate([t for topic, t, *_ in reader if topic == name])
    assert reader.stats[name].saturated == 3 and len(kept) == n - 3


def _ros1_chunks(bag):
    from imucal_cli.io.rosbag1 import Ros1Log

    with Ros1Log(bag) as reader:
        return reader.chunks


def test_rosbag1_index_pointing_past_its_chunk_loses_that_chunk_only(logs):
    """An index entry whose offset lies past its chunk's end: only that chunk is lost (its
    messages counted from the bag's index), the rest read bit for bit."""
    from imucal_cli.io.rosbag1 import _U32, _record

    log, topics, full = logs["rosbag1"]
    bad = _copy(log, "index-past-end")
    data = bytearray(bad.read_bytes())
    chunk_pos, per_conn = _ros1_chunks(bad)[len(_ros1_chunks(bad)) // 2]
    fields, _, _, after = _record(bytes(data), chunk_pos)  # the chunk, then its index data
    _, start, nbytes, _ = _record(bytes(data), after)
    entry = start + (nbytes // 12 // 2) * 12  # (sec, nsec, offset): the offset of its middle entry
    struct.pack_into("<I", data, entry + 8, _U32.unpack(fields["size"])[0] + 100)
    bad.write_bytes(bytes(data))
    losses = []
    got = read_imu(bad, topics, losses=losses)
    _assert_subset_exact(full, got)
    assert [x.offset for x in losses] == [chunk_pos] and "past the chunk's end" in losses[0].reason
    lost = sum(len(full[t].stream) - len(got[t].stream) for t in topics)
    assert lost == sum(losses[0].messages.values()) == sum(per_conn.values())


@pytest.mark.parametrize("claimed", ["huge", "small"])
def test_rosbag1_chunk_claiming_a_wrong_size_is_lost_alone(logs, claimed):
    """A chunk header whose decompressed size is damaged (past what LZ4 can expand to, or too
    small for its records): that chunk is lost, counted from its index, before any room is
    made for it; the others are read bit for bit."""
    log, topics, full = logs["rosbag1"]
    bad = _copy(log, f"size-{claimed}")
    data = bytearray(bad.read_bytes())
    chunk_pos = _ros1_chunks(bad)[1][0]
    at = data.index(b"size=", chunk_pos) + len(b"size=")
    size = struct.unpack_from("<I", data, at)[0]
    struct.pack_into("<I", data, at, 0xFFFFFFF0 if claimed == "huge" else size // 2)
    bad.write_bytes(bytes(data))
    losses = []
    tracemalloc.start()  # numpy's buffers are traced too
    try:
        got = read_imu(bad, topics, losses=losses)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 256 << 20  # no room made for the claimed 4 GiB
    _assert_subset_exact(full, got)
    assert [x.offset for x in losses] == [chunk_pos]
    assert (
        "claims to decompress to 4294967280" if claimed == "huge" else "decompressed to more than"
    ) in losses[0].reason
    assert (
        sum(len(full[t].stream) - len(got[t].stream) for t in topics)
        == sum(losses[0].messages.values())
        > 0
    )


def test_mcap_message_index_pointing_past_its_chunk_loses_that_chunk_only(logs):
    """A message index entry whose offset lies past its chunk's end: the group's check finds
    it, and only that chunk is lost (counted from its index), the rest read bit for bit."""
    from imucal_cli.io.mcap_log import McapLog

    log, topics, full = logs["mcap"]
    bad = _copy(log, "mcap-index-past-end")
    data = bytearray(bad.read_bytes())
    with McapLog(bad) as reader:
        chunk = list(reader._chunks)[2]
    at = next(iter(chunk.message_index_offsets.values()))
    assert data[at] == 0x07  # a message index record: op, length, channel, then its entries
    (nbytes,) = struct.unpack_from("<I", data, at + 1 + 8 + 2)
    entry = at + 1 + 8 + 2 + 4 + (nbytes // 16 // 2) * 16  # (log time, offset) of its middle one
    struct.pack_into("<Q", data, entry + 8, chunk.uncompressed_size + 100)
    bad.write_bytes(bytes(data))
    losses = []
    got = read_imu(bad, topics, losses=losses)
    _assert_subset_exact(full, got)
    assert [x.offset for x in losses] == [
        chunk.chunk_start_offset
    ] and "past the chunk's end" in losses[0].reason
    lost = sum(len(full[t].stream) - len(got[t].stream) for t in topics)
    assert lost == sum(losses[0].messages.values()) > 0


def test_a_long_gap_in_one_imu_does_not_confuse_its_units_or_its_clock(tmp_path):
    """A lidar IMU silent for 10 s of a 60 s drive: units and clock offsets are measured where
    every IMU has data (a spline across the gap once read as a gyro in neither unit)."""
    from imucal_cli.api import calibrate
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import TopicData
    from imucal_cli.types import ImuStream

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=7))
    topics = drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    t = data.stream.t_ns
    keep = (t < t[0] + 20 * 10**9) | (t > t[0] + 30 * 10**9)
    topics[name] = TopicData(
        ImuStream(t[keep], data.stream.gyro[keep], data.stream.accel[keep], data.stream.frame_id),
        data.log_time_ns[keep],
    )
    log = write_imu_log(tmp_path / "gap.mcap", "mcap", topics)
    from imucal_cli.documents import write_document

    write_document(tmp_path / "c.yaml", drive.config_document())
    run = calibrate(log, tmp_path / "c.yaml")
    for sensor in run.document()["sensors"].values():
        assert not any("publishes" in w for w in sensor["warnings"])  # no unit conversion made up
    assert run.reading.counts[name]["gaps"] == 1


def test_a_topic_that_stops_is_named_and_the_others_use_the_whole_log(tmp_path):
    """A lidar IMU that stops sending a third of the way in (a driver that died): a warning
    names it, its windows after that are not used, and the other sensor calibrates from the
    whole log (it used to wait for the stopped one, buffering everything)."""
    from imucal_cli.api import calibrate
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import TopicData

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=150.0, seed=4))
    topics = drive.topics()
    stopped = list(topics)[1]
    data = topics[stopped]
    end = data.stream.t_ns[0] + 50 * 10**9
    keep = data.stream.t_ns < end
    topics[stopped] = TopicData(
        data.stream.__class__(
            data.stream.t_ns[keep],
            data.stream.gyro[keep],
            data.stream.accel[keep],
            data.stream.frame_id,
        ),
        data.log_time_ns[keep] if data.log_time_ns is not None else None,
    )
    log = write_imu_log(tmp_path / "d.mcap", "mcap", topics)
    config = tmp_path / "c.yaml"
    write_document(config, drive.config_document())
    run = calibrate(log, config)
    names = {s["imu_topic"]: n for n, s in drive.config_document()["sensors"].items()}
    gone, other = names[stopped], next(n for t, n in names.items() if t != stopped)
    sensors = run.document()["sensors"]
    assert any(stopped in w and "sent nothing from" in w for w in sensors[gone]["warnings"])
    assert not any("sent nothing" in w for w in sensors[other]["warnings"])
    total = sensors[other]["segments"]["total"]
    assert total >= 13  # 150 s in 10 s windows, less the padding at the ends
    assert sensors[gone]["segments"]["total"] == total  # counted alike; its late ones not used
    assert sensors[gone]["segments"]["selected"] <= 5
    assert sensors[other]["status"] == "ok"


def test_a_log_too_short_for_one_window_is_too_little_data_exit_2(tmp_path):
    """5 s of a drive (a log cut after 5 s): exit 2 saying how much data there was and how
    much one window needs (it was exit 0 with every sensor unobservable), the cut's place said
    before the repair hint."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=7))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 5 // 60])
    write_document(tmp_path / "c.yaml", drive.config_document())
    result = runner.invoke(app, ["calibrate", str(cut), "-c", str(tmp_path / "c.yaml")])
    assert result.exit_code == 2, result.output
    line = result.stderr.strip()
    assert (
        len(line.splitlines()) == 1
        and "too little data: the IMUs overlap for" in line
        and "needs" in line
    )
    assert "not read from byte" in line and line.index("not read from byte") < line.index(
        "mcap recover"
    )


def test_follow_runs_the_clock_check_calibrate_runs(tmp_path, short_drive):
    """--follow on a finished log with a sensor on another clock: the same one line and exit 2
    as calibrate (follow mode did not compare the clocks, and swallowed what the last windows
    raised: issue 29's one read loop, in part)."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    topics[name] = TopicData(
        _with(data.stream, t_ns=data.stream.t_ns - data.stream.t_ns[0] + 12_345_000_000),
        data.log_time_ns,
    )
    log = write_imu_log(tmp_path / "p.mcap", "mcap", topics)
    config = tmp_path / "c.yaml"
    write_document(config, short_drive.config_document())
    lines = []
    for extra in ([], ["--follow", "--timeout", "60"]):
        result = runner.invoke(app, ["calibrate", str(log), "-c", str(config), *extra])
        assert result.exit_code == 2, (extra, result.output)
        *talk, error = result.stderr.strip().splitlines()
        assert all(line.startswith("imucal: following ") for line in talk)  # (follow mode)
        lines.append(error)
    assert lines[0] == lines[1] and name in lines[0] and "max_time_offset_s" in lines[0]


def test_windows_that_held_a_clipped_run_the_reader_dropped_are_not_used(tmp_path):
    """A lidar gyro at the end of a 250 deg/s range for three samples: reading drops the run
    (a clipped value is not the motion), and the window that held it is not used, where the
    spline would otherwise interpolate across the hole as if nothing had happened."""
    from imucal_cli.api import calibrate
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import TopicData

    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=90.0, seed=5))
    write_document(tmp_path / "c.yaml", drive.config_document())
    clean = calibrate(
        write_imu_log(tmp_path / "a.mcap", "mcap", drive.topics()), tmp_path / "c.yaml"
    )
    topics = drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    gyro = data.stream.gyro.copy()
    at = int(np.searchsorted(data.stream.t_ns, data.stream.t_ns[0] + 45 * 10**9))
    gyro[at : at + 3, 1] = 4.3633
    topics[name] = TopicData(_with(data.stream, gyro), data.log_time_ns)
    run = calibrate(write_imu_log(tmp_path / "b.mcap", "mcap", topics), tmp_path / "c.yaml")
    assert run.reading.counts[name]["saturated"] == 3
    sensor = next(
        s
        for s in drive.config_document()["sensors"]
        if drive.config_document()["sensors"][s]["imu_topic"] == name
    )
    before = clean.estimates[sensor].windows
    after = run.estimates[sensor].windows
    changed = [i for i, (b, a) in enumerate(zip(before, after, strict=True)) if b.valid != a.valid]
    assert len(changed) >= 1 and all(before[i].valid and not after[i].valid for i in changed)
    t_clip = (data.stream.t_ns[at] - data.stream.t_ns[0]) * 1e-9
    assert all(after[i].start_s - 2.0 < t_clip < after[i].end_s + 2.0 for i in changed)


def test_the_read_loop_keeps_no_clipped_stamps_nobody_asked_for(tmp_path, short_drive):
    """``biases`` reads with no use for the stamps of dropped clipped samples: the read loop
    takes them all the same, so a log that clips throughout does not pile them up."""
    from imucal_cli.config import parse_config
    from imucal_cli.pipeline import read_log
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim.writers import TopicData

    topics = short_drive.topics()
    name = next(t for t in topics if t != "/gnss/imu")
    data = topics[name]
    gyro = data.stream.gyro.copy()
    gyro[100:103, 1] = 4.3633  # a run at the end of a 250 deg/s range
    topics[name] = TopicData(_with(data.stream, gyro), data.log_time_ns)
    log = write_imu_log(tmp_path / "clipped.mcap", "mcap", topics)
    config = parse_config(short_drive.config_document(), "sim.config.yaml")
    reader = ImuBatches(log, list(topics))
    read_log(reader, config, lambda *_: None, clocks=False)
    assert reader.stats[name].saturated == 3
    assert all(not stamps for stamps in reader.clipped.values())


def _with_nan(data, fraction, seed=0):
    """A topic's samples with ``fraction`` of them NaN (a driver's glitch)."""
    from dataclasses import replace as replaced

    from imucal_cli.sim.writers import TopicData

    rng = np.random.default_rng(seed)
    gyro = data.stream.gyro.copy()
    gyro[rng.uniform(size=len(gyro)) < fraction] = np.nan
    return TopicData(replaced(data.stream, gyro=gyro), data.log_time_ns)


def test_dropped_samples_are_said_first_and_biases_says_its_warnings_on_stderr(
    tmp_path, short_drive
):
    """30% NaN on a sensor: its first warning blamed the model (residuals, units, a moving
    mount), the dropped samples came third; biases put them in its document only. The cause
    is said first, and biases -o says its warnings on stderr as calibrate does."""
    import json

    from imucal_cli.documents import write_document

    topics = short_drive.topics()
    sensor_topic = list(topics)[1]
    topics[sensor_topic] = _with_nan(topics[sensor_topic], 0.3)
    log = write_imu_log(tmp_path / "d.mcap", "mcap", topics)
    write_document(tmp_path / "c.yaml", short_drive.config_document())
    out = tmp_path / "e.json"
    done = runner.invoke(
        app, ["calibrate", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(out)]
    )
    assert done.exit_code == 0, done.output
    sensor = next(
        s for s in json.loads(out.read_text())["sensors"].values() if s["imu_topic"] == sensor_topic
    )
    assert "not finite" in sensor["warnings"][0], sensor["warnings"]
    biases = runner.invoke(
        app, ["biases", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(tmp_path / "b.yaml")]
    )
    assert biases.exit_code == 0 and "not finite" in biases.stderr, biases.stderr


def test_init_says_a_bounded_number_of_lines_whatever_the_log_declares(tmp_path, short_drive):
    """A log declaring 60,000 IMU channels made init print two lines per missing transform
    (119,998 lines on stderr): each kind is said for 20 sensors, then counted."""
    topics = short_drive.topics()
    data = next(iter(topics.values()))
    for k in range(30):
        topics[f"/lidar/extra_{k}/imu"] = data
    log = write_imu_log(tmp_path / "d.mcap", "mcap", topics)
    made = runner.invoke(app, ["init", str(log), "--base", next(iter(topics))])
    assert made.exit_code == 0, made.output
    lines = made.stderr.splitlines()
    assert len(lines) == 21 and lines[-1] == "imucal: ... and 44 more placeholders", lines[-3:]


def test_sigterm_during_simulate_leaves_no_partial_log_and_exits_143(tmp_path):
    """SIGTERM (what a CI runner sends at its timeout) left a hidden .NAME.XXXX.partial/
    folder of up to 677 MB (7 of 7 runs): it now ends as a Ctrl-C does."""
    import signal
    import subprocess
    import sys

    argv = [sys.executable, "-m", "imucal_cli.cli", "simulate", str(tmp_path / "long.mcap")]
    process = subprocess.Popen(
        [*argv, "--duration", "900", "--sensors", "4"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(tmp_path.iterdir()):
        time.sleep(0.01)  # (the partial log's folder is made: the write has begun)
    time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 143, stderr
    assert b"terminated" in stderr and b"Traceback" not in stderr
    assert list(tmp_path.iterdir()) == []
