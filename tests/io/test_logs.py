"""Readers: round trips through every writer, and the stamp bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest

from imucal_cli.errors import LogError
from imucal_cli.inspection import summarize_log
from imucal_cli.io.logs import open_log
from imucal_cli.reading import read_imu
from imucal_cli.sim.writers import FORMATS, TopicData, write_imu_log
from imucal_cli.types import ImuStream

T0 = 1_700_000_000_000_000_000


def log_name(tmp_path, fmt: str, stem: str = "log"):
    if fmt.startswith("mcap"):
        return tmp_path / f"{stem}.mcap"
    if fmt == "rosbag1":
        return tmp_path / f"{stem}.bag"
    return tmp_path / stem


def random_stream(rng, n: int, period_ns: int, frame: str, offset_ns: int = 0) -> ImuStream:
    t = T0 + offset_ns + np.arange(n, dtype=np.int64) * period_ns
    # full-precision doubles, including tiny and huge magnitudes: the round trip must be bit-exact
    gyro = rng.normal(size=(n, 3)) * np.array([1e-9, 1.0, 1e1])  # every scale an IMU reports
    accel = rng.normal(size=(n, 3)) * 9.81
    return ImuStream(t, gyro, accel, frame)


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_is_bit_exact(tmp_path, fmt):
    rng = np.random.default_rng(1)
    base = random_stream(rng, 300, 10_000_000, "base_link")
    lidar = random_stream(rng, 620, 5_000_000, "lidar_imu", offset_ns=1_234_567)
    topics = {
        "/gnss/imu": TopicData(base, base.t_ns + 2_000_000),
        "/lidar/a/imu": TopicData(lidar, lidar.t_ns + 3_000_000),
    }
    path = write_imu_log(log_name(tmp_path, fmt), fmt, topics)
    reads = read_imu(path, ["/gnss/imu", "/lidar/a/imu"])
    for topic, data in topics.items():
        got = reads[topic]
        assert got.stream.t_ns.tobytes() == data.stream.t_ns.tobytes()
        assert got.stream.gyro.tobytes() == data.stream.gyro.tobytes()
        assert got.stream.accel.tobytes() == data.stream.accel.tobytes()
        assert got.stream.frame_id == data.stream.frame_id
        assert np.array_equal(got.log_time_ns, data.log_time_ns)
        assert got.stats.messages == len(data.stream)
        assert (got.stats.duplicates, got.stats.backwards, got.stats.zero_stamps) == (0, 0, 0)
    with open_log(path) as log:
        infos = log.topics()
        assert {t: i.count for t, i in infos.items()} == {"/gnss/imu": 300, "/lidar/a/imu": 620}
        assert all(i.is_imu for i in infos.values())
        expected_format = {"mcap-ros1": "mcap"}.get(fmt, fmt)
        assert log.format_name == expected_format


@pytest.mark.parametrize("fmt", FORMATS)
def test_out_of_order_duplicate_and_zero_stamps_are_counted(tmp_path, fmt):
    rng = np.random.default_rng(2)
    s = random_stream(rng, 100, 10_000_000, "imu")
    t = s.t_ns.copy()
    t[[40, 41]] = t[[41, 40]]  # one swap: one backwards step in log order
    t[70] = t[69]  # a duplicate stamp
    t[90] = 0  # a zero stamp: log time is used
    log_ns = s.t_ns + 1_000_000
    path = write_imu_log(
        log_name(tmp_path, fmt),
        fmt,
        {"/imu": TopicData(ImuStream(t, s.gyro, s.accel, "imu"), log_ns)},
    )
    got = read_imu(path, ["/imu"])["/imu"]
    assert got.stats.messages == 100
    assert got.stats.zero_stamps == 1
    assert got.stats.duplicates == 1
    assert got.stats.backwards == 1
    assert len(got.stream) == 99
    assert np.all(np.diff(got.stream.t_ns) > 0)
    assert log_ns[90] in got.stream.t_ns  # the zero stamp replaced by its log time
    # sorted back into place: the swapped samples carry their own values
    i40 = np.flatnonzero(got.stream.t_ns == s.t_ns[40])[0]
    assert np.array_equal(got.stream.gyro[i40], s.gyro[41])
    # of the duplicate pair, the first (in log order) is kept
    i69 = np.flatnonzero(got.stream.t_ns == s.t_ns[69])[0]
    assert np.array_equal(got.stream.gyro[i69], s.gyro[69])


def test_inspect_reports_gaps_backwards_duplicates(tmp_path):
    rng = np.random.default_rng(3)
    s = random_stream(rng, 500, 10_000_000, "imu")
    keep = np.ones(500, dtype=bool)
    keep[200:260] = False  # a 0.61 s gap
    t = s.t_ns.copy()
    t[[10, 11]] = t[[11, 10]]
    t[300] = t[299]
    stream = ImuStream(t[keep], s.gyro[keep], s.accel[keep], "imu")
    path = write_imu_log(tmp_path / "g.mcap", "mcap", {"/imu": TopicData(stream, s.t_ns[keep])})
    summary = summarize_log(path)
    (timing,) = summary.topics
    assert summary.t0_ns == T0
    assert timing.count == 440 and timing.backwards == 1 and timing.duplicates == 1
    assert timing.rate_hz == pytest.approx(100.0)
    assert len(timing.gaps) == 1
    start, end = timing.gaps[0]
    assert start == pytest.approx(1.99) and end == pytest.approx(2.60)


def test_missing_path_and_unknown_format(tmp_path):
    with pytest.raises(LogError, match="no such file"):
        open_log(tmp_path / "nope.mcap")
    junk = tmp_path / "junk.dat"
    junk.write_bytes(b"hello world, not a log")
    with pytest.raises(LogError, match="unknown log format") as info:
        open_log(junk)
    assert str(junk) in str(info.value)


@pytest.mark.parametrize("suffix", [".mcap", ".bag"])
def test_garbage_with_log_suffix_is_a_log_error(tmp_path, suffix):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(LogError) as info:
        read_imu(path, ["/imu"])
    assert str(path) in str(info.value)


@pytest.mark.parametrize("seed", range(5))
def test_inspect_timing_streamed_agrees_with_sorting_every_stamp(seed):
    """The streamed clock of ``inspect`` (memory flat in the log's length) gives what sorting
    all the stamps gives: count, span, backwards, duplicates and gaps exactly, the median
    period to its rounding (50 ns once the steps have more than 16384 lengths)."""
    from imucal_cli.inspection import COARSE_NS, REORDER_NS, _Clock, _timing
    from imucal_cli.types import GAP_PERIODS

    rng = np.random.default_rng(seed)
    n = 200_000
    period = int(1e9 / rng.choice([100.0, 200.0, 400.0]))
    jitter = int(rng.choice([0, 300_000]))
    t = np.arange(n, dtype=np.int64) * period + rng.integers(-jitter, jitter + 1, n)
    t[rng.choice(n, 50, replace=False)] += (
        int(rng.integers(20, 200)) * period
    )  # gaps (moved stamps)
    for i in rng.choice(n - 1, 100, replace=False):  # reordered within the reordering window
        t[i], t[i + 1] = t[i + 1], t[i]
    dup = rng.choice(n - 1, 30, replace=False)
    t[dup + 1] = t[dup]
    t = t[t.argsort(kind="stable")] if seed == 0 else t  # one sorted case
    assert 200 * period < REORDER_NS
    clock = _Clock()
    for part in np.array_split(t, 37):
        clock.add(part)
    got = _timing("x", "m", clock, int(t.min()), "header.stamp")
    s = np.sort(t)
    steps = np.diff(s)
    median = float(np.median(steps[steps > 0]))
    gaps = [
        ((a - t.min()) * 1e-9, (b - t.min()) * 1e-9)
        for a, b, d in zip(s[:-1], s[1:], steps, strict=True)
        if d > GAP_PERIODS * median
    ]
    assert got.count == n and got.duration_s == (s[-1] - s[0]) * 1e-9
    assert got.backwards == int(np.count_nonzero(np.diff(t) < 0))
    assert got.duplicates == int(np.count_nonzero(steps == 0))
    assert got.gaps == gaps
    assert abs(1e9 / got.rate_hz - median) <= (COARSE_NS / 2 if jitter else 0.5)


def test_the_same_drive_gives_the_same_windows_and_estimate_from_every_container(tmp_path):
    """sqlite3 storage handed the calibrator 8,192 messages of one topic at a time, a 100 Hz
    topic 82 s ahead of the others: on a drive longer than that the others looked stopped
    ("sent nothing"), windows were dropped, the std inflated. Every container now gives what
    MCAP gives, to the bit."""
    from imucal_cli.api import calibrate
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive

    drive = simulate_drive(DriveOptions(scenario="urban", duration_s=200.0, seed=3))
    write_document(tmp_path / "c.yaml", drive.config_document())
    documents = {}
    for fmt in FORMATS:
        log = write_imu_log(tmp_path / f"d-{fmt}", fmt, drive.topics())
        documents[fmt] = calibrate(log, tmp_path / "c.yaml").document()["sensors"]
    reference = documents["mcap"]
    for fmt, sensors in documents.items():
        for name, sensor in sensors.items():
            expected = reference[name]
            assert sensor["segments"] == expected["segments"], (fmt, name)
            assert sensor["warnings"] == expected["warnings"] == [], (fmt, name)
            assert sensor["T_base_lidar"] == expected["T_base_lidar"], (fmt, name)
            assert sensor["rotation_std_deg"] == expected["rotation_std_deg"], (fmt, name)


def _file_compressed(bag, payload=None):
    """The rosbag2 folder ``bag`` with its storage compressed whole (``compression_mode:
    file``, as ``ros2 bag record --compression-mode file`` writes it), or with ``payload``
    compressed in its place."""
    import yaml
    import zstandard

    metadata = bag / "metadata.yaml"
    document = yaml.safe_load(metadata.read_text())
    info = document["rosbag2_bagfile_information"]
    files = []
    for name in info["relative_file_paths"]:
        storage = bag / name
        data = storage.read_bytes() if payload is None else payload
        (bag / f"{name}.zstd").write_bytes(zstandard.ZstdCompressor().compress(data))
        storage.unlink()
        files.append(f"{name}.zstd")
    info |= {"relative_file_paths": files, "compression_format": "zstd", "compression_mode": "file"}
    metadata.write_text(yaml.safe_dump(document))
    return bag


def test_a_file_compressed_bag_reads_and_a_bomb_is_refused_before_it_is_inflated(tmp_path):
    """rosbags inflates a file-compressed bag whole into TMPDIR: a 130 kB bag wrote 4 GiB there
    (ENOSPC on a small TMPDIR, an empty temp folder left). Each file is now counted
    decompressed first, held to 1000:1 and TMPDIR's room."""
    stream = random_stream(np.random.default_rng(0), 500, 10_000_000, "imu")
    bag = write_imu_log(tmp_path / "bag", "rosbag2-sqlite3", {"/imu": TopicData(stream)})
    (tmp_path / "bomb").mkdir()
    for path in bag.iterdir():
        (tmp_path / "bomb" / path.name).write_bytes(path.read_bytes())
    read = read_imu(_file_compressed(bag), ["/imu"])
    np.testing.assert_array_equal(read["/imu"].stream.t_ns, stream.t_ns)
    bomb = _file_compressed(tmp_path / "bomb", bytes(200 << 20))  # 200 MiB of zeros
    with pytest.raises(LogError, match="decompresses to more than"):
        read_imu(bomb, ["/imu"])


def test_a_sqlite3_bag_in_a_folder_named_with_uri_characters_reads_whole(tmp_path):
    """sqlite3 storage is opened through a URI (read-only): a folder named with ``#``, ``?``
    and a space could not be opened at all ("unable to open database file")."""
    streams = {
        f"/imu{k}": random_stream(np.random.default_rng(k), 3000, 5_000_000, f"imu{k}")
        for k in range(2)
    }
    bag = write_imu_log(
        tmp_path / "bag", "rosbag2-sqlite3", {t: TopicData(s) for t, s in streams.items()}
    )
    named = bag.rename(tmp_path / "run #3? day 2")
    read = read_imu(named, list(streams))
    for topic, stream in streams.items():
        np.testing.assert_array_equal(read[topic].stream.t_ns, stream.t_ns)
        np.testing.assert_array_equal(read[topic].stream.gyro, stream.gyro)
        np.testing.assert_array_equal(read[topic].stream.accel, stream.accel)
    with open_log(named) as log:  # (the counts metadata.yaml gives)
        assert {t: info.count for t, info in log.topics().items()} == dict.fromkeys(streams, 3000)


def test_a_sqlite3_bag_written_under_uri_characters_holds_its_storage_and_nothing_strays(
    tmp_path,
):
    """rosbags writes sqlite3 storage through an unescaped URI: a bag named with ``#`` got a
    metadata.yaml and no database, which went to a file beside its folder (``.run ``)."""
    stream = random_stream(np.random.default_rng(3), 500, 5_000_000, "imu")
    parent = tmp_path / "drives #1"
    parent.mkdir()
    for name in ("run #3? day", "100%25 fine"):
        bag = write_imu_log(parent / name, "rosbag2-sqlite3", {"/imu": TopicData(stream)})
        assert len(list(bag.glob("*.db3"))) == 1
        read = read_imu(bag, ["/imu"])
        np.testing.assert_array_equal(read["/imu"].stream.t_ns, stream.t_ns)
        np.testing.assert_array_equal(read["/imu"].stream.gyro, stream.gyro)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drives #1"]
    assert sorted(p.name for p in parent.iterdir()) == ["100%25 fine", "run #3? day"]


def test_a_rosbag2_whose_storage_is_a_fifo_is_refused_not_waited_for(tmp_path):
    """A rosbag2 folder whose .db3 is a FIFO nobody writes hung forever, silently."""
    import os
    import time

    stream = random_stream(np.random.default_rng(0), 100, 10_000_000, "imu")
    bag = write_imu_log(tmp_path / "bag", "rosbag2-sqlite3", {"/imu": TopicData(stream)})
    storage = next(bag.glob("*.db3"))
    storage.unlink()
    os.mkfifo(storage)
    started = time.monotonic()
    with pytest.raises(LogError, match="not a regular file"):
        read_imu(bag, ["/imu"])
    assert time.monotonic() - started < 5.0


@pytest.mark.parametrize("fmt", ["rosbag2-sqlite3", "rosbag2-mcap"])
def test_a_rosbag2_whose_file_list_is_no_list_is_an_error_naming_the_key(tmp_path, fmt):
    """``relative_file_paths: 7`` in metadata.yaml: one error naming the key, for either
    storage (the sqlite3 one raised a TypeError)."""
    import yaml

    stream = random_stream(np.random.default_rng(0), 100, 10_000_000, "imu")
    bag = write_imu_log(tmp_path / "bag", fmt, {"/imu": TopicData(stream)})
    metadata = bag / "metadata.yaml"
    document = yaml.safe_load(metadata.read_text())
    document["rosbag2_bagfile_information"]["relative_file_paths"] = 7
    metadata.write_text(yaml.safe_dump(document))
    with pytest.raises(LogError, match="relative_file_paths is not a list of file names"):
        read_imu(bag, ["/imu"])
