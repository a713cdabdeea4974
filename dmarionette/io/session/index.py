"""Rewriting a session file chunked, indexed and zstd-compressed (``dmarionette session index``).

A recording is written unchunked, record by record, so that a crash leaves a readable file
(docs/session.md). When it closes normally, :class:`SessionWriter` calls :func:`index_session`,
which rewrites it the way viewers want it: zstd-compressed chunks with chunk and message
indexes and a summary (Rerun's MCAP importer reads only indexed files; Foxglove seeks by the
indexes). For a file left by a crash, ``dmarionette session index FILE`` does the same with
everything up to the last complete record.

An old session (format version 1: log time = simulated time, no Foxglove channels) is
converted: log times become wall-clock (the recording's ``created`` time plus the simulated
time) and the Foxglove channels are added from the recorded bar poses and puppet states.
"""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from dmarionette.io.session.read import decode_session_metadata, read_session, read_session_records
from dmarionette.io.session.format import FORMAT_VERSION

__all__ = ["CHUNK_BYTES", "index_session"]

#: Chunk size of an indexed session [bytes] (uncompressed).
CHUNK_BYTES = 1 << 20


def _created_ns(meta: dict[str, Any]) -> int:
    try:
        created = datetime.datetime.fromisoformat(str(meta.get("created")))
    except ValueError:
        return 0
    if created.tzinfo is None:
        created = created.replace(tzinfo=datetime.timezone.utc)
    return int(created.timestamp()) * 1_000_000_000


def _latest(times: np.ndarray, t: float) -> int:
    """Index of the last of ``times`` at or before ``t`` (the first one if none)."""
    return max(int(np.searchsorted(times, t + 1e-12, side="right")) - 1, 0)


def _foxglove_messages(path: Path, meta: dict[str, Any], origin: int) -> list[tuple[str, str, int, bytes]]:
    """(topic, schema, log_time, data) of the Foxglove channels, built from the recorded channels."""
    from dmarionette.io.session.foxglove import FoxglovePuppet

    bars = list(meta["bars"])
    topics = ["/puppet/state", "/strings/taut"] + [f"/bar/{b}/{k}" for b in bars for k in ("pose", "feedback")]
    try:
        session = read_session(path, topics=topics)
    except Exception:  # noqa: BLE001 - the scene does not load: draw without shapes
        session = read_session(path, topics=topics, load_scene=False)
    puppet = session.channels.get("/puppet/state")
    if puppet is None or not len(puppet["t"]):
        return []
    builder = FoxglovePuppet(meta, session.scene)
    poses = {b: session.channels[f"/bar/{b}/pose"] for b in bars if f"/bar/{b}/pose" in session.channels}
    feedback = {b: session.channels[f"/bar/{b}/feedback"] for b in bars if f"/bar/{b}/feedback" in session.channels}
    taut = session.channels.get("/strings/taut")
    out = []
    for k, t in enumerate(puppet["t"]):
        t = float(t)
        log_time = origin + int(round(t * 1e9))
        bar_poses = {}
        for b, c in poses.items():
            i = _latest(c["t"], t)
            bar_poses[b] = (c["position"][i], c["rotation"][i])
        reactions = {b: c["reaction"][_latest(c["t"], t)] for b, c in feedback.items() if c["t"][0] <= t + 1e-12}
        flags = taut["taut"][_latest(taut["t"], t)] if taut is not None and taut["t"][0] <= t + 1e-12 else None
        args = (log_time, t, bar_poses, puppet["body_pos"][k], puppet["body_rot"][k])
        out.append(("/foxglove/transforms", "foxglove.FrameTransforms", log_time, builder.transforms(*args)))
        out.append(("/foxglove/scene", "foxglove.SceneUpdate", log_time,
                    builder.scene_update(*args, reactions=reactions, taut=flags)))
        out.append(("/foxglove/points", "foxglove.PointCloud", log_time, builder.points(*args)))
    return out


