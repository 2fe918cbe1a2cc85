"""Exports: every format parsed back (YAML, XML, command lines) reproduces the transforms."""

from __future__ import annotations

import json
import shlex
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.exports import FORMATS, Extrinsics, SensorExtrinsics, export
from imucal_cli.types import Transform, rpy_to_rotation

runner = CliRunner()
FULL = 1e-9  # full-precision formats: round-off only
SIX_DECIMALS_M = 0.5e-6 + 1e-12  # Autoware: 6 decimals in metres ...
SIX_DECIMALS_RAD = 3 * 0.5e-6  # ... and radians: three rounded angles, each off by <= 5e-7 rad


def angle(a: Rotation, b: Rotation) -> float:
    return float((a.inv() * b).magnitude())


NOISE = {
    "accelerometer_noise_density": 2e-3,
    "accelerometer_random_walk": 3e-3,
    "gyroscope_noise_density": 2e-4,
    "gyroscope_random_walk": 2e-5,
}


def extrinsics(transforms: list[Transform]) -> Extrinsics:
    sensors = tuple(
        SensorExtrinsics(
            f"s{k}",
            f"lidar_{k}",
            f"/lidar/{k}/imu",
            T,
            T * Transform.from_rpy(np.array([0.1, -0.2, 3.0]), np.array([0.01, 0.02, -0.03])),
            0.001 * k - 0.002,
            200.0,
            NOISE,
        )
        for k, T in enumerate(transforms)
    )
    return Extrinsics("test.yaml", "base_link", "/gnss/imu", 100.0, sensors, NOISE, BASE_POSE)


#: The base IMU's pose in B: an INS upside down, turned and away from B's origin.
BASE_POSE = Transform.from_rpy(np.array([np.pi, 0.0, 0.3]), np.array([1.2, 0.1, 0.5]))


def parse(fmt: str, files: dict[str, str], parent: str = "base_link") -> dict[str, Transform]:
    """Per lidar frame, the transform the file says (T_parent_lidar; Kalibr: T_base_imu)."""
    out: dict[str, Transform] = {}
    if fmt == "autoware":
        doc = yaml.safe_load(files["main"])
        for frame, v in doc[parent].items():
            out[frame] = Transform.from_rpy(
                np.array([v["roll"], v["pitch"], v["yaw"]]), np.array([v["x"], v["y"], v["z"]])
            )
    elif fmt == "urdf":
        root = ET.fromstring(files["main"])
        for joint in root.iter("joint"):
            assert joint.get("type") == "fixed" and joint.find("parent").get("link") == parent
            origin = joint.find("origin")
            xyz = np.array([float(v) for v in origin.get("xyz").split()])
            rpy = np.array([float(v) for v in origin.get("rpy").split()])
            out[joint.find("child").get("link")] = Transform(rpy_to_rotation(rpy), xyz)
    elif fmt in ("tf-static-ros2", "tf-static-ros1"):
        lines = [ln for ln in files["main"].splitlines() if "static_transform_publisher" in ln]
        nodes = ET.fromstring(files["launch"]).findall("node")
        assert len(nodes) == len(lines)
        for line, node in zip(lines, nodes, strict=True):
            words = shlex.split(line.removesuffix("&"))
            args = words[words.index("static_transform_publisher") + 1 :]
            assert args == shlex.split(node.get("args"))  # the launch file says the same
            if fmt == "tf-static-ros2":
                assert (
                    words[:3] == ["ros2", "run", "tf2_ros"]
                    and node.get("exec") == "static_transform_publisher"
                )
                named = dict(zip(args[::2], args[1::2], strict=True))
                assert named["--frame-id"] == parent
                t = [float(named[k]) for k in ("--x", "--y", "--z")]
                q = [float(named[k]) for k in ("--qx", "--qy", "--qz", "--qw")]
                child = named["--child-frame-id"]
            else:
                assert (
                    words[:2] == ["rosrun", "tf2_ros"]
                    and node.get("type") == "static_transform_publisher"
                )
                assert len(args) == 9 and args[7] == parent  # x y z qx qy qz qw frame child
                t, q, child = [float(v) for v in args[:3]], [float(v) for v in args[3:7]], args[8]
            out[child] = Transform(Rotation.from_quat(q), np.array(t))
    elif fmt == "kalibr":
        doc = yaml.safe_load(files["main"])
        for key in sorted(doc):
            T_i_b = np.array(doc[key]["T_i_b"])
            assert (
                doc[key]["model"] == "calibrated"
                and "update_rate" in doc[key]
                and "rostopic" in doc[key]
            )
            out[key] = Transform.from_matrix(np.linalg.inv(T_i_b))  # T_base_imu
    elif fmt == "json":
        doc = json.loads(files["main"])
        for s in doc["sensors"].values():
            out[s["lidar_frame"]] = Transform.from_matrix(np.array(s["T_base_lidar"]))
            out["imu:" + s["lidar_frame"]] = Transform.from_matrix(np.array(s["T_base_imu"]))
    return out


