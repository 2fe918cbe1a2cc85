"""Make the third-party log fixtures in this folder (run by hand; the outputs are committed).

These logs are written by tools other than imucal, so the readers are tested on files they did
not produce themselves:

- ``ros1_rosbag.bag``: ROS 1's own ``rosbag`` Python package (Debian ``python3-rosbag``), with
  genpy ``sensor_msgs/Imu`` and ``std_msgs/String`` messages, bz2-compressed chunks.
- ``ros1_mcap_ros1_writer.mcap``: ``mcap_ros1.writer`` with the same genpy messages.
- ``ros2_mcap_ros2_writer.mcap``: ``mcap_ros2.writer``, its own CDR serializer.
- ``rosbag2_converted_sqlite3/``: ``rosbags-convert`` of ``ros1_rosbag.bag`` to rosbag2 (sqlite3
  storage, messages re-encoded from ROS 1 to CDR by the converter).

Needs: ``apt-get install python3-rosbag python3-sensor-msgs`` and
``pip install mcap-ros1-support mcap-ros2-support``. Run: ``python tests/data/make_fixtures.py``.
The message values follow :func:`expected_imu` in ``tests/test_third_party_logs.py``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).parent
COUNT = 150
CHATTER = 40
T0_S = 1_600_000_000

ROSBAG_SCRIPT = r"""
import sys
import rosbag, rospy
from sensor_msgs.msg import Imu
from std_msgs.msg import String
out, count, chatter, t0 = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
with rosbag.Bag(out, "w", compression="bz2") as bag:
    for i in range(count):
        m = Imu()
        m.header.seq = i
        m.header.stamp = rospy.Time(t0 + i // 100, (i % 100) * 10_000_000)
        m.header.frame_id = "imu_link"
        w = m.angular_velocity
        w.x, w.y, w.z = i * 0.001, -i * 0.002, 0.5
        m.linear_acceleration.x, m.linear_acceleration.y = 0.1, 0.2
        m.linear_acceleration.z = 9.81 + i * 1e-4
        m.orientation_covariance[0] = -1.0
        bag.write("/imu/data", m, m.header.stamp + rospy.Duration(0, 1_000_000))
    for i in range(chatter):
        stamp = rospy.Time(t0 + i // 25, (i % 25) * 40_000_000)
        bag.write("/chatter", String(data="hello %d" % i), stamp)
"""


def make_rosbag1() -> None:
    out = HERE / "ros1_rosbag.bag"
    subprocess.run(
        ["/usr/bin/python3", "-c", ROSBAG_SCRIPT, str(out), str(COUNT), str(CHATTER), str(T0_S)],
        check=True,
    )


def make_mcap_ros1() -> None:
    sys.path.append("/usr/lib/python3/dist-packages")  # genpy messages from Debian
    import genpy
    from mcap_ros1.writer import Writer
    from sensor_msgs.msg import Imu

    with (HERE / "ros1_mcap_ros1_writer.mcap").open("wb") as handle:
        writer = Writer(handle)
        for i in range(COUNT):
            m = Imu()
            m.header.seq = i
            m.header.stamp = genpy.Time(T0_S + i // 100, (i % 100) * 10_000_000)
            m.header.frame_id = "imu_link"
            m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (
                i * 0.001,
                -i * 0.002,
                0.5,
            )
            m.linear_acceleration.x, m.linear_acceleration.y = 0.1, 0.2
            m.linear_acceleration.z = 9.81 + i * 1e-4
            log_ns = m.header.stamp.to_nsec() + 1_000_000
            writer.write_message("/imu/data", m, log_time=log_ns, publish_time=log_ns)
        writer.finish()


IMU_MSGDEF = """std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
"""


def make_mcap_ros2() -> None:
    from mcap_ros2.writer import Writer

    with (HERE / "ros2_mcap_ros2_writer.mcap").open("wb") as handle:
        writer = Writer(handle)
        schema = writer.register_msgdef("sensor_msgs/msg/Imu", IMU_MSGDEF)
        string_schema = writer.register_msgdef("std_msgs/msg/String", "string data\n")
        for i in range(COUNT):
            sec, nanosec = T0_S + i // 100, (i % 100) * 10_000_000
            message = {
                "header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "imu_link"},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [-1.0] + [0.0] * 8,
                "angular_velocity": {"x": i * 0.001, "y": -i * 0.002, "z": 0.5},
                "angular_velocity_covariance": [0.0] * 9,
                "linear_acceleration": {"x": 0.1, "y": 0.2, "z": 9.81 + i * 1e-4},
                "linear_acceleration_covariance": [0.0] * 9,
            }
            log_ns = sec * 1_000_000_000 + nanosec + 1_000_000
            writer.write_message("/imu/data", schema, message, log_time=log_ns, publish_time=log_ns)
        for i in range(CHATTER):
            log_ns = (T0_S + i // 25) * 1_000_000_000 + (i % 25) * 40_000_000
            writer.write_message("/chatter", string_schema, {"data": f"hello {i}"}, log_time=log_ns)
        writer.finish()


def make_rosbag2_converted() -> None:
    import shutil

    out = HERE / "rosbag2_converted_sqlite3"
    shutil.rmtree(out, ignore_errors=True)
    subprocess.run(
        [
            "rosbags-convert",
            "--src",
            str(HERE / "ros1_rosbag.bag"),
            "--dst",
            str(out),
            "--dst-storage",
            "sqlite3",
            "--dst-typestore",
            "ros2_humble",
        ],
        check=True,
    )


if __name__ == "__main__":
    make_rosbag1()
    make_rosbag2_converted()
    make_mcap_ros1()
    make_mcap_ros2()
    for path in sorted(HERE.iterdir()):
        print(path.name, path.stat().st_size)
