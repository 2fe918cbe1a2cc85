"""Logs written by other tools (ROS 1 rosbag, mcap_ros1/mcap_ros2 writers, rosbags-convert).

The fixtures are made by ``tests/data/make_fixtures.py`` and committed; imucal never wrote them.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA

from imucal_cli.errors import LogError
from imucal_cli.inspection import summarize_log
from imucal_cli.reading import read_imu

COUNT, T0_S = 150, 1_600_000_000

FIXTURES = {
    "ros1_rosbag.bag": ("rosbag1", {"/imu/data": "sensor_msgs/Imu", "/chatter": "std_msgs/String"}),
    "ros1_mcap_ros1_writer.mcap": ("mcap", {"/imu/data": "sensor_msgs/Imu"}),
    "ros2_mcap_ros2_writer.mcap": (
        "mcap",
        {"/imu/data": "sensor_msgs/msg/Imu", "/chatter": "std_msgs/msg/String"},
    ),
    "rosbag2_converted_sqlite3": (
        "rosbag2-sqlite3",
        {"/imu/data": "sensor_msgs/msg/Imu", "/chatter": "std_msgs/msg/String"},
    ),
}


def expected_imu():
    i = np.arange(COUNT)
    t_ns = (T0_S + i // 100) * 1_000_000_000 + (i % 100) * 10_000_000
    gyro = np.column_stack([[k * 0.001 for k in i], [-k * 0.002 for k in i], np.full(COUNT, 0.5)])
    accel = np.column_stack(
        [np.full(COUNT, 0.1), np.full(COUNT, 0.2), [9.81 + k * 1e-4 for k in i]]
    )
    return t_ns.astype(np.int64), gyro, accel


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_third_party_log_values(name):
    got = read_imu(DATA / name, ["/imu/data"])["/imu/data"]
    t_ns, gyro, accel = expected_imu()
    assert got.stats.messages == COUNT and len(got.stream) == COUNT
    assert np.array_equal(got.stream.t_ns, t_ns)
    assert got.stream.gyro.tobytes() == gyro.tobytes()
    assert got.stream.accel.tobytes() == accel.tobytes()
    assert got.stream.frame_id == "imu_link"
    assert np.array_equal(got.log_time_ns, t_ns + 1_000_000)


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_third_party_log_inspect(name):
    fmt, types = FIXTURES[name]
    summary = summarize_log(DATA / name)
    assert summary.format_name == fmt
    got = {t.topic: (t.msgtype, t.count) for t in summary.topics}
    assert got == {
        topic: (msgtype, COUNT if "imu" in topic else 40) for topic, msgtype in types.items()
    }
    imu = next(t for t in summary.topics if t.topic == "/imu/data")
    assert imu.rate_hz == pytest.approx(100.0) and imu.time_source == "header.stamp"
    assert imu.duration_s == pytest.approx(1.49)


def test_missing_topic_lists_the_imu_topics():
    with pytest.raises(LogError) as info:
        read_imu(DATA / "ros1_rosbag.bag", ["/gnss/imu"])
    message = str(info.value)
    assert "ros1_rosbag.bag" in message and "/gnss/imu" in message and "/imu/data" in message
    assert "/chatter" not in message


def test_wrong_type_names_both_types():
    with pytest.raises(LogError) as info:
        read_imu(DATA / "ros2_mcap_ros2_writer.mcap", ["/chatter"])
    message = str(info.value)
    assert (
        "/chatter" in message
        and "std_msgs/msg/String" in message
        and "sensor_msgs/msg/Imu" in message
    )
