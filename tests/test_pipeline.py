"""The one pipeline: its sensors solved apart on two cores give what one process gives."""

from __future__ import annotations

import multiprocessing
import sys

import pytest

from imucal_cli.config import parse_config
from imucal_cli.pipeline import estimate, stream_log
from imucal_cli.sim.writers import write_imu_log

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="solving apart forks")


@pytest.fixture(scope="module")
def streamed(tmp_path_factory, ideal_drive):
    """The 4-lidar ideal drive streamed from an MCAP: windows reduced, nothing solved."""
    log = write_imu_log(tmp_path_factory.mktemp("apart") / "d.mcap", "mcap", ideal_drive.topics())
    return stream_log(log, parse_config(ideal_drive.config_document(), "sim.config.yaml"))


def test_sensors_solved_apart_give_the_document_solved_in_one_process(streamed):
    """Half of the sensors solved in a forked child: every figure of the calibrate document is
    the one-process solve's, to the bit, and no process is left behind."""
    from imucal_cli.outputs import calibration_document

    def document(apart: bool) -> dict:
        result = estimate(streamed, apart=apart)
        return calibration_document(result, str(streamed.log), streamed.losses, streamed.counts())

    here, apart = document(False), document(True)
    assert len(here["sensors"]) == 4
    assert apart == here
    assert not multiprocessing.active_children()


def test_an_error_in_the_solving_child_is_the_solve_raised_here(streamed, monkeypatch):
    """A sensor whose solve fails in the child is solved again in this process, which raises
    the solve's own error (the message a user sees is the one-process run's)."""
    calibrator = streamed.calibrator
    names = list(calibrator.sensors)
    solve_one = type(calibrator).estimate

    def failing(self, name):
        if name == names[1]:  # solved in the child: the first sensor it takes
            raise ValueError(f"{name}: degenerate")
        return solve_one(self, name)

    monkeypatch.setattr(type(calibrator), "estimate", failing)
    with pytest.raises(Exception, match=f"numerically degenerate \\({names[1]}: degenerate\\)"):
        estimate(streamed, apart=True)
    assert not multiprocessing.active_children()
