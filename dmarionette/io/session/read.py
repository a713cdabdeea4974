"""Reading a session file (docs/session.md), whole or cut off by a crash.

A file still being written, or left by a crash, has no summary and no footer, and its last
record may be cut in the middle; ``mcap.reader.make_reader(f).iter_messages()`` refuses it
(it looks for the footer first). This reader walks the records from the start with the
``mcap`` package's own record parser (:class:`mcap.stream_reader.StreamReader`), stopping
at the last complete record, so it reads everything that reached the disk.
"""

from __future__ import annotations

import dataclasses
import io
import json
import struct
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from dmarionette.scene.bars import BarTrajectory
from dmarionette.scene.scene import Scene, scene_from_table
from dmarionette.io.session.validate import (
    SessionError,
    check_integrity,
    check_message,
    check_metadata,
    check_scene_consistency,
    decode_message,
    schema_of_topic,
)
from dmarionette.io.session.format import FORMAT, FORMAT_VERSION

__all__ = ["Session", "SessionError", "decode_session_metadata", "format_session_info", "read_session",
           "read_session_records", "session_bar_trajectories", "session_info"]

try:  # a zstd chunk that does not decompress is damage too (sessions are indexed with zstd)
    from zstandard import ZstdError
except ImportError:  # without zstandard such chunks are not read at all
    ZstdError = ValueError

_MAGIC = b"\x89MCAP0\r\n"
FOXGLOVE_PREFIX = "/foxglove/"  # the writer's viewer channels (protobuf, io/session/foxglove.py)
_INT_FIELDS = {"buttons", "taut"}


@dataclasses.dataclass
class _Records:
    """The raw records of a session file, up to its end or its last complete record."""

    header: Header | None
    metadata: dict[str, dict[str, str]]
    channels: dict[int, Channel]
    schemas: dict[int, Schema]
    messages: dict[int, list[Message]]
    truncated: bool
    size: int
    notes: list[str] = dataclasses.field(default_factory=list)
    in_file_order: list[Message] = dataclasses.field(default_factory=list)  # every message read, as written


def _read_records(path: Path, topics: Iterable[str] | None = None) -> _Records:
    """Reads the data section of ``path`` record by record; tolerant of a cut-off end."""
    if not path.is_file():
        raise SessionError.text(path, "no such session file")
    try:
        data = path.read_bytes()
    except OSError as error:
        raise SessionError(str(path), "(file)", f"an unreadable file ({error.strerror or error})",
                           "a readable session file") from None
    if not data.startswith(_MAGIC):
        raise SessionError.text(path, f"not an MCAP file (it does not start with the MCAP magic bytes "
                                f"{_MAGIC!r}; got {data[:8]!r}); a session is the .mcap file written by --record")
    # Walk the record lengths: the data section ends at DataEnd (or the footer, or the cut);
    # a damaged file (a record that does not parse, a CRC that does not match) is refused.
    end, truncated, notes, offsets = check_integrity(path, data)
    wanted = None if topics is None else set(topics)
    records = _Records(header=None, metadata={}, channels={}, schemas={}, messages=defaultdict(list),
                       truncated=truncated, size=len(data), notes=notes)
    # A chunk cut off (an indexed file cut short): the records its compressed prefix holds.
    tail = _cut_chunk_records(data, end) if truncated and end + 9 <= len(data) else b""
    reader = iter(StreamReader(io.BytesIO(data[len(_MAGIC):end] + tail), skip_magic=True, validate_crcs=True).records)
    count = 0
    chunked = any(data[o] == Opcode.CHUNK for o in offsets)
    expected = None if chunked else sum(1 for o in offsets if data[o] < 0x80)  # private records are skipped
    offsets = [] if chunked else [o for o in offsets if data[o] < 0x80]
    while True:
        try:
            record = next(reader)
            count += 1
        except StopIteration:
            if expected is not None and count < expected:  # a record swallowed the ones after it
                raise SessionError(str(path), "(file)", f"records that stop parsing at byte {offsets[count]} "
                                   f"({count} of {expected} read)", "a well-formed MCAP file: this one is "
                                   "damaged") from None
            break
        except (EndOfFile, McapError, ValueError, struct.error, UnicodeDecodeError, ZstdError) as error:
            # Every record up to ``end`` is complete: one that does not parse (or whose chunk CRC
            # does not match) is damage, not a cut.
            if isinstance(error, EndOfFile) and (expected is None or count >= expected):
                break  # every record read
            at = ""
            if count < len(offsets):  # the record there, or the one before it read too far
                at = f" at byte {offsets[count]}" + (f" (or the one before it, at byte {offsets[count - 1]})"
                                                    if count else "")
            raise SessionError(str(path), "(file)", f"a damaged MCAP record{at} ({type(error).__name__}: {error})",
                               "a well-formed MCAP file: this one is damaged") from None
        if isinstance(record, Message):
            channel = records.channels.get(record.channel_id)
            if channel is None:  # the writer registers every channel before its first message
                at = f" at byte {offsets[count - 1]}" if count - 1 < len(offsets) else ""
                raise SessionError(str(path), "(file)", f"a message{at} on channel id "
                                   f"{record.channel_id}, which no Channel record before it defines",
                                   "a well-formed MCAP file: this one is damaged")
            if wanted is None or channel.topic in wanted:
                records.messages[record.channel_id].append(record)
                records.in_file_order.append(record)
        elif isinstance(record, Channel):
            records.channels[record.id] = record
        elif isinstance(record, Schema):
            records.schemas[record.id] = record
        elif isinstance(record, Metadata):
            records.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Header):
            records.header = record
    return records


