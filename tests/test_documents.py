"""Documents are written as PyYAML (and json) write them: libyaml's emitter where PyYAML has
it, lists of rows a chunk at a time."""

from __future__ import annotations

import numpy as np
import yaml
from conftest import SAMPLE_DATA
from hypothesis import given, settings
from hypothesis import strategies as st

from imucal_cli.api import calibrate, segments
from imucal_cli.documents import Rows, dumps, to_plain


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


def _rows(items, size):
    """``items`` as a :class:`Rows` of chunks of ``size``."""
    return Rows(len(items), lambda: (items[a : a + size] for a in range(0, len(items), size)))


_KEYS = st.text("abz_019", min_size=1, max_size=12).filter(lambda k: not k[0].isdigit())


@st.composite
def _with_rows(draw, document=_DOCUMENTS):
    """A document some of whose lists (at any depth, in a mapping or a list) are :class:`Rows`
    of random chunks; and the same document with lists."""
    if draw(st.booleans()):
        items = draw(st.lists(st.dictionaries(st.text(), _DOCUMENTS, max_size=3), max_size=5))
        return _rows(items, draw(st.integers(1, 3))), items
    value = draw(document)
    if isinstance(value, dict) or draw(st.booleans()):
        keys = draw(st.lists(_KEYS | st.text(max_size=4), max_size=4, unique=True))
        pairs = [draw(_with_rows()) for _ in keys]
        return (
            {k: lazy for k, (lazy, _) in zip(keys, pairs, strict=True)},
            {k: listed for k, (_, listed) in zip(keys, pairs, strict=True)},
        )
    if isinstance(value, list) and value:
        pairs = [draw(_with_rows()) for _ in value]
        return [lazy for lazy, _ in pairs], [listed for _, listed in pairs]
    return value, value


@given(_KEYS, _with_rows())
@settings(max_examples=300, deadline=None)
def test_rows_are_written_as_the_lists_they_stand_for(key, documents):
    """A document with lists made as they are written (:class:`Rows`) is the same text, YAML and
    JSON, as the document with the lists: wherever they lie, in chunks of any size."""
    lazy, listed = ({key: documents[0]}, {key: documents[1]})
    for as_json in (False, True):
        assert dumps(lazy, as_json) == dumps(listed, as_json)


def test_a_long_segments_document_is_written_as_its_windows_come(tmp_path, monkeypatch):
    """``segments`` writes each sensor's windows a chunk at a time: the file is the document's
    text, YAML and JSON, for a drive whose windows were merged as it went."""
    from imucal_cli import outputs
    from imucal_cli.core import streaming
    from imucal_cli.documents import load_document, write_document

    monkeypatch.setattr(streaming, "FULL_WINDOWS", 2)
    monkeypatch.setattr(streaming, "MAX_UNITS", 5)
    monkeypatch.setattr(outputs, "ROWS_CHUNK", 7)
    config = load_document(SAMPLE_DATA / "aggressive.config.yaml")
    config["segments"]["window_s"] = 2.0
    write_document(tmp_path / "config.yaml", config)
    run = segments(SAMPLE_DATA / "aggressive.mcap", tmp_path / "config.yaml")
    listed = run.segments_document()
    for sensor in listed["sensors"].values():  # (every window, in time order)
        starts = [w["start_s"] for w in sensor["windows"]]
        assert len(starts) == sensor["total"] > 30 and starts == sorted(starts)
    monkeypatch.setattr(Rows, "__iter__", None)  # (no list is made of them: written by chunks)
    for suffix in (".yaml", ".json"):
        write_document(tmp_path / f"windows{suffix}", run.segments_document(streamed=True))
        written = (tmp_path / f"windows{suffix}").read_text()
        assert written == dumps(listed, as_json=suffix == ".json")
