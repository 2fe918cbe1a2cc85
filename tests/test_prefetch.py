"""Reading ahead in a child process gives the same batches, statistics and errors as inline."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from conftest import DATA

from imucal_cli.errors import ConfigError, LogError
from imucal_cli.io.logs import ImuBatches
from imucal_cli.io.prefetch import read_ahead

SAMPLE = DATA.parent.parent / "sample_data" / "aggressive.mcap"
TOPICS = ["/gnss/imu", "/lidar/front_left_top/imu", "/lidar/front_right_top/imu"]


def _all(batches):
    return [(topic, st.tobytes(), lt.tobytes(), g.tobytes(), a.tobytes()) for topic, st, lt, g, a in batches]


def test_child_process_reads_the_same_batches_and_stats_as_inline():
    inline = ImuBatches(SAMPLE, TOPICS)
    ahead = ImuBatches(SAMPLE, TOPICS)
    expected = _all(read_ahead(inline, background=False))
    got = _all(read_ahead(ahead))
    assert got == expected
    assert len(got) > 1
    assert {t: s.to_dict() for t, s in ahead.stats.items()} == {t: s.to_dict() for t, s in inline.stats.items()}
    assert sum(s.messages for s in ahead.stats.values()) == sum(len(np.frombuffer(b[1], np.int64)) for b in got)


def test_errors_in_the_child_are_raised_in_the_parent_with_their_message():
    reader = ImuBatches(SAMPLE, ["/gnss/imu", "/no/such/imu"])
    with pytest.raises(LogError) as inline:
        list(read_ahead(ImuBatches(SAMPLE, ["/gnss/imu", "/no/such/imu"]), background=False))
    with pytest.raises(LogError) as ahead:
        list(read_ahead(reader))
    assert str(ahead.value) == str(inline.value)
    assert "/no/such/imu" in str(ahead.value)


def test_leaving_early_stops_the_reader():
    batches = read_ahead(ImuBatches(SAMPLE, TOPICS))
    first = next(batches)
    assert first[0] in TOPICS
    batches.close()  # what a break or an exception in the consumer does


@pytest.mark.parametrize("error", [LogError("a.mcap", "cannot read", "/imu"), LogError("a.mcap", "bad"), ConfigError("c.yaml", "sensors[0].name", "missing")])
def test_errors_cross_processes_intact(error):
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is type(error) and str(again) == str(error) and again.__dict__ == error.__dict__