def check(fmt: str, ex: Extrinsics) -> None:
    got = parse(fmt, export(ex, fmt))
    tol_t, tol_r = (SIX_DECIMALS_M, SIX_DECIMALS_RAD) if fmt == "autoware" else (FULL, FULL)
    for k, s in enumerate(ex.sensors, start=1):
        if fmt == "kalibr":
            pairs = [(got[f"imu{k}"], s.T_base_imu), (got["imu0"], ex.base_T_base_imu)]
        elif fmt == "json":
            pairs = [
                (got[s.lidar_frame], s.T_base_lidar),
                (got["imu:" + s.lidar_frame], s.T_base_imu),
            ]
        else:
            pairs = [(got[s.lidar_frame], s.T_base_lidar)]
        for parsed, expected in pairs:
            assert np.max(np.abs(parsed.translation - expected.translation)) <= tol_t
            assert angle(parsed.rotation, expected.rotation) <= tol_r


@pytest.mark.parametrize("fmt", FORMATS)
def test_sample_calibration_round_trips(fmt, tmp_path):
    from conftest import SAMPLE_DATA

    out = tmp_path / "ext.yaml"
    result = runner.invoke(
        app,
        [
            "calibrate",
            str(SAMPLE_DATA / "aggressive.mcap"),
            "-c",
            str(SAMPLE_DATA / "aggressive.config.yaml"),
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    document = yaml.safe_load(out.read_text())
    ex = Extrinsics.from_document(document, str(out))
    check(fmt, ex)
    target = tmp_path / f"export_{fmt}.txt"
    result = runner.invoke(app, ["export", str(out), "--format", fmt, "-o", str(target)])
    assert result.exit_code == 0, result.output
    files = {"main": target.read_text()}
    if fmt.startswith("tf-static"):
        files["launch"] = (
            tmp_path
            / (
                "export_tf-static-ros2.launch.xml"
                if fmt.endswith("ros2")
                else "export_tf-static-ros1.launch"
            )
        ).read_text()
        assert target.stat().st_mode & 0o111  # the command lines are a script to run
    assert files == export(ex, fmt)
    printed = runner.invoke(app, ["export", str(out), "--format", fmt])
    assert printed.stdout == files["main"]  # one file printed, never the launch file mixed in


def test_kalibr_T_i_b_is_the_base_in_the_imu():
    T_base_imu = Transform.from_rpy(np.array([0.0, 0.0, np.pi / 2]), np.array([1.0, 0.0, 0.0]))
    ex = extrinsics([Transform.identity()])
    ex = Extrinsics(
        ex.source,
        ex.base_frame,
        ex.base_topic,
        ex.base_imu_rate_hz,
        (SensorExtrinsics("s", "l", "/imu", Transform.identity(), T_base_imu, 0.0, 200.0, NOISE),),
        NOISE,
        Transform.identity(),
    )
    T_i_b = np.array(yaml.safe_load(export(ex, "kalibr")["main"])["imu1"]["T_i_b"])
    # The IMU sits 1 m along the base's x axis, yawed 90 deg: its y axis points along the base's
    # -x. The base origin, 1 m behind the IMU along base x, is 1 m along the IMU's +y.
    assert np.allclose(T_i_b @ np.array([0, 0, 0, 1.0]), [0.0, 1.0, 0.0, 1.0])


near_pole = st.floats(-1e-6, 1e-6) | st.floats(-1e-3, 1e-3)


@settings(max_examples=60, deadline=None)
@given(
    yaw=st.sampled_from([np.pi, -np.pi, 0.0, np.pi / 2]).flatmap(
        lambda y: near_pole.map(lambda d: y + d)
    ),
    pitch=st.sampled_from([np.pi / 2, -np.pi / 2, 0.3]).flatmap(
        lambda p: near_pole.map(lambda d: p + d)
    ),
    roll=st.floats(-np.pi, np.pi),
    xyz=st.lists(st.floats(-10, 10), min_size=3, max_size=3),
)
def test_every_format_round_trips_near_gimbal_lock_and_yaw_wrap(yaw, pitch, roll, xyz):
    T = Transform.from_rpy(np.array([roll, pitch, yaw]), np.array(xyz))
    ex = extrinsics([T, T.inverse()])
    for fmt in FORMATS:
        check(fmt, ex)


def test_export_bad_input_exits_2(tmp_path):
    bad = tmp_path / "x.yaml"
    bad.write_text("sensors: {a: {lidar_frame: l}}\n")
    result = runner.invoke(app, ["export", str(bad), "--format", "urdf"])
    assert result.exit_code == 2 and "x.yaml" in result.stderr and "T_base_lidar" in result.stderr
    result = runner.invoke(app, ["export", str(bad), "--format", "ros3"])
    assert result.exit_code == 2 and "ros3" in result.stderr


def test_export_rejects_a_non_number_rate(tmp_path):
    from conftest import SAMPLE_DATA

    out = tmp_path / "e.yaml"
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(SAMPLE_DATA / "aggressive.mcap"),
                "-c",
                str(SAMPLE_DATA / "aggressive.config.yaml"),
                "-o",
                str(out),
            ],
        ).exit_code
        == 0
    )
    document = yaml.safe_load(out.read_text())
    name = next(iter(document["sensors"]))
    document["sensors"][name]["imu_rate_hz"] = "fast"
    out.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["export", str(out), "--format", "kalibr"])
    assert (
        result.exit_code == 2
        and f"sensors.{name}.imu_rate_hz" in result.stderr
        and "e.yaml" in result.stderr
    )


