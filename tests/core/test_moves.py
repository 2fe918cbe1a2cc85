"""Mounts that moved during the log: the change-point test over the windows, and drives whose
lidar mount is knocked."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from imucal_cli.core.moves import best_split, scatter
from tests.conftest import lidar_error


def _windows(K: int, jump_at: int | None, size: float, seed: int = 0, clock: float = 0.0):
    """Per window, the information (K, 7, 7) and gradient (K, 7) of a pose that is 0 before
    window ``jump_at`` and ``size`` (every axis) after it, the window itself half of it, and a
    clock offset that steps by ``clock`` there, with unit-information noise."""
    rng = np.random.default_rng(seed)
    information = np.repeat(np.eye(7)[None], K, axis=0)
    truth = np.zeros((K, 7))
    if jump_at is not None:
        truth[jump_at + 1 :] = [*[size] * 6, clock]
        truth[jump_at] = truth[jump_at + 1] / 2
    gradient = truth + rng.normal(size=(K, 7))  # I (pose - 0) + noise: the score at pose 0
    return information, gradient


def test_the_window_the_pose_jumps_in_has_the_largest_ratio():
    information, gradient = _windows(30, 17, 3.0)
    k, ratio, dof, _ = best_split(information, gradient)
    assert k in (16, 17, 18) and dof == 6 and ratio > 100.0
    assert scatter(information, gradient, 17) == pytest.approx(1.0, abs=0.5)


def test_a_clock_that_steps_is_not_a_move():
    """The clock's offset steps by 50 of its std, the pose stays: each side's clock is its
    own in both hypotheses, so the ratio is of the pose alone, chi-square with 6 dof."""
    information, gradient = _windows(30, 17, 0.0, clock=50.0)
    _, ratio, dof, _ = best_split(information, gradient)
    assert dof == 6 and ratio < 40.0


def test_without_a_jump_the_ratio_is_chi_square_and_rarely_beyond_the_threshold():
    """The largest ratio over the splits of a pose that never moved, against the Bonferroni
    threshold at 1%: beyond it in about 1% of draws (here 0 or 1 of 50), never often."""
    from scipy.special import chdtri

    beyond = 0
    for seed in range(50):
        information, gradient = _windows(30, None, 0.0, seed)
        _, ratio, dof, _ = best_split(information, gradient)
        beyond += ratio > chdtri(dof, 0.01 / 26)
    assert beyond <= 3


@pytest.fixture(scope="module")
def knocked():
    """A 300 s urban drive; the first lidar's mount knocked at 165 s (1.15 deg about y, 14 mm)."""
    from imucal_cli.sim import DriveOptions, simulate_drive

    knock = ((165.0, (0.0, 0.02, 0.0), (0.01, 0.0, 0.01)),)
    return simulate_drive(
        DriveOptions(scenario="urban", duration_s=300.0, seed=1, knocks=(knock, ()))
    )


def test_a_knocked_mount_is_said_with_when_how_far_and_the_pose_it_has_now(knocked):
    """Before, the knocked lidar was `inconsistent`, its pose a blend 0.6 deg from either; now
    the move is said within a window of when it happened, its size within 3 std of the true
    turn and shift, the pose before within 4 std of the truth, and the sensor is `ok` with the
    pose it has now (within 4 std). The lidar that was not knocked has no move."""
    from imucal_cli.api import calibrate_streams
    from imucal_cli.core.so3 import rotation_angle_deg
    from imucal_cli.types import Transform

    cal = calibrate_streams(knocked.streams(), knocked.config())
    document = cal.document()["sensors"]
    truth = knocked.truth_document()["sensors"]
    name, other = (m.name for m in knocked.mounts)
    s = document[name]
    assert s["status"] == "ok", s["warnings"]
    (move,) = s["moved"]
    assert abs(move["at_s"] - 165.0) <= 10.0
    before_true = Transform.from_dict(truth[name]["moved"][0]["before"]["T_base_lidar"], "", "")
    after_true = knocked.mounts[0].T_base_lidar
    angle = rotation_angle_deg(before_true.rotation, after_true.rotation)
    shift = float(np.linalg.norm(after_true.translation - before_true.translation))
    std_r = np.hypot(max(move["before"]["rotation_std_deg"]), max(s["rotation_std_deg"]))
    std_t = np.hypot(max(move["before"]["translation_std_m"]), max(s["translation_std_m"]))
    assert abs(move["rotation_deg"] - angle) <= 3 * std_r
    assert abs(move["translation_m"] - shift) <= 3 * std_t
    before = Transform.from_dict(move["before"]["T_base_lidar"], "", "")
    turned = rotation_angle_deg(before.rotation, before_true.rotation)
    assert turned <= 4 * max(move["before"]["rotation_std_deg"])
    error, std = lidar_error(knocked, cal, name)
    assert np.all(np.abs(error) <= 4 * std)
    assert any(w.startswith("the mount moved at") for w in s["warnings"])
    assert document[other]["moved"] == [] and document[other]["status"] == "ok"


