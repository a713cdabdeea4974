"""Writing a session: an MCAP file of what a puppetry run sent and received (docs/session.md).

One JSON message per channel and time step, with a JSON Schema per message type, so the
``mcap`` CLI, Foxglove and the ``mcap`` Python reader open the file as it is; beside them, at
the puppet rate, the bodies, bars, strings and forces in Foxglove's well-known schemas
(``/foxglove/transforms``, ``/foxglove/scene``, ``/foxglove/points``; protobuf,
:mod:`dmarionette.io.session.foxglove`), which Foxglove's 3D panel and Rerun draw.
Log times are wall-clock nanoseconds: the time the session started (``log_time_origin_ns``
in the metadata) plus the simulated time; every message holds the simulated time ``t`` too.
When the writer closes normally the file is rewritten chunked, indexed and zstd-compressed
(:func:`dmarionette.io.session.index.index_session`). The scene (its TOML text, made self-contained) and every
constant go first, as metadata records, so even a file cut off after a second holds them.

Crash safety: by default the file is unchunked: every record goes to the file's buffer as it
comes (the buffer reaches the operating system every 8 KiB), and every ``flush_seconds`` of
simulated time, and of wall-clock time (a background thread, so a stalled simulation is
covered too), the buffer is flushed. (With ``chunk_bytes``, the chunk in progress is finished
at each flush instead.) A crash therefore loses at most the last ``flush_seconds`` (1 s by
default); the tolerant reader (:func:`dmarionette.io.session.read.read_session`) reads
everything before the cut.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import threading
import time
import tomllib
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from dmarionette.io.session.format import FORMAT, FORMAT_VERSION
from dmarionette.scene.bars import read_bar_trajectory_csv
from dmarionette.scene.scene import Scene, resolve_puppet_table

__all__ = ["FORMAT", "FORMAT_VERSION", "SCHEMAS", "SessionWriter", "scene_constants", "session_metadata"]



def _vector(n: int, description: str, items: dict | None = None) -> dict:
    return {"type": "array", "items": items or {"type": ["number", "null"]}, "minItems": n, "maxItems": n,
            "description": description}


_T = {"type": "number", "description": "simulated time [s] (the log time is log_time_origin_ns + t in ns)"}

def _message_schema(name: str, description: str, properties: dict, optional: tuple[str, ...] = ()) -> dict:
    """JSON Schema of one message type: an object with the simulated time ``t`` and ``properties``,
    each of them required but the ``optional`` ones."""
    required = [key for key in properties if key not in optional]
    return {"title": name, "type": "object", "description": description,
            "properties": {"t": _T, **properties}, "required": ["t", *required]}


def _vector3_message_schema(name: str, description: str, **vectors: str) -> dict:
    """:func:`_message_schema` of a message of 3-vectors (each required), by name and description."""
    return _message_schema(name, description, {key: _vector(3, text) for key, text in vectors.items()})


#: JSON Schema of each message type, by schema name (one schema record each in the file).
SCHEMAS: dict[str, dict] = {schema["title"]: schema for schema in (
    _message_schema(
        "dmarionette.DeviceSample",
        "A haptic device sample, device frame (x right, y up, z towards the user).",
        {"position": _vector(3, "tip position [m], device frame"),
         "orientation": _vector(4, "unit quaternion (w, x, y, z), device frame"),
         "buttons": {"type": "integer", "description": "button bitmask"},
         "device_time": {"type": "number",
                         "description": "the device's clock [s since open], when t is the simulated time (optional)"}},
        optional=("device_time",)),
    _vector3_message_schema(
        "dmarionette.DeviceForce", "The force sent to the device (after the safety filter), device frame.",
        force="force [N], device frame"),
    _vector3_message_schema(
        "dmarionette.BarPose", "A control bar's pose, world frame (y up).",
        position="bar centre [m], world frame", rotation="XYZ Euler angles [deg], R = Rz Ry Rx (control_bar.py)"),
    _vector3_message_schema(
        "dmarionette.BarFeedback", "Forces of the strings on a bar, world frame.",
        eq4="paper eq. 4 feedback summed over the bar's taut strings [N]",
        reaction="exact reaction: sum of string tensions at the attach points [N]"),
    _message_schema(
        "dmarionette.StringTaut",
        "Taut flags (paper 3.2), one per string in the order of the metadata's 'strings'.",
        {"taut": {"type": "array", "items": {"type": "integer", "enum": [0, 1]}}}),
    _message_schema(
        "dmarionette.PuppetState",
        "The puppet: generalised coordinates and body poses (world frame), bodies in the order of the "
        "metadata's 'bodies'.",
        {"joint_q": {"type": "array", "items": {"type": ["number", "null"]},
                     "description": "generalised coordinates (metadata 'joint_q_layout')"},
         "body_pos": {"type": "array", "items": _vector(3, "body centre [m]")},
         "body_rot": {"type": "array", "items": _vector(4, "body quaternion (x, y, z, w)")}}),
)}

# topic pattern -> schema name
_TOPIC_SCHEMA = {
    "device/sample": "dmarionette.DeviceSample",
    "device/force": "dmarionette.DeviceForce",
    "bar/pose": "dmarionette.BarPose",
    "bar/feedback": "dmarionette.BarFeedback",
    "strings/taut": "dmarionette.StringTaut",
    "puppet/state": "dmarionette.PuppetState",
}

_encode_strict = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def _encode(message: dict) -> bytes:
    """Compact JSON; a non-finite number (not valid JSON) is written as null."""
    try:
        return _encode_strict(message).encode()
    except ValueError:
        return _encode_strict(_finite_or_none(message)).encode()


def _finite_or_none(value):
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    return value


def _floats(values) -> list:
    """A (nested) list of Python floats from an array or a sequence."""
    if isinstance(values, np.ndarray):
        return values.astype(np.float64, copy=False).tolist()
    return np.asarray(values, dtype=np.float64).tolist()


def _foxglove_puppet(metadata: dict, scene: Scene):
    """The Foxglove message builder, or ``None`` without ``foxglove-schemas-protobuf``."""
    try:
        from dmarionette.io.session.foxglove import FoxglovePuppet
    except ImportError:
        return None
    return FoxglovePuppet(metadata, scene)


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("dmarionette")
    except Exception:  # noqa: BLE001 - not installed: the source tree
        return "unknown"


def self_contained_table(scene_text: str, source: str) -> dict:
    """The scene's TOML table with what it refers to inlined, so it loads from anywhere.

    ``[puppet] include = ...`` is replaced by the merged puppet table, and a bar's
    ``trajectory_file`` by the ``keyframes`` it holds (the same spline).
    """
    table = tomllib.loads(scene_text)
    if isinstance(table.get("puppet"), Mapping):
        table["puppet"] = dict(resolve_puppet_table(table["puppet"], source))
    for name, bar in (table.get("bars") or {}).items():
        if isinstance(bar, Mapping) and "trajectory_file" in bar:
            file = Path(str(bar["trajectory_file"]))
            trajectory = read_bar_trajectory_csv(file if file.is_absolute() else Path(source).parent / file)
            bar = {k: v for k, v in bar.items() if k != "trajectory_file"}
            bar["keyframes"] = [{"t": float(t), "position": list(map(float, p)), "rotation": list(map(float, r))}
                                for t, p, r in zip(trajectory.times, trajectory.positions, trajectory.rotations)]
            table["bars"][name] = bar
    return table


def scene_constants(scene: Scene) -> dict:
    """Every constant of ``scene`` that the simulation uses, as JSON-ready values."""
    def plain(value):
        if dataclasses.is_dataclass(value):
            return {k: plain(v) for k, v in dataclasses.asdict(value).items()}
        if isinstance(value, Mapping):
            return {str(k): plain(v) for k, v in value.items()}
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        if isinstance(value, (np.floating, np.integer, np.bool_)):
            return value.item()
        return value

    return {
        "strings": {s.name: plain(s) for s in scene.strings},
        "string_body_points": list(scene.string_body_points),
        "feedback": {"stiffness": scene.feedback_stiffness, "damping": scene.feedback_damping},
        "contact": plain(scene.contact),
        "world": {"gravity": list(scene.gravity), "ground_height": scene.ground_height},
        "effects": plain(scene.effects),
        "body_effects": plain(scene.body_effects),
        "precision": scene.precision,
        "chair": plain(scene.chair),
        "ball": plain(scene.ball),
        "initial_pose": plain(scene.initial_pose),
        "motion": plain(scene.motion),
    }


def _joint_q_layout(scene: Scene) -> list:
    if scene.puppet is None:
        return []
    layout = [[scene.puppet.root, "free", 7]]
    layout += [[j.name, j.type, 4 if j.type == "ball" else len(j.axes)] for j in scene.puppet.joints]
    if scene.ball is not None:
        layout.append(["ball", "free", 7])
    return layout


def session_metadata(scene: Scene, *, recorder: str, log_time_origin_ns: int = 0) -> dict[str, Any]:
    """The ``"dmarionette"`` metadata record (each value is stored as JSON text)."""
    bodies = [b.name for b in scene.puppet.bodies] + (["ball"] if scene.ball is not None else []) \
        if scene.puppet is not None else []
    bar_of = {s: b.name for b in scene.bars for s in b.attach}
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "version": _version(),
        "recorder": recorder,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "time": "log_time = publish_time = log_time_origin_ns + simulated time [ns]; every message also holds t [s]",
        "log_time_origin_ns": int(log_time_origin_ns),
        "string_hz": scene.string_hz,
        "puppet_hz": scene.puppet_hz,
        "puppet_substeps": max(1, round(scene.string_hz / scene.puppet_hz)),
        "bars": [b.name for b in scene.bars],
        "bar_attach": {b.name: {s: list(p) for s, p in b.attach.items()} for b in scene.bars},
        "strings": [s.name for s in scene.strings],
        "string_bars": [bar_of.get(s.name) for s in scene.strings],
        "bodies": bodies,
        "joint_q_layout": _joint_q_layout(scene),
        "puppet_mass": float(sum(b.mass for b in scene.puppet.bodies)) if scene.puppet is not None else 0.0,
        "constants": scene_constants(scene),
    }


class SessionWriter:
    """Writes a session file as it happens; safe to call from one thread at 1 kHz.

    Args:
        path: the ``.mcap`` file to write (replaced if it exists).
        scene: the scene being simulated (its constants are stored).
        scene_text: the scene file's TOML text (stored verbatim, and self-contained).
        flush_seconds: at most this much simulated or wall-clock time stays unwritten.
        recorder: ``"live"`` (a puppetry session) or ``"simulation"``; stored in the metadata.
        chunk_bytes: ``None`` (default): an unchunked file, every record written to the file
            as it comes (no chunk or message indexes; readers scan it linearly). A number: chunks
            of at most this many bytes, each also finished at every flush, with indexes; but
            finishing a chunk takes milliseconds of Python (2.6 ms measured for 256 KiB at
            9 messages per 1 kHz tick), too long for a 1 kHz loop's thread.
        compression: ``"none"``, ``"zstd"`` or ``"lz4"``, for chunks only (the last two need
            the ``zstandard`` / ``lz4`` packages, on the reading machine too).
        fsync: also ``os.fsync`` at each flush (survives a power cut, costs a disk sync).
        foxglove: also write ``/foxglove/transforms``, ``/foxglove/scene`` and ``/foxglove/points`` at each puppet
            state (needs ``foxglove-schemas-protobuf``; without it they are left out).
        index_on_close: when closed normally, rewrite the file chunked, indexed and
            zstd-compressed (:func:`dmarionette.io.session.index.index_session`).
    """

    def __init__(self, path: str | Path, scene: Scene, scene_text: str, *, flush_seconds: float = 1.0,
                 recorder: str = "live", chunk_bytes: int | None = None, compression: str = "none",
                 fsync: bool = False, foxglove: bool = True, index_on_close: bool = True):
        if not flush_seconds > 0.0:
            raise ValueError(f"flush_seconds: got {flush_seconds}; expected a positive number of seconds")
        kinds = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}
        if compression not in kinds:
            raise ValueError(f"compression: got {compression!r}; expected one of {sorted(kinds)}")
        self.path = Path(path)
        self.scene = scene
        self.flush_seconds = float(flush_seconds)
        self._fsync = fsync
        # Everything that can fail on a bad scene comes before the file is created.
        scene_record = {"name": scene.name, "source": str(scene.source), "toml": scene_text,
                        "table_json": json.dumps(self_contained_table(scene_text, str(scene.source)))}
        self.log_time_origin_ns = time.time_ns()  # wall clock at the start; log time = origin + t
        meta = session_metadata(scene, recorder=recorder, log_time_origin_ns=self.log_time_origin_ns)
        metadata = {k: json.dumps(v) for k, v in meta.items()}
        self._foxglove = _foxglove_puppet(meta, scene) if foxglove else None
        self._index_on_close = index_on_close
        self._bar_poses: dict[str, tuple] = {}
        self._reactions: dict[str, list] = {}
        self._taut: list | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb", buffering=8192)  # reaches the OS every 8 KiB
        # Chunks need Writer.flush (finish the chunk in progress), which came with newer mcap
        # releases; without it the file is written unchunked.
        self._chunked = chunk_bytes is not None and hasattr(Writer, "flush")
        self._writer = Writer(self._file, chunk_size=int(chunk_bytes or 0), compression=kinds[compression],
                              use_chunking=self._chunked)
        self._writer.start(profile="", library=f"dmarionette {_version()} (mcap-python)")
        self._writer.add_metadata("scene", scene_record)
        self._writer.add_metadata("dmarionette", metadata)
        self._schema_ids = {name: self._writer.register_schema(name, SchemaEncoding.JSONSchema,
                                                               json.dumps(schema).encode())
                            for name, schema in SCHEMAS.items()}
        self._foxglove_topics: dict[str, str] = {}
        if self._foxglove is not None:
            from dmarionette.io.session.foxglove import FOXGLOVE_TOPICS, file_descriptor_set

            self._foxglove_topics = dict(FOXGLOVE_TOPICS)
            for topic, name in FOXGLOVE_TOPICS.items():
                schema = self._writer.register_schema(name, SchemaEncoding.Protobuf, file_descriptor_set(name))
                self._schema_ids[name] = schema
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._lock = threading.Lock()
        self._dirty = False
        self._closed = False
        self._last_flush_t = -math.inf
        self._flush_locked(-math.inf)  # header, metadata and schemas reach the disk at once
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_periodically, name="session-flush", daemon=True)
        self._flusher.start()

    # Channels ------------------------------------------------------------------------------

    def _channel(self, topic: str, kind: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            schema = _TOPIC_SCHEMA.get(kind) or self._foxglove_topics[topic]
            encoding = MessageEncoding.Protobuf if schema.startswith("foxglove.") else MessageEncoding.JSON
            channel = self._writer.register_channel(topic, encoding, self._schema_ids[schema])
            self._channels[topic] = channel
            self._sequence[topic] = 0
        return channel

    def _write(self, topic: str, kind: str, t: float, message: dict | bytes) -> None:
        if not (t >= 0.0 and math.isfinite(t)):
            raise ValueError(f"{self.path}: {topic}: time t = {t!r}; expected a finite time >= 0 [s] "
                             "(MCAP log times are unsigned nanoseconds)")
        data = message if isinstance(message, bytes) else _encode(message)
        log_time = self.log_time_origin_ns + int(round(t * 1e9))
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path}: the session is closed")
            channel = self._channel(topic, kind)
            sequence = self._sequence[topic]
            self._sequence[topic] = sequence + 1
            self._writer.add_message(channel, log_time, data, log_time, sequence)
            self._dirty = True
            if t - self._last_flush_t >= self.flush_seconds:
                self._flush_locked(t)

    # Messages ------------------------------------------------------------------------------

    def write_device_sample(self, bar: str, sample, t: float | None = None) -> None:
        """``/device/BAR/sample``: a :class:`dmarionette.hw.HapticSample` (device frame).

        ``t`` [s] is the simulated time the sample belongs to; when given, the sample's own
        clock (``sample.time``, seconds since the device opened) is kept as ``device_time``.
        Without ``t``, ``sample.time`` is the time.
        """
        message = {"t": float(sample.time if t is None else t), "position": _floats(sample.position),
                   "orientation": _floats(sample.orientation), "buttons": int(sample.buttons)}
        if t is not None:
            message["device_time"] = float(sample.time)
        self._write(f"/device/{bar}/sample", "device/sample", message["t"], message)

    def write_force(self, bar: str, t: float, force) -> None:
        """``/device/BAR/force``: the force [N] sent to the device at ``t`` [s], device frame."""
        self._write(f"/device/{bar}/force", "device/force", t, {"t": float(t), "force": _floats(force)})

    def write_bar_pose(self, bar: str, t: float, position, rotation_deg) -> None:
        """``/bar/BAR/pose``: bar centre [m] and XYZ Euler angles [deg] at ``t`` [s], world frame."""
        message = {"t": float(t), "position": _floats(position), "rotation": _floats(rotation_deg)}
        self._write(f"/bar/{bar}/pose", "bar/pose", t, message)
        self._bar_poses[bar] = (message["position"], message["rotation"])

    def write_feedback(self, bar: str, t: float, eq4, reaction) -> None:
        """``/bar/BAR/feedback``: eq. 4 feedback and exact reaction [N] on the bar, world frame."""
        message = {"t": float(t), "eq4": _floats(eq4), "reaction": _floats(reaction)}
        self._write(f"/bar/{bar}/feedback", "bar/feedback", t, message)
        self._reactions[bar] = message["reaction"]

    def write_taut(self, t: float, flags) -> None:
        """``/strings/taut``: one 0/1 flag per string (scene order) at ``t`` [s]."""
        message = {"t": float(t), "taut": [int(bool(f)) for f in flags]}
        self._write("/strings/taut", "strings/taut", t, message)
        self._taut = message["taut"]

    def write_puppet_state(self, t: float, joint_q, body_pos, body_rot) -> None:
        """``/puppet/state``: ``joint_q`` ``(q,)``, ``body_pos`` [m] ``(bodies, 3)``, ``body_rot``
        (x, y, z, w) ``(bodies, 4)`` at ``t`` [s]."""
        message = {"t": float(t), "joint_q": _floats(joint_q), "body_pos": _floats(body_pos),
                   "body_rot": _floats(body_rot)}
        self._write("/puppet/state", "puppet/state", t, message)
        if self._foxglove is not None:  # the puppet in Foxglove's schemas, with the latest bar poses
            log_time = self.log_time_origin_ns + int(round(float(t) * 1e9))
            args = (log_time, float(t), dict(self._bar_poses), message["body_pos"], message["body_rot"])
            self._write("/foxglove/transforms", "foxglove", t, self._foxglove.transforms(*args))
            self._write("/foxglove/scene", "foxglove", t,
                        self._foxglove.scene_update(*args, reactions=dict(self._reactions), taut=self._taut))
            self._write("/foxglove/points", "foxglove", t, self._foxglove.points(*args))

    def write_metadata(self, name: str, values: Mapping[str, Any]) -> None:
        """An extra metadata record (e.g. ``"device"``: its spec, the mapping ``S``, ``W``, the
        safety settings); each value is stored as JSON text. Written and flushed at once."""
        if name in ("scene", "dmarionette"):
            raise ValueError(f"metadata name {name!r} is reserved; choose another")
        with self._lock:
            self._writer.add_metadata(name, {str(k): json.dumps(v) for k, v in values.items()})
            self._flush_locked(self._last_flush_t)

    # Flushing ------------------------------------------------------------------------------

    def _flush_locked(self, t: float) -> None:
        if self._chunked:
            self._writer.flush()  # finishes the chunk in progress and flushes the stream
        else:
            self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self._dirty = False
        self._last_flush_t = t
        self._last_flush_wall = time.monotonic()

    def _flush_periodically(self) -> None:
        period = min(self.flush_seconds, 1.0) / 4.0
        while not self._stop.wait(period):
            with self._lock:
                if self._closed:
                    return
                if self._dirty and time.monotonic() - self._last_flush_wall >= self.flush_seconds * 0.75:
                    self._flush_locked(self._last_flush_t)

    def flush(self) -> None:
        """Writes everything so far to the operating system now."""
        with self._lock:
            if not self._closed:
                self._flush_locked(self._last_flush_t)

    def close(self) -> None:
        """Writes the summary (statistics, indexes) and the footer; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        self._flusher.join()
        self._writer.finish()
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self._file.close()
        if self._index_on_close:
            from dmarionette.io.session.index import index_session

            try:
                index_session(self.path)
            except Exception as error:  # noqa: BLE001 - the unchunked file is complete and stays
                warnings.warn(f"{self.path}: left unchunked, not indexed ({type(error).__name__}: {error}); "
                              "'dmarionette session index FILE' rewrites it", stacklevel=2)

    @property
    def topics(self) -> list[str]:
        """Topics written so far."""
        return list(self._channels)

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
