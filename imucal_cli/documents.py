"""YAML/JSON documents: strict loading (duplicate keys rejected) and atomic writing."""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from imucal_cli.errors import InputError

#: The largest YAML/JSON document read (a config, truth, estimate or reference: a few kB each;
#: a calibrate document of twenty sensors is under 100 kB). PyYAML parses about 300 kB/s.
MAX_DOCUMENT_BYTES = 1 << 20
#: The deepest nesting read (imucal's documents nest four deep) ...
MAX_DEPTH = 32
#: ... and the most values a document may expand to through its aliases (a "billion laughs"
#: document of 2 kB expands to 10^9).
MAX_VALUES = 200_000


class _StrictLoader(yaml.SafeLoader):
    """A safe loader that refuses duplicate mapping keys instead of keeping the last one, and
    documents nested deeper than :data:`MAX_DEPTH` or expanding to more than :data:`MAX_VALUES`."""

    depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise yaml.YAMLError(f"nested more than {MAX_DEPTH} deep")
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def get_single_node(self) -> Any:
        node = super().get_single_node()
        if node is not None and _expanded(node, {}) > MAX_VALUES:
            raise yaml.YAMLError(
                f"expands to more than {MAX_VALUES:,} values (through its aliases)"
            )
        return node


def _expanded(node: yaml.Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` stands for with every alias expanded (each shared node counted
    once per use, computed once: linear in the document's own size)."""
    if id(node) not in sizes:
        sizes[id(node)] = 1  # (a recursive alias counts once: the constructor refuses nothing here)
        children = node.value if isinstance(node.value, list) else []
        items = (
            [n for pair in children for n in pair]
            if isinstance(node, yaml.MappingNode)
            else children
        )
        sizes[id(node)] = min(1 + sum(_expanded(n, sizes) for n in items), MAX_VALUES + 1)
    return sizes[id(node)]


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    mapping: dict[Any, Any] = {}
    loader.flatten_mapping(node)
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in mapping:
            line = key_node.start_mark.line + 1
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (line {line})", key_node.start_mark
            )
        mapping[key] = loader.construct_object(value_node, deep=deep)
    return mapping


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_capped(path: Path, cap: int, what: str) -> bytes:
    """The bytes of the regular file ``path``, at most ``cap`` of them read (a larger file is
    refused as not ``what``; ``/dev/zero`` or a sparse file is never read whole); a FIFO or a
    device, which could block forever, is refused without opening it."""
    import stat

    try:
        if not stat.S_ISREG(path.stat().st_mode):
            raise InputError(f"{path}: not a regular file (a FIFO, a device or a folder)")
        with path.open("rb") as handle:
            data = handle.read(cap + 1)
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    if len(data) > cap:
        raise InputError(f"{path}: larger than {cap >> 20} MiB: not {what}")
    return data


def load_document(path: str | Path) -> Any:
    """Load a YAML or JSON file (JSON is YAML). Raises :class:`InputError` naming the file."""
    path = Path(path)
    data = read_capped(path, MAX_DOCUMENT_BYTES, "a config or calibration document")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except (ValueError, OverflowError) as exc:  # a scalar YAML builds and Python cannot hold
        problem = str(exc).splitlines()[0][:200]  # (a 5,000-digit int, the date 2001-13-45)
        raise InputError(f"{path}: a value that is no number or date: {problem}") from None
    except (yaml.YAMLError, RecursionError) as exc:
        problem = " ".join(str(exc).split())
        problem = (
            problem if len(problem) <= 300 else problem[:300] + " ..."
        )  # (a message quotes the document)
        raise InputError(f"{path}: not valid YAML/JSON: {problem}") from None


def to_plain(value: Any) -> Any:
    """Convert numpy scalars/arrays and tuples to plain Python for YAML/JSON."""
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_plain(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f + 0.0 if math.isfinite(f) else None  # (+ 0.0: -0.0 is written 0.0)
    return value


class Rows:
    """A list of mappings in a document, made as it is written: ``chunks()`` yields lists of its
    items, so a document of a day's windows is never held whole (:func:`dump_chunks`).
    ``length``: how many items there are."""

    def __init__(self, length: int, chunks: Callable[[], Iterator[list[Any]]]) -> None:
        self.length, self.chunks = length, chunks

    def __iter__(self) -> Iterator[Any]:
        for chunk in self.chunks():
            yield from chunk


def dumps(document: Any, as_json: bool) -> str:
    """Serialise a document as JSON (indented) or YAML: block style, a collection of scalars
    only in flow style, keys in their order."""
    return "".join(dump_chunks(document, as_json))


def _dumps(plain: Any, as_json: bool) -> str:
    if as_json:
        return json.dumps(plain, indent=2) + "\n"
    # libyaml's emitter where PyYAML has it: the same text, three times as fast
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    return yaml.dump(plain, Dumper=dumper, sort_keys=False, default_flow_style=None, width=100)


_HOLE = "@imucal-rows-{}@"
_HOLES = {
    False: re.compile(
        r"^(?P<indent> *)(?P<key>[A-Za-z_]\w*): \['@imucal-rows-(?P<k>\d+)@'\]\n", re.M
    ),
    True: re.compile(r"\[\n(?P<indent> *)\"@imucal-rows-(?P<k>\d+)@\"\n *\]", re.M),
}


def dump_chunks(document: Any, as_json: bool) -> Iterator[str]:
    """:func:`dumps`' text in pieces, each :class:`Rows` of the document written a chunk at a
    time: the same text as the document with lists in their place. (A :class:`Rows` is
    written so only as a mapping's value under a plain key; elsewhere it is made a list.)"""
    rows: list[Rows] = []

    def hole(value: Any) -> Any:
        if isinstance(value, Rows):
            rows.append(value)
            return [_HOLE.format(len(rows) - 1)]
        if isinstance(value, dict):
            return {k: hole(v) for k, v in value.items()}
        return [hole(v) for v in value] if isinstance(value, list) else value

    text = _dumps(hole(to_plain(document)), as_json)
    holes = list(_HOLES[as_json].finditer(text))
    if len(holes) != len(rows):  # (a Rows in a list or under a key YAML writes otherwise)
        yield _dumps(to_plain(_listed(document)), as_json)
        return
    done = 0
    for match in holes:
        yield text[done : match.start()]
        done = match.end()
        lazy, indent = rows[int(match["k"])], match["indent"]
        if as_json:
            yield "[\n" if lazy.length else "[]"
            if lazy.length:
                yield from _json_items(lazy, indent)
                yield "\n" + indent[:-2] + "]"
        else:
            yield f"{indent}{match['key']}:{'' if lazy.length else ' []'}\n"
            if lazy.length:
                yield from _yaml_items(lazy, len(indent) // 2)
    yield text[done:]


def _listed(value: Any) -> Any:
    if isinstance(value, Rows):
        return [_listed(v) for v in value]
    if isinstance(value, dict):
        return {k: _listed(v) for k, v in value.items()}
    return [_listed(v) for v in value] if isinstance(value, list) else value


def _json_items(lazy: Rows, indent: str) -> Iterator[str]:
    # (json indents by depth alone: an item dumped alone, each line moved in, is the same text)
    between = ""
    for chunk in lazy.chunks():
        if chunk:
            yield between + ",\n".join(
                indent + json.dumps(to_plain(item), indent=2).replace("\n", "\n" + indent)
                for item in chunk
            )
            between = ",\n"


def _yaml_items(lazy: Rows, depth: int) -> Iterator[str]:
    # (a YAML line's wrapping depends on its column: each chunk is dumped at the list's depth,
    # under keys of one line each, which are then taken off)
    for chunk in lazy.chunks():
        if not all(isinstance(item, dict) for item in chunk):  # (YAML writes scalars in flow)
            raise TypeError("a Rows holds mappings")
        nested: Any = to_plain(chunk)
        for _ in range(depth + 1):
            nested = {"k": nested}
        text = _dumps(nested, as_json=False)
        yield text.split("\n", depth + 1)[depth + 1]


def write_document(path: str | Path, document: Any) -> None:
    """Write ``document`` as YAML (``.yaml``/``.yml``) or JSON (``.json``), atomically.

    The text goes to a temporary file in the same folder, which is renamed over ``path`` only
    once it is complete: a failed or interrupted run leaves no partial file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in {".yaml", ".yml", ".json"}:
        raise InputError(f"{path}: output must end in .yaml, .yml or .json")
    write_chunks_atomic(path, dump_chunks(document, as_json=suffix == ".json"))


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write text to ``path`` through a temporary file and a rename."""
    write_chunks_atomic(path, [text])


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_chunks_atomic(path: str | Path, chunks: Iterable[str | bytes]) -> None:
    """Write the text or bytes ``chunks`` make, one after the other, to ``path`` through a
    temporary file and a rename (the file appears whole or not at all)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{path}: output folder {folder} does not exist")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:  # a read-only folder
        raise InputError(f"{path}: cannot write in {folder}: {exc.strerror}") from None
    try:
        os.chmod(tmp_name, 0o666 & ~_umask())  # mkstemp makes 0600; use the usual mode
        with os.fdopen(fd, "wb") as handle:
            for chunk in chunks:
                handle.write(chunk.encode("utf-8") if isinstance(chunk, str) else chunk)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except BaseException as exc:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):  # a full disk, say: one line, no partial file
            raise InputError(f"{path}: cannot write: {exc.strerror or exc}") from None
        raise
