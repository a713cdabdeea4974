"""Checks of a session file's structure, metadata and messages (docs/session.md).

Every check raises :class:`SessionError` naming the file, where in it (the metadata record,
or the channel and the message number and time), the key, the value received and what was
expected. :func:`check_integrity` uses the MCAP record structure and CRCs to tell a
damaged file (refused, with the byte offset where known) from one cut off by a crash (read
up to its last complete record, with a note).
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any


__all__ = ["SessionError", "check_integrity", "check_message", "check_metadata", "check_scene_consistency",
           "decode_message", "schema_of_topic"]

_MAGIC = b"\x89MCAP0\r\n"
_OPCODE_DATA_END = 0x0F
_OPCODE_FOOTER = 0x02
_MISSING = object()


class SessionError(ValueError):
    """A session file that cannot be used as it is (damaged, or not what the format says).

    Attributes:
        where: the file and the place in it (``"take.mcap: channel /bar/main/pose, message #3 (t = 0.002 s)"``).
        key: the offending key or field (``"(file)"`` for the file's structure).
        received: the value found.
        expected: what would have been accepted.
    """

    def __init__(self, where: str, key: str, received: Any, expected: str, *, message: str | None = None):
        self.where = where
        self.key = key
        self.received = received
        self.expected = expected
        got = "nothing (missing)" if received is _MISSING else _short(received)
        super().__init__(message if message is not None else f"{where}: key '{key}': got {got}; expected {expected}")

    @classmethod
    def text(cls, path: Path | str, message: str, key: str = "(file)") -> SessionError:
        """An error whose message is ``"PATH: message"``."""
        return cls(str(path), key, None, "", message=f"{path}: {message}")


def _short(value: Any) -> str:
    text = value if isinstance(value, str) and value.startswith(("bytes", "a ", "an ", "CRC")) else repr(value)
    return text if len(text) <= 200 else text[:200] + "..."


# File structure ------------------------------------------------------------------------------


def check_integrity(path: Path, data: bytes) -> tuple[int, bool, list[str], list[int]]:
    """Walks the MCAP records of ``data``: where the data section ends, whether the file was cut
    off, and notes; refuses a damaged file.

    A complete file (ending in the magic bytes) must reach its ``DataEnd`` record through
    well-formed records, and the CRC that ``DataEnd`` stores (the mcap writer computes it
    over every byte before it) must match; a footer whose summary CRC does not match is
    noted (the messages are read from the data section, which is intact). A file cut off by
    a crash (no footer) is read up to its last complete record.

    Returns:
        ``(end, truncated, notes, offsets)``: the offset of the end of the last data record,
        whether the file was cut off, lines worth showing, and the byte offset of each data
        record (to say where a record that does not parse is).

    Raises:
        SessionError: a record with an unknown opcode, a complete file whose records do not
            reach its footer, or a data-section CRC that does not match.
    """
    complete = len(data) >= 2 * len(_MAGIC) and data.endswith(_MAGIC)
    offset, notes, offsets = len(_MAGIC), [], []
    while offset + 9 <= len(data):
        opcode = data[offset]
        (length,) = struct.unpack_from("<Q", data, offset + 1)
        if opcode == 0 or 0x10 <= opcode < 0x80:
            raise SessionError(f"{path}", "(file)", f"bytes that are not an MCAP record at byte {offset} "
                               f"(opcode 0x{opcode:02x})", "a well-formed MCAP file: this one is damaged")
        if offset + 9 + length > len(data):
            if complete:
                raise SessionError(f"{path}", "(file)", f"a record at byte {offset} whose length ({length} bytes) "
                                   f"runs past the end of the file ({len(data)} bytes)",
                                   "a well-formed MCAP file: this one is damaged")
            return offset, True, notes, offsets  # the last record was cut off by a crash
        if opcode == _OPCODE_DATA_END:
            if length >= 4:
                (crc,) = struct.unpack_from("<I", data, offset + 9)
                actual = zlib.crc32(data[:offset])
                if crc != 0 and crc != actual:
                    raise SessionError(f"{path}", "(file)", f"CRC 0x{actual:08x} over bytes 0-{offset} (the data "
                                       f"section)", f"the CRC stored in its DataEnd record (0x{crc:08x}): the file "
                                       "is damaged between its start and byte " f"{offset}")
            if not complete:
                notes.append("the file's data section is complete (it reaches its DataEnd record) but the file "
                             "does not end with the MCAP magic bytes: its summary or footer is cut off or damaged")
                return offset, False, notes, offsets
            _check_summary(data, notes)
            return offset, False, notes, offsets
        if opcode == _OPCODE_FOOTER:
            return offset, not complete, notes, offsets
        offsets.append(offset)
        offset += 9 + length
    if complete:
        raise SessionError(f"{path}", "(file)", f"records that end at byte {offset} without a DataEnd or Footer "
                           "record", "a well-formed MCAP file: this one is damaged")
    return offset, True, notes, offsets


def _check_summary(data: bytes, notes: list[str]) -> None:
    footer = len(data) - len(_MAGIC) - (9 + 20)
    if footer < 0 or data[footer] != _OPCODE_FOOTER:
        notes.append("the footer is damaged (the messages were read from the data section, which is intact)")
        return
    summary_start, _, crc = struct.unpack_from("<QQI", data, footer + 9)
    if crc == 0 or summary_start == 0:
        return
    if summary_start > footer or zlib.crc32(data[footer:footer + 9 + 16], zlib.crc32(data[summary_start:footer])) != crc:
        notes.append(f"the summary section (bytes {summary_start}-{footer}) is damaged: its CRC does not match "
                     "(the messages were read from the data section, which is intact)")


# Metadata ------------------------------------------------------------------------------------


def _names(meta: Mapping[str, Any], key: str, where: str, allow_empty: bool = True) -> list[str]:
    value = meta.get(key, _MISSING)
    ok = isinstance(value, list) and all(isinstance(v, str) and v for v in value) and len(set(value)) == len(value)
    if not ok or (not allow_empty and not value):
        raise SessionError(where, key, value, "a list of distinct non-empty names")
    return value


def _rate(meta: Mapping[str, Any], key: str, where: str) -> float:
    value = meta.get(key, _MISSING)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0.0 < value <= 1.0e6:
        raise SessionError(where, key, value, "a rate in Hz, a finite number > 0 and <= 1e6")
    return float(value)


def check_metadata(path: Path, meta: Mapping[str, Any], format_name: str, format_version: int) -> None:
    """Type-checks the decoded ``"dmarionette"`` metadata record.

    Raises:
        SessionError: naming the key.
    """
    where = f"{path}: metadata record 'dmarionette'"
    if meta.get("format") != format_name:
        raise SessionError(where, "format", meta.get("format", _MISSING), repr(format_name))
    version = meta.get("format_version", _MISSING)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise SessionError(where, "format_version", version, "an integer >= 1")
    if version > format_version:
        raise SessionError(where, "format_version", version,
                           f"a version up to {format_version}, the newest this dmarionette reads (upgrade dmarionette)")
    string_hz = _rate(meta, "string_hz", where)
    puppet_hz = _rate(meta, "puppet_hz", where)
    if puppet_hz > string_hz:
        raise SessionError(where, "puppet_hz", puppet_hz, f"a rate <= string_hz ({string_hz:g} Hz)")
    bars = _names(meta, "bars", where)
    strings = _names(meta, "strings", where)
    _names(meta, "bodies", where)
    constants = meta.get("constants", _MISSING)
    if not isinstance(constants, dict):
        raise SessionError(where, "constants", constants, "a table of the scene's constants")
    recorded = constants.get("strings", {})
    if not isinstance(recorded, dict) or not all(isinstance(v, dict) for v in recorded.values()):
        raise SessionError(where, "constants.strings", recorded, "a table: string name -> its constants")
    for key in ("feedback", "contact", "world", "initial_pose"):
        if key in constants and not isinstance(constants[key], dict):
            raise SessionError(where, f"constants.{key}", constants[key], "a table")
    for key in ("stiffness", "damping"):
        if "feedback" in constants:
            _finite_number(constants["feedback"].get(key, _MISSING), where, f"constants.feedback.{key}")
    if "world" in constants:
        world = constants["world"]
        gravity = world.get("gravity", _MISSING)
        if not (isinstance(gravity, list) and len(gravity) == 3):
            raise SessionError(where, "constants.world.gravity", gravity, "three numbers [m/s^2]")
        for c in gravity:
            _finite_number(c, where, "constants.world.gravity")
        _finite_number(world.get("ground_height", _MISSING), where, "constants.world.ground_height")
    if "string_bars" in meta:
        value = meta["string_bars"]
        if not isinstance(value, list) or len(value) != len(strings) or \
                not all(v is None or v in bars for v in value):
            raise SessionError(where, "string_bars", value, f"one bar name (or null) per string ({len(strings)})")
    if "bar_attach" in meta:
        value = meta["bar_attach"]
        ok = isinstance(value, dict) and sorted(value) == sorted(bars) and all(
            isinstance(points, dict) and all(
                isinstance(p, list) and len(p) == 3 and all(_is_number(c, nullable=False) and math.isfinite(c)
                                                            for c in p) for p in points.values())
            for points in value.values())
        if not ok:
            raise SessionError(where, "bar_attach", value, f"per bar ({bars}) a table: string -> attach point "
                               "[x, y, z] in the bar frame [m]")
    if "puppet_substeps" in meta:
        value = meta["puppet_substeps"]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SessionError(where, "puppet_substeps", value, "an integer >= 1")
    if "joint_q_layout" in meta:
        layout = meta["joint_q_layout"]
        ok = isinstance(layout, list) and all(
            isinstance(e, list) and len(e) == 3 and isinstance(e[0], str) and isinstance(e[1], str)
            and isinstance(e[2], int) and not isinstance(e[2], bool) and e[2] >= 0 for e in layout)
        if not ok:
            raise SessionError(where, "joint_q_layout", layout, "a list of [joint, type, coordinate count]")


def _finite_number(value: Any, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SessionError(where, key, value, "a finite number")
    return float(value)


def check_scene_consistency(path: Path, meta: Mapping[str, Any], scene) -> None:
    """The metadata's bars, strings and bodies against the embedded scene's."""
    where = f"{path}: metadata record 'dmarionette'"
    bars = [b.name for b in scene.bars]
    if list(meta["bars"]) != bars:
        raise SessionError(where, "bars", meta["bars"], f"the embedded scene's bars {bars}")
    strings = [s.name for s in scene.strings]
    if list(meta["strings"]) != strings:
        raise SessionError(where, "strings", meta["strings"], f"the embedded scene's strings {strings}")
    if scene.puppet is not None:
        bodies = [b.name for b in scene.puppet.bodies] + (["ball"] if scene.ball is not None else [])
        if list(meta["bodies"]) != bodies:
            raise SessionError(where, "bodies", meta["bodies"], f"the embedded scene's bodies {bodies}")
    recorded = meta["constants"].get("strings", {})
    if recorded and sorted(recorded) != sorted(strings):
        raise SessionError(where, "constants.strings", sorted(recorded), f"the embedded scene's strings {sorted(strings)}")


# Messages ------------------------------------------------------------------------------------

# schema kind -> field -> (shape, required): shape () a number, (n,) n numbers, ("bodies", k) one row of k
# per body, ("strings",) one 0/1 per string, ("joint_q",) one number per generalised coordinate.
_FIELDS: dict[str, dict[str, tuple[tuple, bool]]] = {
    "device/sample": {"position": ((3,), True), "orientation": ((4,), True), "buttons": (("int",), True),
                      "device_time": ((), False)},
    "device/force": {"force": ((3,), True)},
    "bar/pose": {"position": ((3,), True), "rotation": ((3,), True)},
    "bar/feedback": {"eq4": ((3,), True), "reaction": ((3,), True)},
    "strings/taut": {"taut": (("strings",), True)},
    "puppet/state": {"joint_q": (("joint_q",), True), "body_pos": (("bodies", 3), True),
                     "body_rot": (("bodies", 4), True)},
}


def schema_of_topic(topic: str, bars: list[str]) -> str | None:
    """The message kind of a dmarionette topic (``"bar/pose"``), or ``None`` for another topic."""
    if topic == "/strings/taut":
        return "strings/taut"
    if topic == "/puppet/state":
        return "puppet/state"
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == "" and parts[1] in ("bar", "device"):
        kind = f"{parts[1]}/{parts[3]}"
        return kind if kind in _FIELDS else None
    return None


def decode_message(path: Path, topic: str, index: int, data: bytes, log_time: int) -> dict:
    """A message's JSON object; refuses bytes that are not a JSON object."""
    where = f"{path}: channel {topic}, message #{index + 1} (log time {log_time * 1e-9:.6g} s)"
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SessionError(where, "(message)", f"bytes that are not JSON ({error})", "a JSON object") from None
    if not isinstance(value, dict):
        raise SessionError(where, "(message)", f"a JSON {type(value).__name__}", "a JSON object {\"t\": ..., ...}")
    return value


def _is_number(v: Any, nullable: bool = True) -> bool:
    return (v is None and nullable) or (isinstance(v, (int, float)) and not isinstance(v, bool))


def check_message(path: Path, topic: str, kind: str, index: int, message: dict, log_time: int,
                  meta: Mapping[str, Any]) -> None:
    """Checks one decoded message of a dmarionette topic against its schema and the metadata.

    Numbers may be ``null`` (the writer stores a non-finite value so); lengths must match
    the schema and the metadata (one taut flag per string, one body row per body, one
    coordinate per ``joint_q_layout`` entry); ``t`` must be a finite time matching the
    message's log time.
    """
    t = message.get("t", _MISSING)
    where = f"{path}: channel {topic}, message #{index + 1} (log time {log_time * 1e-9:.6g} s)"
    if not _is_number(t, nullable=False) or not math.isfinite(t) or t < 0.0:
        raise SessionError(where, "t", t, "a finite time >= 0 [s]")
    if abs(t * 1e9 - log_time) > 0.5 + 1e-15 * t * 1e9:  # the writer stores log_time = round(t * 1e9)
        raise SessionError(where, "t", t, f"the message's log time ({log_time * 1e-9:.9g} s)")
    coordinates = sum(e[2] for e in meta.get("joint_q_layout", [])) if "joint_q_layout" in meta else None
    for key, (shape, required) in _FIELDS[kind].items():
        value = message.get(key, _MISSING)
        if value is _MISSING:
            if required:
                raise SessionError(where, key, value, "a value (the field is required)")
            continue
        if shape == ():
            ok, what = _is_number(value), "a number"
        elif shape == ("int",):
            ok, what = isinstance(value, int) and not isinstance(value, bool), "an integer"
        elif shape == ("strings",):
            n = len(meta["strings"])
            ok = isinstance(value, list) and len(value) == n and all(v in (0, 1) and not isinstance(v, bool)
                                                                      for v in value)
            what = f"one flag 0 or 1 per string ({n}: {meta['strings']})"
        elif shape == ("joint_q",):
            ok = isinstance(value, list) and all(_is_number(v) for v in value) and (
                coordinates is None or len(value) == coordinates)
            what = f"a list of {coordinates if coordinates is not None else 'the'} generalised coordinates"
        elif shape[0] == "bodies":
            n, k = len(meta["bodies"]), shape[1]
            ok = isinstance(value, list) and len(value) == n and all(
                isinstance(row, list) and len(row) == k and all(_is_number(v) for v in row) for row in value)
            what = f"one row of {k} numbers per body ({n})"
        else:
            ok = isinstance(value, list) and len(value) == shape[0] and all(_is_number(v) for v in value)
            what = f"a list of {shape[0]} numbers"
        if not ok:
            raise SessionError(where, key, value, what)