def _kalibr_imu_parameters(data: dict, name: str) -> tuple:
    """What Kalibr's ``kalibr_common.ConfigReader.ImuParameters`` reads and checks of one IMU
    (its getRosTopic, getUpdateRate, getAccelerometerStatistics, getGyroStatistics: a missing
    field or a value that is not positive is an error), and the T_i_b its IMU chain holds."""
    imu = data[name]
    for field in (
        "rostopic",
        "update_rate",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "gyroscope_noise_density",
        "gyroscope_random_walk",
    ):
        assert field in imu, f"[ImuConfig Reader]: Field '{field}' missing"
    assert isinstance(imu["rostopic"], str), "rostopic has to be a string"
    assert imu["update_rate"] > 0.0, "invalid update_rate"
    for field in (
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "gyroscope_noise_density",
        "gyroscope_random_walk",
    ):
        assert isinstance(imu[field], float) and imu[field] > 0.0, f"invalid {field}"
    T = np.array(imu["T_i_b"], dtype=float)
    assert (
        T.shape == (4, 4)
        and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        and np.allclose(T[3], [0, 0, 0, 1])
    )
    return imu["accelerometer_noise_density"] / np.sqrt(1.0 / imu["update_rate"]), imu[
        "gyroscope_noise_density"
    ] / np.sqrt(1.0 / imu["update_rate"])


def _openvins_noise(data: dict) -> dict:
    """What OpenVINS's VioManagerOptions::print_and_load_noise takes from the IMU file: imu0's
    four noise figures, each required (parse_external fails without it)."""
    keys = (
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
    )
    missing = [k for k in keys if k not in data["imu0"]]
    assert not missing, f"unable to find {missing}"
    return {k: float(data["imu0"][k]) for k in keys}