def _cut_chunk_records(data: bytes, offset: int) -> bytes:
    """The complete inner records of the cut-off Chunk record at ``offset``, decompressed as far
    as the bytes go; ``b""`` if it is not a chunk or its compression cannot be streamed."""
    if data[offset] != Opcode.CHUNK:
        return b""
    body = data[offset + 9:]
    head = 8 + 8 + 8 + 4  # start, end, uncompressed size, crc
    if len(body) < head + 4:
        return b""
    (name_length,) = struct.unpack_from("<I", body, head)
    start = head + 4 + name_length + 8  # compression name, records length
    if len(body) < start:
        return b""
    compression, records = body[head + 4:head + 4 + name_length].decode(errors="replace"), body[start:]
    if compression == "zstd":
        try:
            import zstandard
        except ImportError:
            return b""
        try:
            records = zstandard.ZstdDecompressor().decompressobj().decompress(records)
        except zstandard.ZstdError:
            return b""
    elif compression != "":
        return b""  # lz4: not streamed here
    end = 0  # up to the last complete record
    while end + 9 <= len(records):
        (length,) = struct.unpack_from("<Q", records, end + 1)
        if end + 9 + length > len(records):
            break
        end += 9 + length
    return records[:end]


def read_session_records(path: str | Path) -> _Records:
    """The raw ``mcap`` records of a session file (``header``, ``metadata`` by name, ``schemas``
    and ``channels`` by id, ``messages`` by channel id, ``truncated``), read up to the last
    complete record; for tools that rewrite a file (:mod:`dmarionette.io.session.index`)."""
    return _read_records(Path(path))


def decode_session_metadata(path: str | Path, records: _Records) -> tuple[dict[str, Any], dict[str, str]]:
    """The decoded ``"dmarionette"`` record and the ``"scene"`` record of ``records``;
    ``ValueError`` naming ``path`` when the file is not a dmarionette session."""
    return _session_metadata(Path(path), records)


def _session_metadata(path: Path, records: _Records) -> tuple[dict[str, Any], dict[str, str]]:
    """The decoded ``"dmarionette"`` record and the ``"scene"`` record, type-checked; clear errors if absent."""
    topics = sorted({c.topic for c in records.channels.values()})
    if "dmarionette" not in records.metadata and records.truncated and not records.channels:
        raise SessionError.text(path, f"an MCAP file cut off after {records.size} bytes, before its metadata "
                                "records (a recording that crashed at once): nothing to read")
    if "dmarionette" not in records.metadata:
        raise SessionError.text(path, f"an MCAP file, but not a dmarionette session: it has no 'dmarionette' "
                                f"metadata record (metadata found: {sorted(records.metadata)}; topics: {topics})")
    meta = {}
    for key, value in records.metadata["dmarionette"].items():
        try:
            meta[key] = json.loads(value)
        except json.JSONDecodeError as error:
            raise SessionError(f"{path}: metadata record 'dmarionette'", key, value,
                               f"a JSON value ({error})") from None
    required = ("string_hz", "puppet_hz", "bars", "strings", "bodies", "constants")
    missing = [k for k in required if k not in meta]
    if missing and meta.get("format") == FORMAT:
        raise SessionError.text(path, f"the 'dmarionette' metadata record lacks {missing}")
    scene = records.metadata.get("scene")
    if scene is None or "toml" not in scene:
        raise SessionError.text(path, "a dmarionette session without its 'scene' metadata record (or without "
                                "its 'toml' key): the scene cannot be rebuilt")
    check_metadata(path, meta, FORMAT, FORMAT_VERSION)
    return meta, scene


