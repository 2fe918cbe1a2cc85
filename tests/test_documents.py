"""Documents are written by libyaml's emitter where PyYAML has it, from nodes made without
PyYAML's representer: the same text as PyYAML's."""

from __future__ import annotations

import numpy as np
import yaml
from conftest import SAMPLE_DATA
from hypothesis import given, settings
from hypothesis import strategies as st

from imucal_cli.api import calibrate, segments
from imucal_cli.documents import dumps, to_plain


def test_the_written_yaml_is_pure_pythons_text():
    run = calibrate(SAMPLE_DATA / "aggressive.mcap", SAMPLE_DATA / "aggressive.config.yaml")
    windows = segments(SAMPLE_DATA / "aggressive.mcap", run.config).segments_document()
    for document in (run.document(), windows):
        expected = yaml.safe_dump(
            to_plain(document), sort_keys=False, default_flow_style=None, width=100
        )
        assert dumps(document, as_json=False) == expected


_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e16, 1e17, 1e-5, 123456789.0]),
    st.text(),
    st.sampled_from(["", "yes", "null", "~", "1e3", "0x1F", "- a", "a: b", " x", "#", "*a"]),
    # what to_plain turns into those
    st.floats().map(np.float64),
    st.integers(-(2**63), 2**63 - 1).map(np.int64),
    st.booleans().map(np.bool_),
    st.lists(st.floats(), max_size=3).map(np.array),
)
_DOCUMENTS = st.recursive(
    _SCALARS,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.lists(inner, max_size=3).map(tuple)
        | st.dictionaries(st.text() | st.integers(), inner, max_size=4)
    ),
    max_leaves=30,
)


@given(st.dictionaries(st.text(), _DOCUMENTS, max_size=6))  # a document is a mapping
@settings(max_examples=300, deadline=None)
def test_any_plain_document_is_written_as_pyyamls_representer_writes_it(document):
    # the same emitter (libyaml's writes some keys pure Python's does not: `{'': null}`)
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    expected = yaml.dump(
        to_plain(document), Dumper=dumper, sort_keys=False, default_flow_style=None, width=100
    )
    assert dumps(document, as_json=False) == expected
