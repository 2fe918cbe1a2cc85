"""MCAP: the project's conformance files, and IMU logs in every layout the official writer makes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import without_summary
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.reading import read_imu
from imucal_cli.sim.writers import _merged, _msgdef, _Serialized, write_imu_log

runner = CliRunner()
CONFORMANCE = Path(__file__).resolve().parents[3] / "shared" / "conformance" / "mcap"


def _expected() -> dict[str, dict[str, int]]:
    return (
        json.loads((CONFORMANCE / "expected_counts.json").read_text())
        if CONFORMANCE.is_dir()
        else {}
    )


@pytest.mark.skipif(
    not CONFORMANCE.is_dir(),
    reason="the MCAP project's conformance files (kept outside this repository) are not on "
    "this machine",
)
def test_every_conformance_file_lists_the_topics_and_counts_the_mcap_library_reads():
    wrong = []
    for name, counts in _expected().items():
        result = runner.invoke(app, ["inspect", str(CONFORMANCE / name), "--json"])
        got = json.loads(result.stdout)["topics"] if result.exit_code == 0 else result.output
        if result.exit_code != 0 or {t: v["count"] for t, v in got.items()} != counts:
            wrong.append((name, counts, got))
        elif (
            not counts and "warning" in result.stderr
        ):  # a complete file with no messages is not cut off
            wrong.append((name, counts, result.stderr))
    assert not wrong, f"{len(wrong)} of {len(_expected())} files read wrong, first: {wrong[0]}"
    assert len(_expected()) == 255


def _write(path: Path, topics, **options) -> Path:
    """The drive through the official writer with ``options`` (mcap.writer.Writer's)."""
    from mcap.writer import Writer

    msgdef, _ = _msgdef(False)
    blob = _Serialized(topics, False)
    with path.open("wb") as handle:
        writer = Writer(handle, **options)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(
            name="sensor_msgs/msg/Imu", encoding="ros2msg", data=msgdef.encode()
        )
        channels = {
            t: writer.register_channel(topic=t, message_encoding="cdr", schema_id=schema)
            for t in topics
        }
        for log_ns, topic, i in _merged(topics):
            writer.add_message(
                channel_id=channels[topic],
                log_time=log_ns,
                data=blob(topic, i),
                publish_time=log_ns,
            )
        writer.finish()
    return path


@pytest.fixture(scope="module")
def layouts(tmp_path_factory, short_drive):
    from mcap.writer import IndexType

    root = tmp_path_factory.mktemp("layouts")
    topics = short_drive.topics()
    made = {
        "default": _write(root / "default.mcap", topics),
        "no repeated channels or schemas": _write(
            root / "norepeat.mcap", topics, repeat_channels=False, repeat_schemas=False
        ),
        "message indexes only": _write(root / "mx.mcap", topics, index_types=IndexType.MESSAGE),
        "chunk indexes only": _write(root / "chx.mcap", topics, index_types=IndexType.CHUNK),
        "unchunked": _write(root / "unchunked.mcap", topics, use_chunking=False),
        "no statistics": _write(root / "nostats.mcap", topics, use_statistics=False),
    }
    made["no summary"] = without_summary(made["default"], root / "default-nosummary.mcap")
    return made, list(topics)


@pytest.mark.parametrize(
    "layout",
    [
        "no repeated channels or schemas",
        "message indexes only",
        "chunk indexes only",
        "unchunked",
        "no statistics",
        "no summary",
    ],
)
def test_every_layout_of_the_official_writer_reads_the_same_samples(layouts, layout):
    made, topics = layouts
    want, got = read_imu(made["default"], topics), read_imu(made[layout], topics)
    for topic in topics:
        assert got[topic].stream.t_ns.tobytes() == want[topic].stream.t_ns.tobytes()
        assert got[topic].stream.gyro.tobytes() == want[topic].stream.gyro.tobytes()
        assert got[topic].stream.accel.tobytes() == want[topic].stream.accel.tobytes()
        assert got[topic].stats.to_dict() == want[topic].stats.to_dict()


@pytest.mark.parametrize(
    "layout", ["no repeated channels or schemas", "chunk indexes only", "no summary"]
)
def test_calibrate_gives_the_same_result_on_every_layout(layouts, layout, tmp_path, short_drive):
    from imucal_cli.documents import write_document

    made, _ = layouts
    config = tmp_path / "c.yaml"
    write_document(config, short_drive.config_document())
    docs = []
    for path in (made["default"], made[layout]):
        result = runner.invoke(app, ["calibrate", str(path), "-c", str(config), "--json"])
        assert result.exit_code == 0, result.output
        doc = json.loads(result.stdout)
        doc.pop("log")
        docs.append(doc)
    assert docs[0] == docs[1]


def test_a_rosbag2_given_as_its_metadata_file_reads_as_its_folder(tmp_path, short_drive):
    topics = short_drive.topics()
    for fmt in ("rosbag2-sqlite3", "rosbag2-mcap"):
        bag = write_imu_log(tmp_path / fmt, fmt, topics)
        by_folder, by_metadata = (
            read_imu(bag, list(topics)),
            read_imu(bag / "metadata.yaml", list(topics)),
        )
        for topic in topics:
            assert (
                by_metadata[topic].stream.t_ns.tobytes() == by_folder[topic].stream.t_ns.tobytes()
            )


def test_a_storage_file_or_a_folder_that_is_not_a_bag_says_what_to_give(tmp_path, short_drive):
    bag = write_imu_log(tmp_path / "bag", "rosbag2-sqlite3", short_drive.topics())
    storage = next(bag.glob("*.db3"))
    result = runner.invoke(app, ["inspect", str(storage)])
    assert result.exit_code == 2 and f"give its bag folder ({bag})" in result.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["inspect", str(empty)])
    assert (
        result.exit_code == 2
        and "no metadata.yaml" in result.stderr
        and "ros2 bag reindex" in result.stderr
    )
    zstd = tmp_path / "bag2" / "x.db3.zstd"
    zstd.parent.mkdir()
    zstd.write_bytes(b"\x28\xb5\x2f\xfd")
    result = runner.invoke(app, ["inspect", str(zstd)])
    assert result.exit_code == 2 and "give its bag folder" in result.stderr


