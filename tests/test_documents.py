"""Documents are written by libyaml's emitter where PyYAML has it: the same text as PyYAML's."""

from __future__ import annotations

import yaml
from conftest import SAMPLE_DATA

from imucal_cli.documents import dumps, to_plain
from imucal_cli.pipeline import calibrate_log, stream_log


def test_the_written_yaml_is_pure_pythons_text():
    run = calibrate_log(SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml")
    from imucal_cli.outputs import segments_document

    streamed = stream_log(SAMPLE_DATA / "aggressive.mcap", run.result.config)
    segments = segments_document(streamed.t0_ns, run.result.config, streamed.calibrator)
    for document in (run.document, segments):
        expected = yaml.safe_dump(
            to_plain(document), sort_keys=False, default_flow_style=None, width=100
        )
        assert dumps(document, as_json=False) == expected