def test_kalibr_export_reads_in_kalibr_and_openvins_with_the_noise_the_drive_has(tmp_path):
    from conftest import SAMPLE_DATA

    out = tmp_path / "ext.yaml"
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(SAMPLE_DATA / "aggressive.mcap"),
                "-c",
                str(SAMPLE_DATA / "aggressive.config.yaml"),
                "-o",
                str(out),
            ],
        ).exit_code
        == 0
    )
    result = runner.invoke(app, ["export", str(out), "--format", "kalibr"])
    assert result.exit_code == 0, result.output
    data = yaml.safe_load(result.stdout)
    names = sorted(data)
    assert names == [f"imu{k}" for k in range(len(names))] and len(names) >= 2
    for name in names:
        _kalibr_imu_parameters(data, name)
    noise = _openvins_noise(data)
    # the sample drive's IMUs (the simulator's defaults): base 0.002 deg/s/sqrt(Hz) and
    # 50 ug/sqrt(Hz), lidar IMUs 0.015 deg/s/sqrt(Hz) and 230 ug/sqrt(Hz); measured within 10%
    assert noise["gyroscope_noise_density"] == pytest.approx(np.radians(0.002), rel=0.1)
    assert noise["accelerometer_noise_density"] == pytest.approx(50e-6 * 9.80665, rel=0.1)
    assert data["imu1"]["gyroscope_noise_density"] == pytest.approx(np.radians(0.015), rel=0.1)
    assert data["imu1"]["accelerometer_noise_density"] == pytest.approx(230e-6 * 9.80665, rel=0.1)


def test_kalibr_export_of_a_document_without_noise_names_the_missing_key(tmp_path):
    from conftest import SAMPLE_DATA

    out = tmp_path / "ext.yaml"
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(SAMPLE_DATA / "aggressive.mcap"),
                "-c",
                str(SAMPLE_DATA / "aggressive.config.yaml"),
                "-o",
                str(out),
            ],
        ).exit_code
        == 0
    )
    document = yaml.safe_load(out.read_text())
    del document["base_imu_noise"]
    out.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["export", str(out), "--format", "kalibr"])
    assert (
        result.exit_code == 2
        and "base_imu_noise.accelerometer_noise_density: missing" in result.stderr
    )


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    from conftest import SAMPLE_DATA

    out = tmp_path_factory.mktemp("export") / "ext.yaml"
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(SAMPLE_DATA / "aggressive.mcap"),
                "-c",
                str(SAMPLE_DATA / "aggressive.config.yaml"),
                "-o",
                str(out),
            ],
        ).exit_code
        == 0
    )
    return out


def _json_export(path, *args):
    result = runner.invoke(app, ["export", str(path), "--format", "json", *args])
    assert result.exit_code == 0, result.output
    import json

    return json.loads(result.stdout)


def test_parent_re_expresses_every_transform_not_just_its_name(calibrated):
    document = yaml.safe_load(calibrated.read_text())
    a, b = sorted(document["sensors"])
    frame_a = document["sensors"][a]["lidar_frame"]
    exported = _json_export(calibrated, "--parent", frame_a)
    assert exported["base_frame"] == frame_a and list(exported["sensors"]) == [b]
    T_a_b = Transform.from_dict(document["pairs"][f"{a}/{b}"]).as_matrix()
    assert np.allclose(
        exported["sensors"][b]["T_base_lidar"], T_a_b, atol=1e-12
    )  # the calibrate pair, T_a_b
    lifted = _json_export(
        calibrated, "--parent", "base_footprint", "--parent-transform", "0 0 -0.3 0 0 0 1"
    )
    plain = _json_export(calibrated)
    for name in document["sensors"]:
        moved = (
            np.array(lifted["sensors"][name]["T_base_lidar"])[:3, 3]
            - np.array(plain["sensors"][name]["T_base_lidar"])[:3, 3]
        )
        assert np.allclose(moved, [0.0, 0.0, 0.3], atol=1e-12)