def _stack(values: list) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):  # ragged (an unchecked topic): keep the lists
        return np.asarray(values, dtype=object)


def _decode_topic(path: Path, topic: str, messages: list[Message], meta: dict[str, Any]) -> dict[str, np.ndarray]:
    """A topic's messages as arrays; the dmarionette topics are checked message by message."""
    kind = schema_of_topic(topic, meta["bars"])
    decoded = []
    origin = int(meta.get("log_time_origin_ns", 0))  # format 1: log time = simulated time
    for i, m in enumerate(messages):
        message = decode_message(path, topic, i, m.data, m.log_time - origin)
        if kind is not None:
            check_message(path, topic, kind, i, message, m.log_time - origin, meta)
        decoded.append(message)
    fields: dict[str, np.ndarray] = {"log_time": np.array([m.log_time for m in messages], dtype=np.int64)}
    keys = dict.fromkeys(k for d in decoded for k in d)  # optional fields too (missing: NaN)
    for key in keys:
        array = _stack([d.get(key) for d in decoded])
        if key in _INT_FIELDS and array.dtype != object:
            array = array.astype(np.int64)
        fields[key] = array
    return fields


@dataclasses.dataclass
class Session:
    """A session read back.

    Attributes:
        path: the file.
        metadata: the ``"dmarionette"`` record, decoded (``string_hz``, ``puppet_hz``, ``bars``,
            ``strings``, ``bodies``, ``constants``, ... see docs/session.md).
        scene_record: the ``"scene"`` record (``name``, ``source``, ``toml``, ``table_json``).
        extra_metadata: any other metadata record, by name (values JSON-decoded when they are JSON).
        scene: the scene rebuilt from the embedded TOML (its source is ``"<path>#scene"``), or
            ``None`` when not asked for.
        channels: topic -> field -> array: ``log_time`` [ns] ``(N,)``, ``t`` [s] ``(N,)`` and each
            message field stacked (``position`` ``(N, 3)``, ``body_pos`` ``(N, bodies, 3)``, ...).
        truncated: the file has no footer (cut off by a crash, or still being written).
        notes: lines worth showing (cut off; a damaged summary section; ...).
    """

    path: Path
    metadata: dict[str, Any]
    scene_record: dict[str, str]
    extra_metadata: dict[str, dict[str, Any]]
    scene: Scene | None
    channels: dict[str, dict[str, np.ndarray]]
    truncated: bool
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def bars(self) -> list[str]:
        return list(self.metadata["bars"])

    @property
    def strings(self) -> list[str]:
        return list(self.metadata["strings"])

    @property
    def bodies(self) -> list[str]:
        return list(self.metadata["bodies"])

    @property
    def string_hz(self) -> float:
        return float(self.metadata["string_hz"])

    @property
    def puppet_hz(self) -> float:
        return float(self.metadata["puppet_hz"])

    def require(self, topics: Iterable[str], purpose: str) -> None:
        """Raises ``ValueError`` naming the file and every topic of ``topics`` it lacks (or has empty)."""
        missing = [t for t in topics if len(self.channels.get(t, {}).get("t", ())) == 0]
        if missing:
            raise ValueError(f"{self.path}: {purpose} needs the channels {missing}, which this session "
                             f"does not have (it has {sorted(self.channels)})")

    def topic(self, topic: str) -> dict[str, np.ndarray]:
        """The arrays of one topic; ``ValueError`` naming the file when it is absent."""
        self.require([topic], f"reading {topic}")
        return self.channels[topic]


