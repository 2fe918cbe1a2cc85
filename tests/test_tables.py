"""What a person reads of a document: the lines of the follow view before its first estimate."""

from __future__ import annotations

from imucal_cli import tables


def test_the_waiting_line_says_each_sensor_s_samples_and_what_the_first_waits_for():
    state = {
        "base_samples": 1200,
        "sensors": {
            "front_left_top": {"samples": 12345, "windows": 0, "waiting_for": "the base's boot"},
            "rear": {"samples": 7, "windows": 0, "waiting_for": "data"},
        },
    }
    line = tables.waiting_line("live.mcap", state)
    assert line == (
        "following live.mcap: front_left_top 12,345 samples, rear 7 samples; "
        "waiting for the base's boot"
    )