def test_parent_that_is_no_frame_of_the_calibration_is_refused(calibrated):
    result = runner.invoke(app, ["export", str(calibrated), "--format", "urdf", "--parent", "map"])
    assert (
        result.exit_code == 2
        and "--parent map: not a frame" in result.stderr
        and "--parent-transform" in result.stderr
    )
    result = runner.invoke(
        app,
        [
            "export",
            str(calibrated),
            "--format",
            "kalibr",
            "--parent",
            "map",
            "--parent-transform",
            "0 0 0 0 0 0 1",
        ],
    )
    assert result.exit_code == 2 and "Kalibr" in result.stderr


def test_a_sensor_not_ok_goes_out_only_when_allowed_and_an_unobserved_offset_is_not_written(
    calibrated, tmp_path
):
    document = yaml.safe_load(calibrated.read_text())
    name = sorted(document["sensors"])[0]
    document["sensors"][name]["status"] = "partial"
    document["sensors"][name]["time_offset_observable"] = False
    document["sensors"][name]["time_offset_s"] = 0.0
    weak = tmp_path / "weak.yaml"
    weak.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["export", str(weak), "--format", "urdf"])
    assert (
        result.exit_code == 2
        and f"{name} (partial)" in result.stderr
        and "--allow-not-ok" in result.stderr
    )
    result = runner.invoke(app, ["export", str(weak), "--format", "kalibr", "--allow-not-ok"])
    assert result.exit_code == 0
    entry = next(
        k
        for k, v in yaml.safe_load(result.stdout).items()
        if v["rostopic"] == document["sensors"][name]["imu_topic"]
    )
    block = result.stdout.split(f"\n{entry}:\n")[1].split("\nimu")[0]
    assert "time_offset: 0.0  # not observable" in block


def test_kalibr_export_reads_in_opencv_filestorage_as_openvins_reads_it(tmp_path):
    """OpenVINS reads the IMU chain with OpenCV's cv::FileStorage, which refused the file
    without its YAML directive ('Input file is invalid'); every IMU's keys read back equal to
    what Kalibr's YAML reader reads (issue 32, item 1)."""
    cv2 = pytest.importorskip("cv2")
    from conftest import SAMPLE_DATA

    out = tmp_path / "ext.yaml"
    assert (
        runner.invoke(
            app,
            [
                "calibrate",
                str(SAMPLE_DATA / "aggressive.mcap"),
                "-c",
                str(SAMPLE_DATA / "aggressive.config.yaml"),
                "-o",
                str(out),
            ],
        ).exit_code
        == 0
    )
    chain = tmp_path / "kalibr_imu_chain.yaml"
    assert (
        runner.invoke(app, ["export", str(out), "--format", "kalibr", "-o", str(chain)]).exit_code
        == 0
    )
    data = yaml.safe_load(chain.read_text())  # as Kalibr reads it
    storage = cv2.FileStorage(str(chain), cv2.FILE_STORAGE_READ)
    assert storage.isOpened()
    for name, imu in data.items():
        node = storage.getNode(name)
        assert not node.empty(), name
        T = node.getNode("T_i_b")
        read = np.array([[T.at(i).at(j).real() for j in range(4)] for i in range(4)])
        np.testing.assert_array_equal(read, np.array(imu["T_i_b"]))
        assert (
            node.getNode("rostopic").string() == imu["rostopic"]
            and node.getNode("model").string() == imu["model"]
        )
        for key in ("update_rate", "time_offset", *KALIBR_KEYS):
            assert node.getNode(key).real() == imu[key], (name, key)
    storage.release()
    # the base's random walks are measured (not the config's gyro filter setting, not a sensor's)
    document = yaml.safe_load(out.read_text())
    assert data["imu0"]["gyroscope_random_walk"] != pytest.approx(np.radians(0.1))
    walks = [s["imu_noise"]["accelerometer_random_walk"] for s in document["sensors"].values()]
    assert data["imu0"]["accelerometer_random_walk"] == min(walks)


KALIBR_KEYS = (
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
)