def index_session(path: str | Path, output: str | Path | None = None, *, foxglove: bool = True,
                  chunk_bytes: int = CHUNK_BYTES) -> dict[str, Any]:
    """Rewrites a session file chunked, indexed and zstd-compressed.

    Args:
        path: the session (complete, cut off by a crash, or of format version 1).
        output: where to write (default: replace ``path``, through a temporary file beside it).
        foxglove: add the Foxglove channels when the file lacks them (needs
            ``foxglove-schemas-protobuf``; without it the file is only indexed).
        chunk_bytes: chunk size [bytes] before compression.

    Returns:
        A report: ``path``, ``messages``, ``truncated`` (the input had no footer),
        ``converted_from`` (the input's format version when it was older, else ``None``),
        ``foxglove_added`` (messages added), ``notes``.

    Raises:
        ValueError: not an MCAP file or not a dmarionette session (naming the file).
    """
    path = Path(path)
    output = Path(output) if output is not None else path
    records = read_session_records(path)
    meta, _ = decode_session_metadata(path, records)
    version = int(meta.get("format_version", 1))
    notes: list[str] = []
    shift = 0
    metadata = {name: dict(values) for name, values in records.metadata.items()}
    if "log_time_origin_ns" not in meta:  # version 1: log time was the simulated time
        shift = _created_ns(meta)
        meta["log_time_origin_ns"] = shift
        notes.append(f"log times moved from simulated time to wall-clock time (+{shift} ns: 'created' "
                     f"{meta.get('created')})")
    origin = int(meta["log_time_origin_ns"])
    meta["format_version"] = FORMAT_VERSION
    meta["time"] = "log_time = publish_time = log_time_origin_ns + simulated time [ns]; every message also holds t [s]"
    metadata["dmarionette"] = {k: json.dumps(v) for k, v in meta.items()}

    has_foxglove = any(c.topic.startswith("/foxglove/") for c in records.channels.values())
    added: list[tuple[str, str, int, bytes]] = []
    if foxglove and not has_foxglove:
        try:
            added = _foxglove_messages(path, meta, origin)
        except ImportError as error:
            notes.append(f"indexed only: the Foxglove channels need foxglove-schemas-protobuf ({error}); "
                         "pip install -e '.[io]'")
        else:
            if not added:
                notes.append("indexed only: no /puppet/state to draw the Foxglove channels from")

    temporary = output.with_name(output.name + ".indexing")
    try:
        messages = _write_indexed(temporary, records, metadata, shift, added, chunk_bytes)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    os.replace(temporary, output)
    if records.truncated:
        notes.insert(0, "the input was cut off (no footer): everything up to its last complete record is kept")
    return {"path": str(output), "messages": messages, "truncated": records.truncated,
            "converted_from": version if version < FORMAT_VERSION else None, "foxglove_added": len(added),
            "notes": notes}


def _write_indexed(temporary: Path, records, metadata: dict, shift: int, added: list, chunk_bytes: int) -> int:
    """Writes the chunked, indexed, zstd file; returns the number of messages."""
    with temporary.open("wb") as f:
        writer = Writer(f, chunk_size=int(chunk_bytes), compression=CompressionType.ZSTD, use_chunking=True)
        header = records.header
        writer.start(profile=header.profile if header else "", library=header.library if header else "dmarionette")
        for name, values in metadata.items():
            writer.add_metadata(name, values)
        schema_ids = {old: writer.register_schema(s.name, s.encoding, s.data) for old, s in records.schemas.items()}
        channel_ids = {old: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0),
                                                    dict(c.metadata))
                       for old, c in records.channels.items()}
        messages = [(m.log_time + shift, m.publish_time + shift, channel_ids[m.channel_id], m.sequence, m.data)
                    for m in records.in_file_order]
        if added:
            from dmarionette.io.session.foxglove import FOXGLOVE_TOPICS, file_descriptor_set

            ids = {}
            for topic, name in FOXGLOVE_TOPICS.items():
                schema = writer.register_schema(name, SchemaEncoding.Protobuf, file_descriptor_set(name))
                ids[topic] = writer.register_channel(topic, MessageEncoding.Protobuf, schema)
            sequence = dict.fromkeys(ids, 0)
            for topic, _, log_time, data in added:
                messages.append((log_time, log_time, ids[topic], sequence[topic], data))
                sequence[topic] += 1
        messages.sort(key=lambda m: m[0])  # stable: at equal times, the order they were written in
        for log_time, publish_time, channel, sequence, data in messages:
            writer.add_message(channel, log_time, data, publish_time, sequence)
        writer.finish()
    return len(messages)
