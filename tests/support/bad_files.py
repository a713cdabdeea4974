"""Valid files to damage, shared by test_bad_inputs_files.py and test_fuzz_files.py (no Warp kernels)."""

from __future__ import annotations

import copy
import io
import json
import tomllib
import types
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer

import dmarionette as dm
from dmarionette.io.session import SessionWriter
from dmarionette.scene.scene import SCENE_DIR

BARS = ("main", "hand")
BODIES = 12
STEPS = 70


def hanging_table() -> dict:
    """The ``hanging`` scene's table with its puppet include resolved (self-contained)."""
    table = tomllib.loads((SCENE_DIR / "hanging.toml").read_text())
    puppet = tomllib.loads((SCENE_DIR / "puppet.toml").read_text())["puppet"]
    table["puppet"] = {**puppet, **{k: v for k, v in table["puppet"].items() if k != "include"}}
    return table


def puppet_table() -> dict:
    return copy.deepcopy(tomllib.loads((SCENE_DIR / "puppet.toml").read_text())["puppet"])


def write_session(path: Path, *, steps: int = STEPS, enable_data_crcs: bool = False, indexed: bool = False) -> Path:
    """A small valid session of the ``hanging`` scene: 70 string steps, every dmarionette channel;
    unchunked as a crash leaves it (the byte-level damage tests walk its records), or ``indexed``
    (chunked, zstd) as a recording that closed normally."""
    scene = dm.load_scene("hanging")
    with SessionWriter(path, scene, Path(scene.source).read_text(), index_on_close=indexed) as writer:
        for k in range(steps):
            t = k * 1e-3
            for b, bar in enumerate(BARS):
                writer.write_bar_pose(bar, t, [0.01 * b, 0.9 + 1e-4 * k, 0.0], [0.0, 0.1 * k, 0.0])
                writer.write_feedback(bar, t, [0.0, 0.1, 0.0], [0.0, 0.2, 0.0])
            writer.write_taut(t, [1, 0, 1, 1, 0, 1])
            if k % 33 == 0:
                writer.write_puppet_state(t, np.zeros(25), np.full((BODIES, 3), 0.1),
                                          np.tile([0.0, 0.0, 0.0, 1.0], (BODIES, 1)))
    if enable_data_crcs:
        rewrite_session(path, path, enable_data_crcs=True)
    return path


def rewrite_session(src: Path, dst: Path, *, metadata=None, message=None, drop_topics=(),
                    enable_data_crcs: bool = False) -> Path:
    """Re-encodes ``src`` to ``dst`` through mcap's writer, with edits.

    Args:
        metadata: ``fn(name, dict) -> dict`` applied to each metadata record (JSON text values).
        message: ``fn(topic, index, bytes) -> bytes | None`` applied to each message (None drops it).
        drop_topics: topics left out.
    """
    with open(src, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
        messages = list(reader.iter_messages())
    buffer = io.BytesIO()
    writer = Writer(buffer, use_chunking=False, enable_data_crcs=enable_data_crcs)
    writer.start()
    for name, values in records:
        writer.add_metadata(name, metadata(name, dict(values)) if metadata else values)
    schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
    channel_ids = {}
    counts: dict[str, int] = {}
    for _schema, channel, msg in messages:
        if channel.topic in drop_topics:
            continue
        if channel.id not in channel_ids:
            channel_ids[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                              schema_ids[channel.schema_id])
        index = counts.get(channel.topic, 0)
        counts[channel.topic] = index + 1
        data = message(channel.topic, index, msg.data) if message else msg.data
        if data is not None:
            writer.add_message(channel_ids[channel.id], msg.log_time, data, msg.publish_time, msg.sequence)
    writer.finish()
    Path(dst).write_bytes(buffer.getvalue())
    return Path(dst)


def edit_json(fn):
    """A ``message`` edit that decodes, changes (``fn(dict) -> dict``) and re-encodes."""
    return lambda data: json.dumps(fn(json.loads(data))).encode()


def synthetic_marionette_trajectory(frames: int = 5, steps_per_frame: int = 3):
    """A consistent marionette trajectory object (no simulation): 2 strings of 3 particles, 2 bodies, 1 bar."""
    steps = frames * steps_per_frame
    rot = np.tile([0.0, 0.0, 0.0, 1.0], (frames + 1, 2, 1))
    return types.SimpleNamespace(
        frame_time=0.01 * np.arange(frames + 1), particle_q=np.zeros((frames + 1, 6, 3)),
        joint_q=np.zeros((frames + 1, 7)), body_pos=np.zeros((frames + 1, 2, 3)), body_rot=rot,
        bar_pos=np.zeros((frames + 1, 1, 3)), bar_rot=np.tile(np.eye(3), (frames + 1, 1, 1, 1)),
        top_q=np.zeros((frames + 1, 2, 3)), step_time=0.01 / steps_per_frame * np.arange(1, steps + 1),
        tie_force=np.zeros((steps, 2, 3)), string_taut=np.ones((steps, 2), dtype=bool),
        bar_feedback=np.zeros((steps, 1, 3)), bar_reaction=np.zeros((steps, 1, 3)),
        string_names=["a", "b"], string_start=np.array([0, 3, 6]), string_rest_length=np.array([0.1, 0.1]),
        body_names=["torso", "head"], body_shape=[("box", (0.1, 0.1, 0.1)), ("sphere", (0.05, 0.0, 0.0))],
        bar_names=["main"], string_dt=0.01 / steps_per_frame, puppet_dt=0.01 / steps_per_frame,
        frame_steps=steps_per_frame, wall_seconds=1.0)


def synthetic_string_trajectory(frames: int = 5, steps_per_frame: int = 3):
    """A consistent strings-only trajectory object (no simulation)."""
    m = synthetic_marionette_trajectory(frames, steps_per_frame)
    return types.SimpleNamespace(
        frame_time=m.frame_time, particle_q=m.particle_q, top_q=m.top_q, step_time=m.step_time,
        tie_force=m.tie_force, string_taut=m.string_taut, string_names=m.string_names,
        string_start=m.string_start, string_rest_length=m.string_rest_length, energy=np.zeros(frames + 1),
        string_dt=m.string_dt, frame_steps=m.frame_steps, wall_seconds=1.0)