def test_tf_static_without_out_says_how_to_get_the_launch_file(tmp_path):
    """Without -o only the command lines are printed; the note said the launch file 'is written
    beside -o OUT', though nothing was written (issue 32, item 9)."""
    document = {
        "base_frame": "base_link",
        "sensors": {
            "front": {
                "status": "ok",
                "lidar_frame": "front_lidar",
                "T_base_lidar": {"translation": [1.0, 0.0, 2.0], "rotation": [0.0, 0.0, 0.0, 1.0]},
                "T_base_imu": {"translation": [1.0, 0.0, 2.0], "rotation": [0.0, 0.0, 0.0, 1.0]},
            }
        },
    }
    path = tmp_path / "e.yaml"
    path.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["export", str(path), "--format", "tf-static-ros2"])
    assert result.exit_code == 0 and "static_transform_publisher" in result.stdout
    assert (
        "give -o OUT to write them and the .launch.xml launch file" in result.stderr
        and "is written" not in result.stderr
    )
    assert list(tmp_path.iterdir()) == [path]


def test_kalibr_imu0_is_the_base_imu_where_it_sits_and_its_walks_are_its_grades(tmp_path):
    """The INS turned and 1.6 m away (``base.T_base_imu``): imu0's ``T_i_b`` was the identity,
    and imu1 in imu0, as OpenCV reads the chain (OpenVINS), came out 180 deg and 6.3 m wrong.
    The calibrate document now carries ``base``, and imu0 is the base IMU where it sits; a
    tactical INS's random walks are its grade's, not a lidar IMU's."""
    from imucal_cli.core.grades import GRADES
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.drive import INS_AWAY
    from imucal_cli.sim.writers import write_imu_log

    drive = simulate_drive(
        DriveOptions(
            scenario="aggressive",
            duration_s=60.0,
            seed=3,
            base_T_base_imu=INS_AWAY,
            base_grade="tactical",
        )
    )
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    write_document(tmp_path / "c.yaml", drive.config_document())
    out, chain = tmp_path / "e.yaml", tmp_path / "chain.yaml"
    args = ["calibrate", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(out)]
    assert runner.invoke(app, args).exit_code == 0
    document = yaml.safe_load(out.read_text())
    assert document["base"]["grade"] == "tactical" and document["base"]["source"] == "config"
    np.testing.assert_allclose(
        Transform.from_dict(document["base"]["T_base_imu"]).as_matrix(), INS_AWAY.as_matrix()
    )
    args = ["export", str(out), "-f", "kalibr", "-o", str(chain), "--allow-not-ok"]
    assert runner.invoke(app, args).exit_code == 0
    data = yaml.safe_load(chain.read_text())
    T_i0_b, T_i1_b = (np.array(data[f"imu{k}"]["T_i_b"]) for k in (0, 1))
    mount = drive.mounts[0]
    truth = (INS_AWAY.inverse() * mount.T_base_imu).as_matrix()  # imu1 in imu0
    imu1_in_imu0 = T_i0_b @ np.linalg.inv(T_i1_b)
    np.testing.assert_allclose(imu1_in_imu0[:3, :3], truth[:3, :3], atol=np.radians(0.1))
    np.testing.assert_allclose(imu1_in_imu0[:3, 3], truth[:3, 3], atol=0.01)
    walks = GRADES["tactical"].random_walks
    assert (data["imu0"]["gyroscope_random_walk"], data["imu0"]["accelerometer_random_walk"]) == (
        walks
    )


def test_kalibr_export_of_an_unobservable_sensor_says_no_window_measured_its_walks(tmp_path):
    """A drive without motion: the random walks are missing because no window was used, not
    because the document is of another imucal version."""
    from imucal_cli.documents import write_document
    from imucal_cli.sim import DriveOptions, simulate_drive
    from imucal_cli.sim.writers import write_imu_log

    drive = simulate_drive(DriveOptions(scenario="stationary", duration_s=30.0, seed=1))
    log = write_imu_log(tmp_path / "d.mcap", "mcap", drive.topics())
    write_document(tmp_path / "c.yaml", drive.config_document())
    out = tmp_path / "e.yaml"
    assert (
        runner.invoke(
            app, ["calibrate", str(log), "-c", str(tmp_path / "c.yaml"), "-o", str(out)]
        ).exit_code
        == 0
    )
    assert all(
        s["status"] == "unobservable" for s in yaml.safe_load(out.read_text())["sensors"].values()
    )
    result = runner.invoke(app, ["export", str(out), "-f", "kalibr", "--allow-not-ok"])
    assert result.exit_code == 2
    assert "random_walk: missing (no window of the drive was used" in result.stderr
    assert "imucal version" not in result.stderr