def read_session(path: str | Path, *, topics: Iterable[str] | None = None, load_scene: bool = True) -> Session:
    """Reads a session file, complete or cut off (everything up to the last complete record).

    Args:
        path: the ``.mcap`` file.
        topics: decode only these topics (all when ``None``).
        load_scene: rebuild the :class:`Scene` from the embedded TOML.

    Raises:
        ValueError: not an MCAP file, not a dmarionette session, metadata missing.
        SceneError: the embedded scene does not load.
    """
    path = Path(path)
    records = _read_records(path, topics)
    meta, scene_record = _session_metadata(path, records)
    extra = {}
    for name, values in records.metadata.items():
        if name not in ("dmarionette", "scene"):
            extra[name] = {k: _json_or_text(v) for k, v in values.items()}
    scene = None
    if load_scene:  # first: messages are checked against metadata that matches the scene
        scene = _load_scene(path, scene_record)
        check_scene_consistency(path, meta, scene)
    channels = {}
    notes = _notes(records)
    for channel_id, messages in records.messages.items():
        channel = records.channels[channel_id]
        if channel.message_encoding != "json" and schema_of_topic(channel.topic, meta["bars"]) is None:
            if not channel.topic.startswith(FOXGLOVE_PREFIX):  # the viewers' channels are not ours to decode
                notes.append(f"channel {channel.topic} ({channel.message_encoding} messages, not JSON) is not decoded")
            continue
        channels[channel.topic] = _decode_topic(path, channel.topic, messages, meta)
    return Session(path=path, metadata=meta, scene_record=scene_record, extra_metadata=extra, scene=scene,
                   channels=channels, truncated=records.truncated, notes=notes)


def _notes(records: _Records) -> list[str]:
    notes = list(records.notes)
    if records.truncated:
        notes.insert(0, "cut off: no footer (the recording crashed or is still being written); "
                        "everything up to the last complete record is read")
    return notes


def _json_or_text(value: str) -> Any:
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value


def _load_scene(path: Path, scene_record: dict[str, str]) -> Scene:
    """The scene from the self-contained table (``table_json``) or, failing that, the TOML text."""
    import tomllib

    source = f"{path}#scene"
    where = f"{path}: metadata record 'scene'"
    if "table_json" in scene_record:
        try:
            table = json.loads(scene_record["table_json"])
        except json.JSONDecodeError as error:
            raise SessionError(where, "table_json", scene_record["table_json"],
                               f"the scene's table as JSON ({error})") from None
        if not isinstance(table, dict):
            raise SessionError(where, "table_json", table, "the scene's table as a JSON object")
    else:
        try:
            table = tomllib.loads(scene_record["toml"])
        except tomllib.TOMLDecodeError as error:
            raise SessionError(where, "toml", scene_record["toml"], f"the scene's TOML text ({error})") from None
    return scene_from_table(table, source)