def _epochs_60(document):
    document.setdefault("calibration", {})["epoch_s"] = 60.0


def test_the_timeline_shows_the_pose_before_the_knock_and_the_pose_after_it(knocked):
    """With ``calibration.epoch_s: 60`` the timeline has an epoch a minute, in time order; each
    wholly before the knock holds the pose before (within 4 of its std), each wholly after the
    pose now, and the lidar that was not knocked its one pose in every epoch."""
    from imucal_cli.api import calibrate_streams
    from imucal_cli.core.so3 import rotation_angle_deg
    from imucal_cli.types import Transform

    cal = calibrate_streams(knocked.streams(), knocked.config(_epochs_60))
    document = cal.document()["sensors"]
    truth = knocked.truth_document()["sensors"]
    name, other = (m.name for m in knocked.mounts)
    before = Transform.from_dict(truth[name]["moved"][0]["before"]["T_base_lidar"], "", "")
    poses = {
        name: (before, knocked.mounts[0].T_base_lidar),
        other: (knocked.mounts[1].T_base_lidar,) * 2,
    }
    for sensor, (then, now) in poses.items():
        epochs = document[sensor]["timeline"]
        assert len(epochs) >= 4
        assert all(a["end_s"] <= b["start_s"] for a, b in pairwise(epochs))
        for epoch in epochs:
            if epoch["start_s"] < 165.0 < epoch["end_s"]:
                continue  # (it holds both poses)
            truth_pose = then if epoch["end_s"] <= 165.0 else now
            pose = Transform.from_dict(
                {"translation": epoch["translation"], "rpy_deg": epoch["rpy_deg"]}, "", ""
            )
            turned = rotation_angle_deg(pose.rotation, truth_pose.rotation)
            assert turned <= 4 * max(epoch["rotation_std_deg"]), (sensor, epoch)
            error = np.abs(pose.translation - truth_pose.translation)
            assert np.all(error <= 4 * np.array(epoch["translation_std_m"])), (sensor, epoch)


def test_following_says_the_move_within_two_epochs_and_goes_on_with_the_new_pose(knocked):
    """Fed as it is recorded (the follow mode's state, an update every 20 s of data), the knock
    at 165 s is said by two epochs (60 s each) after it, and from then on the pose given is
    the one the mount has now (within 4 std)."""
    from imucal_cli.core.so3 import rotation_angle_deg
    from imucal_cli.pipeline import _Follower

    seen = []
    state = _Follower(
        knocked.config(_epochs_60), lambda cal, _: seen.append(cal), None, lambda: False, False
    )
    streams = {"base": knocked.streams().base, **knocked.streams().sensors}
    start = min(int(s.t_ns[0]) for s in streams.values())
    name = knocked.mounts[0].name
    said_at = None
    for edge_s in np.arange(20.0, 301.0, 20.0):
        for imu, stream in streams.items():
            a, b = np.searchsorted(
                stream.t_ns, [start + (edge_s - 20.0) * 1e9, start + edge_s * 1e9]
            )
            state.sink(imu, stream.t_ns[a:b], stream.gyro[a:b], stream.accel[a:b])
        state.caught_up()
        moved = state.latest.document()["sensors"][name]["moved"] if state.latest else []
        if moved and said_at is None:
            said_at = edge_s
        if said_at is not None:
            est = state.latest.estimates[name]
            now = knocked.mounts[0].T_base_imu
            turned = rotation_angle_deg(est.T_base_imu.rotation, now.rotation)
            assert turned <= 4 * max(state.latest.document()["sensors"][name]["rotation_std_deg"])
    assert said_at is not None and said_at <= 165.0 + 2 * 60.0