def _guide_snippets() -> list[tuple[str, str]]:
    """docs/usage.md's export examples: each ``--format F`` paragraph's fenced block."""
    import re

    from conftest import SAMPLE_DATA

    guide = (SAMPLE_DATA.parent / "docs" / "usage.md").read_text()
    section = guide[guide.index("## Exports") : guide.index("## Report")]
    return re.findall(r"`--format (\S+?)[` ][^`]*?`?.*?```\w+\n(.*?)```", section, re.S)


def _same_line(shown: str, printed: str) -> bool:
    """The same text, and the same numbers to 1e-7 (relative): what another machine's floating
    point may change in an estimate's last digits, far below what a change of the estimator
    moves (the guide's numbers of an older build differed in the 4th digit)."""
    import re

    number = r"-?\d+\.\d+(?:e-?\d+)?"
    if re.split(number, shown) != re.split(number, printed):
        return False
    a, b = (np.array(re.findall(number, line), dtype=float) for line in (shown, printed))
    return len(a) == len(b) and np.allclose(a, b, rtol=1e-7, atol=1e-12)


def test_the_usage_guide_shows_the_first_lines_the_sample_s_exports_print(calibrated):
    """The guide's examples are the sample's calibration exported (a run of consecutive lines
    of each format's output), not numbers of an older build."""
    from imucal_cli.api import export
    from imucal_cli.documents import load_document

    snippets = _guide_snippets()
    assert [fmt for fmt, _ in snippets] == [
        "autoware",
        "urdf",
        "tf-static-ros2",
        "tf-static-ros1",
        "kalibr",
    ]
    document = load_document(calibrated)
    for fmt, snippet in snippets:
        lines = export(document, fmt)["main"].splitlines()
        shown = snippet.splitlines()
        assert any(
            all(_same_line(a, b) for a, b in zip(shown, lines[i : i + len(shown)], strict=True))
            for i in range(len(lines) - len(shown) + 1)
        ), fmt


def test_bias_walks_are_measured_over_each_knot_s_own_gap():
    """The relative biases' random walk from the fit's knots, each step over its own time: a
    merged stretch's two knots lie its whole span apart. A walk of known density sampled at
    knots 10 s and 100 s apart comes back within 4 of its estimate's std (one over the square
    root of twice the steps); over one window's 10 s each, it came back 2.3 times too large."""
    from types import SimpleNamespace

    from imucal_cli.outputs import imu_noise

    rng = np.random.default_rng(0)
    walk_g, walk_a, steps = 2e-5, 3e-3, 4000
    gaps = rng.choice([10.0, 100.0], size=steps)
    knots_s = np.concatenate([[0.0], np.cumsum(gaps)])

    def walked(density: float) -> np.ndarray:
        moves = rng.normal(size=(steps, 3)) * density * np.sqrt(gaps)[:, None]
        return np.concatenate([np.zeros((1, 3)), np.cumsum(moves, axis=0)])

    estimate = SimpleNamespace(
        bias_knots_s=knots_s, gyro_bias_knots=walked(walk_g), accel_bias_knots=walked(walk_a)
    )
    result = SimpleNamespace(
        noise_density={"lidar": (1e-4, 2e-3)},
        estimates={"lidar": estimate},
        config=SimpleNamespace(base=SimpleNamespace(grade="ideal")),
    )
    noise = imu_noise(result, "lidar")
    tolerance = 4 * 0.5 * np.sqrt(2.0 / (3 * steps))  # (relative std of a density from 3 x steps)
    assert noise["gyroscope_random_walk"] == pytest.approx(walk_g, rel=tolerance)
    assert noise["accelerometer_random_walk"] == pytest.approx(walk_a, rel=tolerance)
