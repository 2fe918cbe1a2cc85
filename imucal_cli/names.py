"""Names that come from users and logs: ROS's rules for frames, topics and sensor names, and
text made safe to show on a terminal.

A frame or sensor name goes into files other programs read or run (a tf2 launch script, a
Kalibr YAML, a URDF); a topic name read from a log goes to the terminal. ROS's own naming rules
(REP 144 for ROS 1 names, the ROS 2 topic and service name design) allow letters, digits,
underscores and ``/`` between tokens, which is what these checks accept: a name outside them is
refused where it enters (the config, a calibrate document), never quietly changed.
"""

from __future__ import annotations

import re

#: A tf frame: tokens of letters, digits and underscores joined by ``/``; the first starts with a
#: letter or underscore; no leading ``/`` (tf2 refuses one), no empty token.
FRAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z0-9_]+)*")
#: A topic: as a frame, with an optional leading ``/`` (and ``~`` for a private name).
TOPIC = re.compile(r"[/~]?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z0-9_]+)*")
#: A sensor name: one token (it is a YAML key, the default frame ``NAME_lidar`` and half of a
#: pair's ``a/b``).
SENSOR = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

RULES = {
    "frame": (
        FRAME,
        "letters, digits and '_' in tokens joined by '/', starting with a letter or '_' (ROS's "
        "rule)",
    ),
    "topic": (
        TOPIC,
        "letters, digits and '_' in tokens joined by '/', starting with '/' or a letter (ROS's "
        "rule)",
    ),
    "sensor": (SENSOR, "letters, digits and '_', starting with a letter or '_' (a ROS name token)"),
}


def name_problem(value: object, kind: str) -> str | None:
    """Why ``value`` is not a valid ROS name of ``kind`` (``frame``, ``topic``, ``sensor``),
    or ``None`` if it is one."""
    pattern, rule = RULES[kind]
    if not isinstance(value, str):
        return f"expected a {kind} name (a string), got {type(value).__name__}"
    if len(value) > 256:
        return f"a {kind} name of {len(value)} characters (at most 256)"
    if not pattern.fullmatch(value):
        return f"{quoted(value)} is not a valid {kind} name: {rule}"
    return None


def quoted(text: str) -> str:
    """``text`` made :func:`printable`, in single quotes (``repr`` would double every
    backslash of the escapes)."""
    return f"'{printable(text)}'"


_UNSAFE = re.compile(r"[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def printable(text: str) -> str:
    """``text`` with every control character (C0, DEL, C1, bidirectional overrides) written as
    its escape (``\\x1b``, ``\\n``): what a log or a config names can never move the cursor,
    retitle the terminal, end a line or fake one."""
    return _UNSAFE.sub(_escape, text)


def _escape(match: re.Match[str]) -> str:
    char = match.group()
    return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(char) or (
        f"\\x{ord(char):02x}" if ord(char) < 0x100 else f"\\u{ord(char):04x}"
    )


def quoteattr(text: str) -> str:
    """An XML attribute value: quoted, escaped, and without the control characters XML 1.0
    cannot hold at all (written as escapes: :func:`printable`). ``xml.sax.saxutils`` is
    imported when first used: it brings ``urllib`` and ``email``, 30 ms every command would
    pay."""
    from xml.sax.saxutils import quoteattr as quoted

    return quoted(printable(text))


def xml_text(text: str) -> str:
    """XML character data, as :func:`quoteattr`."""
    from xml.sax.saxutils import escape

    return escape(printable(text))