def session_info(path: str | Path, *, check_messages: bool = True) -> dict[str, Any]:
    """A summary of a session file.

    Its structure and metadata are checked as :func:`read_session` checks them and, with
    ``check_messages`` (default), every message of a dmarionette topic too (decoded, not
    kept), so a damaged file does not pass ``dmarionette info``.

    Returns:
        A JSON-ready dict: ``path``, ``bytes``, ``truncated`` (cut off: no footer),
        ``recorder``, ``created``, ``version``, ``scene``, ``scene_source``, ``string_hz``,
        ``puppet_hz``, ``bars``, ``strings``, ``bodies``, ``start`` and ``end`` [s],
        ``duration`` [s], ``messages``, ``topics`` (topic -> ``count``, ``rate_hz`` (mean),
        ``start``, ``end`` [s]), ``device_channels`` (whether device samples/forces were
        recorded) and ``notes`` (lines worth showing).

    Raises:
        SessionError: as :func:`read_session` (without rebuilding the scene).
    """
    path = Path(path)
    records = _read_records(path)
    meta, scene_record = _session_metadata(path, records)
    origin = int(meta.get("log_time_origin_ns", 0))  # format 1: log time = simulated time
    if check_messages:
        for channel_id, messages in records.messages.items():
            topic = records.channels[channel_id].topic
            kind = schema_of_topic(topic, meta["bars"])
            if kind is not None:
                for i, m in enumerate(messages):
                    log_time = m.log_time - origin
                    check_message(path, topic, kind, i, decode_message(path, topic, i, m.data, log_time),
                                  log_time, meta)
    topics = {}
    for channel_id, channel in sorted(records.channels.items()):
        times = (np.array([m.log_time for m in records.messages.get(channel_id, [])], dtype=np.int64) - origin) * 1e-9
        count = len(times)
        span = float(times.max() - times.min()) if count else 0.0
        topics[channel.topic] = {"count": count, "rate_hz": (count - 1) / span if count > 1 and span > 0 else 0.0,
                                 "start": float(times.min()) if count else None,
                                 "end": float(times.max()) if count else None}
    starts = [v["start"] for v in topics.values() if v["start"] is not None]
    ends = [v["end"] for v in topics.values() if v["end"] is not None]
    device = any(t.startswith("/device/") and v["count"] for t, v in topics.items())
    notes = _notes(records)
    if not device:
        notes.append("no device channels (/device/*): "
                     + ("a simulated session" if meta.get("recorder") == "simulation" else "no device was recorded"))
    missing_bars = [b for b in meta["bars"] if not topics.get(f"/bar/{b}/pose", {}).get("count")]
    if missing_bars:
        notes.append(f"no bar poses for {missing_bars}: replay is not possible")
    return {
        "path": str(path), "bytes": records.size, "truncated": records.truncated,
        "recorder": meta.get("recorder"), "created": meta.get("created"), "version": meta.get("version"),
        "scene": scene_record.get("name"), "scene_source": scene_record.get("source"),
        "string_hz": meta["string_hz"], "puppet_hz": meta["puppet_hz"],
        "bars": meta["bars"], "strings": meta["strings"], "bodies": meta["bodies"],
        "start": min(starts) if starts else None, "end": max(ends) if ends else None,
        "duration": (max(ends) - min(starts)) if starts else 0.0,
        "messages": sum(v["count"] for v in topics.values()),
        "topics": topics, "device_channels": device, "notes": notes,
    }


def format_session_info(info: dict[str, Any]) -> str:
    """:func:`session_info`'s summary as lines of text (what ``dmarionette info FILE`` prints)."""
    duration = info["duration"] or 0.0
    lines = [f"{info['path']}: dmarionette session, {info['bytes'] / 1e6:.2f} MB"
             + (" (CUT OFF: no footer)" if info["truncated"] else ""),
             f"  scene {info['scene']!r} ({info['scene_source']}), recorded by {info['recorder']} "
             f"on {info['created']} with dmarionette {info['version']}",
             f"  {duration:.3f} s simulated, {info['messages']} messages; strings at {info['string_hz']:g} Hz, "
             f"puppet at {info['puppet_hz']:g} Hz",
             f"  bars {info['bars']}, {len(info['strings'])} strings, {len(info['bodies'])} bodies",
             "  topics:"]
    width = max((len(t) for t in info["topics"]), default=0)
    for topic, v in info["topics"].items():
        span = f"{v['start']:.3f}-{v['end']:.3f} s" if v["count"] else "-"
        lines.append(f"    {topic:<{width}}  {v['count']:>8} msgs  {v['rate_hz']:>9.2f} Hz  {span}")
    lines += [f"  note: {note}" for note in info["notes"]]
    return "\n".join(lines)


def session_bar_trajectories(session: Session) -> dict[str, BarTrajectory]:
    """The recorded bar poses (``/bar/BAR/pose``) as the trajectories the simulator takes.

    Each is the C1 spline through the timed poses (exact at the recorded times); samples
    whose time does not increase, or with a non-finite value, are dropped. Bars without a
    pose channel are left out.
    """
    trajectories = {}
    for bar in session.bars:
        channel = session.channels.get(f"/bar/{bar}/pose")
        if channel is None or len(channel.get("t", ())) == 0:
            continue
        t, position, rotation = channel["t"], channel["position"], channel["rotation"]
        finite = np.isfinite(t) & np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(rotation), axis=1)
        t, position, rotation = t[finite], position[finite], rotation[finite]
        keep = np.concatenate([[True], t[1:] > np.maximum.accumulate(t)[:-1]]) if len(t) else np.zeros(0, bool)
        if not keep.any():
            raise SessionError(f"{session.path}: channel /bar/{bar}/pose", "position/rotation", "no finite pose "
                               f"in its {len(channel['t'])} messages", "at least one pose with finite numbers")
        trajectories[bar] = BarTrajectory(t[keep], position[keep], rotation[keep])
    return trajectories