def test_a_damaged_chunk_in_a_file_without_summary_is_said_not_hidden(layouts):
    made, topics = layouts
    data = bytearray(made["no summary"].read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)  # inside a chunk's compressed records
    damaged = made["no summary"].with_name("damaged-nosummary.mcap")
    damaged.write_bytes(bytes(data))
    losses = []
    got = read_imu(damaged, topics, losses=losses)
    full = read_imu(made["default"], topics)
    assert sum(len(r.stream) for r in got.values()) < sum(len(r.stream) for r in full.values())
    assert [x for x in losses if x.lost and "chunk does not read" in x.reason]


def test_the_topics_of_a_group_spanning_a_minute_arrive_interleaved(tmp_path, monkeypatch):
    """A group of chunks can span minutes of a low-rate log (the real IMU array board's: 400
    s); each topic's batch of it was given whole, so one topic ran minutes ahead of the other
    and the calibrator took the other for stopped, its windows lost. Batches are now cut at
    ``BATCH_SPAN_NS`` and given in time order."""
    from imucal_cli.api import calibrate
    from imucal_cli.io import base, mcap_log
    from imucal_cli.reading import ImuBatches
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    monkeypatch.setattr(mcap_log, "GROUP_BYTES", 256 << 20)  # the whole log in one group
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=81.0, seed=4, sensors=1))
    log = write_imu_log(tmp_path / "g.mcap", "mcap", drive.topics())
    reached: dict[str, int] = {}
    lead = 0
    for topic, stamps, *_ in ImuBatches(log, list(drive.topics())):
        reached[topic] = max(reached.get(topic, 0), int(stamps.max()))
        if len(reached) == 2:
            lead = max(lead, max(reached.values()) - min(reached.values()))
    assert 0 < lead <= base.BATCH_SPAN_NS + 1_000_000_000
    run = calibrate(log, drive.config())
    for sensor in run.document()["sensors"].values():
        assert not any("sent nothing" in w for w in sensor["warnings"]), sensor["warnings"]
        assert sensor["status"] == "ok"


def test_an_empty_message_record_is_passed_over_not_the_end_of_the_walk(tmp_path, short_drive):
    """A Message record too short for its fields (9 bytes) made the record walk read a log
    time past it (IndexError): the file was 'damaged' there and everything after was lost. It
    is passed over; every message after it is read."""
    import struct

    from conftest import without_summary

    from imucal_cli.io.logs import open_log
    from imucal_cli.reading import read_imu

    topics = list(short_drive.topics())
    intact = write_imu_log(tmp_path / "d.mcap", "mcap", short_drive.topics())
    bare = without_summary(intact, tmp_path / "bare.mcap")
    data = bare.read_bytes()
    (header_length,) = struct.unpack_from("<Q", data, 8 + 1)
    at = 8 + 9 + header_length  # after the magic and the header
    empty = struct.pack("<BQ", 0x05, 0)  # a Message record with no fields
    hostile = tmp_path / "empty.mcap"
    hostile.write_bytes(data[:at] + empty + data[at:])
    expected = read_imu(bare, topics)
    got = read_imu(hostile, topics)
    for topic in topics:
        np.testing.assert_array_equal(got[topic].stream.t_ns, expected[topic].stream.t_ns)
    with open_log(hostile) as reader:
        reader.topics()
        assert not any(loss.lost for loss in reader.losses)


def test_the_chunk_table_gives_back_every_chunk_index_the_mcap_library_reads():
    """The summary's chunk indexes held as arrays come back, row by row, as the ``mcap``
    library's own ``ChunkIndex`` records (every field, in file order), at a fraction of their
    memory."""
    from mcap.reader import make_reader

    from imucal_cli.io.mcap_log import ChunkTable

    log = Path(__file__).resolve().parents[2] / "sample_data" / "urban.mcap"
    with log.open("rb") as handle:
        indexes = make_reader(handle).get_summary().chunk_indexes
    ordered = sorted(indexes, key=lambda index: index.chunk_start_offset)
    table = ChunkTable(indexes)
    assert len(ordered) > 1 and list(table) == ordered
    assert table.values.nbytes + table.offsets.nbytes < 160 * len(ordered)
