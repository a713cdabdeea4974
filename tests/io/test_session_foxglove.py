"""Sessions that the ecosystem's tools open (docs/session.md, "Viewing a session").

A simulated session (``record_simulation``, 0.5 s of "hanging") is read with the ``mcap``
reader (summary: zstd chunks with indexes, schema names, message counts), its Foxglove
messages are decoded from the schema the file carries (as Foxglove does: no generated
code), and Rerun's own MCAP reader (``rerun.chunk.McapReader``, rerun-sdk) turns its
transforms into ``Transform3D`` rows. A file left by a crash and a format-1 session are
indexed with ``dmarionette session index``.
"""

import datetime
import json
import shutil

import numpy as np
import pytest
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader
from mcap.writer import Writer

import dmarionette as dm
from dmarionette.cli import main
from dmarionette.io.session import SessionWriter, read_session, record_simulation, session_info
from dmarionette.io.session.read import read_session_records
from dmarionette.rotations import euler_to_matrix, quat_to_matrix

rerun_chunk = pytest.importorskip("rerun.chunk", reason="needs rerun-sdk")
pytest.importorskip("foxglove_schemas_protobuf", reason="needs foxglove-schemas-protobuf")

DURATION = 0.5
JSON_TOPICS = ["/bar/main/pose", "/bar/main/feedback", "/bar/hand/pose", "/bar/hand/feedback", "/strings/taut",
               "/puppet/state"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    model = dm.MarionetteModel(dm.load_scene("hanging"), optimization_level=0)
    path = tmp_path_factory.mktemp("session") / "take.mcap"
    trajectory, path = record_simulation(model, DURATION, path)
    return trajectory, path


def _summary(path):
    with open(path, "rb") as f:
        reader = make_reader(f)
        return reader.get_summary(), {m.name: m.metadata for m in reader.iter_metadata()}


def _counts(summary):
    return {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}


def _check_indexed(path, frames, steps):
    summary, metadata = _summary(path)
    assert summary.chunk_indexes, "no chunk indexes"
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    channel_ids = set(summary.channels)
    indexed = {cid for c in summary.chunk_indexes for cid in c.message_index_offsets}
    assert indexed == channel_ids, "every channel has message indexes"
    schemas = {summary.schemas[c.schema_id].name: summary.schemas[c.schema_id].encoding
               for c in summary.channels.values()}
    assert schemas["foxglove.FrameTransforms"] == schemas["foxglove.SceneUpdate"] == "protobuf"
    assert schemas["foxglove.PointCloud"] == "protobuf"
    assert schemas["dmarionette.PuppetState"] == "jsonschema" and schemas["dmarionette.BarPose"] == "jsonschema"
    counts = _counts(summary)
    assert counts["/puppet/state"] == counts["/foxglove/transforms"] == counts["/foxglove/scene"] == frames
    assert counts["/foxglove/points"] == frames
    assert counts["/bar/main/pose"] == counts["/bar/hand/pose"] == steps + 1
    assert counts["/strings/taut"] == counts["/bar/main/feedback"] == steps
    return summary, metadata


def _decoders(path):
    """Protobuf classes built from the file's own schema records (what a generic viewer does)."""
    out = {}
    with open(path, "rb") as f:
        for schema in make_reader(f).get_summary().schemas.values():
            if schema.encoding == "protobuf":
                pool = descriptor_pool.DescriptorPool()
                for file in FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(file)
                out[schema.name] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return out


def _messages(path, topic):
    with open(path, "rb") as f:
        return [(m.log_time, m.data) for _, _, m in make_reader(f).iter_messages(topics=[topic])]


def test_a_closed_recording_is_chunked_indexed_and_zstd(recorded):
    trajectory, path = recorded
    _, metadata = _check_indexed(path, len(trajectory.frame_time), len(trajectory.step_time))
    meta = {k: json.loads(v) for k, v in metadata["dmarionette"].items()}
    assert meta["format_version"] == 2
    info = session_info(path)
    assert not info["truncated"] and info["start"] == 0.0 and info["end"] == pytest.approx(trajectory.step_time[-1])


def test_foxglove_transforms_hold_the_recorded_poses(recorded):
    trajectory, path = recorded
    session = read_session(path)
    origin = session.metadata["log_time_origin_ns"]
    assert abs(origin - session.channels["/puppet/state"]["log_time"][0]) < 1  # frame 0 at t = 0
    FrameTransforms = _decoders(path)["foxglove.FrameTransforms"]
    messages = _messages(path, "/foxglove/transforms")
    state = session.channels["/puppet/state"]
    np.testing.assert_array_equal([t for t, _ in messages], state["log_time"])
    for k in (0, len(messages) // 2, len(messages) - 1):
        log_time, data = messages[k]
        frames = {tf.child_frame_id: tf for tf in FrameTransforms.FromString(data).transforms}
        assert set(frames) == {"world"} | {f"body/{b}" for b in session.bodies} | {f"bar/{b}" for b in session.bars}
        assert frames["world"].parent_frame_id == "map"
        for b, name in enumerate(session.bodies):
            tf = frames[f"body/{name}"]
            assert tf.parent_frame_id == "world"
            assert tf.timestamp.seconds * 10**9 + tf.timestamp.nanos == log_time
            np.testing.assert_array_equal([tf.translation.x, tf.translation.y, tf.translation.z],
                                          state["body_pos"][k, b])
            np.testing.assert_array_equal([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w],
                                          state["body_rot"][k, b])
        bar = frames["bar/main"]
        pose = session.channels["/bar/main/pose"]
        i = int(np.searchsorted(pose["t"], state["t"][k] + 1e-12) - 1)
        np.testing.assert_array_equal([bar.translation.x, bar.translation.y, bar.translation.z], pose["position"][i])
        q = np.array([bar.rotation.x, bar.rotation.y, bar.rotation.z, bar.rotation.w])
        np.testing.assert_allclose(quat_to_matrix(q), euler_to_matrix(pose["rotation"][i]), atol=1e-12)


def test_the_scene_update_draws_bodies_strings_and_forces(recorded):
    trajectory, path = recorded
    session = read_session(path)
    SceneUpdate = _decoders(path)["foxglove.SceneUpdate"]
    _, data = _messages(path, "/foxglove/scene")[-1]
    entities = {e.id: e for e in SceneUpdate.FromString(data).entities}
    puppet = session.scene.puppet
    for body in puppet.bodies:
        entity = entities[f"body/{body.name}"]
        assert entity.frame_id == f"body/{body.name}" and entity.frame_locked
        if body.shape == "sphere":
            assert entity.spheres[0].size.x == pytest.approx(2 * body.size[0])
        else:
            cube = entity.cubes[0].size
            assert (cube.x, cube.y, cube.z) == pytest.approx(body.size)
    lines = entities["strings"].lines
    assert len(lines) == len(session.strings)
    head = session.strings.index("head")
    point = {p.name: p for p in puppet.points}["head"]
    b = session.bodies.index(point.body)
    state = session.channels["/puppet/state"]
    rotation = quat_to_matrix(state["body_rot"][-1, b])
    bottom = state["body_pos"][-1, b] + rotation @ np.asarray(point.position)
    end = lines[head].points[-1]
    np.testing.assert_allclose([end.x, end.y, end.z], bottom, atol=1e-12)
    arrows = entities["forces"].arrows
    reaction = session.channels["/bar/main/feedback"]["reaction"][-1]
    assert len(arrows) == 2
    assert arrows[0].shaft_length + arrows[0].head_length == pytest.approx(0.01 * np.linalg.norm(reaction))


def _rerun_transforms(path):
    """Rows of Rerun's Transform3D components from the file, as Rerun's MCAP importer makes them."""
    rows = []
    for chunk in rerun_chunk.McapReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "Transform3D:translation" not in batch.schema.names:
            continue
        assert chunk.entity_path == "/foxglove/transforms"
        field = batch.schema.field("Transform3D:translation")
        assert field.metadata[b"rerun:archetype"] == b"rerun.archetypes.Transform3D"
        child = batch.column("Transform3D:child_frame").to_pylist()
        translation = batch.column("Transform3D:translation").to_pylist()
        quaternion = batch.column("Transform3D:quaternion").to_pylist()
        log_time = batch.column("message_log_time").cast("int64").to_pylist()
        rows += [(t, c[0], p[0], q[0]) for t, c, p, q in zip(log_time, child, translation, quaternion)]
    return rows


def test_rerun_reads_the_transforms_as_transform3d(recorded):
    trajectory, path = recorded
    session = read_session(path)
    rows = _rerun_transforms(path)
    frames = len(session.channels["/puppet/state"]["t"])
    assert len(rows) == frames * (1 + len(session.bodies) + len(session.bars))
    state = session.channels["/puppet/state"]
    head = session.bodies.index("head")
    last = [r for r in rows if r[1] == "body/head"][-1]
    assert last[0] == state["log_time"][-1]
    np.testing.assert_allclose(last[2], state["body_pos"][-1, head], rtol=1e-6)  # Rerun keeps float32
    np.testing.assert_allclose(last[3], state["body_rot"][-1, head], atol=1e-6)


def test_rerun_draws_the_bodies_and_string_ends_as_points3d(recorded):
    trajectory, path = recorded
    session = read_session(path)
    state = session.channels["/puppet/state"]
    chunks = [c for c in rerun_chunk.McapReader(path).stream().to_chunks()
              if c.entity_path == "/foxglove/points" and c.timeline_names]
    batches = [c.to_record_batch() for c in chunks]
    positions = [p for b in batches for p in b.column("Points3D:positions").to_pylist()]
    frames = [f for b in batches for f in b.column("CoordinateFrame:frame").to_pylist()]
    assert len(positions) == len(state["t"]) and all(f == ["world"] for f in frames)
    bodies = len(session.bodies)
    assert all(len(p) == bodies + 2 * len(session.strings) for p in positions)
    for k in (0, len(positions) - 1):
        np.testing.assert_array_equal(np.array(positions[k][:bodies]), state["body_pos"][k].astype(np.float32))
    # the string ends: the last point of the head string is the head's attach point
    point = {p.name: p for p in session.scene.puppet.points}["head"]
    b = session.bodies.index(point.body)
    bottom = state["body_pos"][-1, b] + quat_to_matrix(state["body_rot"][-1, b]) @ np.asarray(point.position)
    head = session.strings.index("head")
    np.testing.assert_allclose(positions[-1][bodies + 2 * head + 1], bottom, rtol=1e-6, atol=1e-7)


def test_session_index_rewrites_a_file_left_by_a_crash(recorded, tmp_path):
    """A copy taken while the writer is open (no footer) is indexed; everything in it is kept."""
    trajectory, path = recorded
    session = read_session(path)
    writer = SessionWriter(tmp_path / "live.mcap", session.scene, session.scene_record["toml"])
    pose = session.channels["/bar/main/pose"]
    state = session.channels["/puppet/state"]
    for k, t in enumerate(state["t"]):
        writer.write_bar_pose("main", t, pose["position"][k], pose["rotation"][k])
        writer.write_puppet_state(t, state["joint_q"][k], state["body_pos"][k], state["body_rot"][k])
    writer.flush()
    crashed = tmp_path / "crashed.mcap"
    shutil.copyfile(tmp_path / "live.mcap", crashed)
    writer.close()
    assert read_session(crashed).truncated
    assert main(["session", "index", str(crashed)]) == 0
    summary, _ = _summary(crashed)
    assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert _counts(summary)["/foxglove/transforms"] == _counts(summary)["/puppet/state"] == len(state["t"])
    again = read_session(crashed)
    assert not again.truncated
    np.testing.assert_array_equal(again.channels["/puppet/state"]["body_pos"], state["body_pos"])
    assert len(_rerun_transforms(crashed)) == len(state["t"]) * (1 + len(session.bodies) + 1)


def _as_format_1(path, out):
    """``path`` as dmarionette 0.1 wrote it: log time = simulated time, no Foxglove channels."""
    records = read_session_records(path)
    meta = {k: json.loads(v) for k, v in records.metadata["dmarionette"].items()}
    origin = meta.pop("log_time_origin_ns")
    meta["format_version"] = 1
    meta["time"] = "log_time = publish_time = simulated time [ns]; every message also holds t [s]"
    with open(out, "wb") as f:
        writer = Writer(f, use_chunking=False)
        writer.start(profile="", library="dmarionette 0.1.0 (mcap-python)")
        writer.add_metadata("scene", records.metadata["scene"])
        writer.add_metadata("dmarionette", {k: json.dumps(v) for k, v in meta.items()})
        schemas = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in records.schemas.items()
                   if s.encoding == "jsonschema"}
        channels = {i: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                    for i, c in records.channels.items() if c.schema_id in schemas}
        for i, messages in records.messages.items():
            for m in messages if i in channels else ():
                writer.add_message(channels[i], m.log_time - origin, m.data, m.publish_time - origin, m.sequence)
        writer.finish()
    return meta


def test_session_index_converts_an_old_session(recorded, tmp_path, capsys):
    trajectory, path = recorded
    old = tmp_path / "old.mcap"
    meta = _as_format_1(path, old)
    assert not any(t.startswith("/foxglove/") for t in _counts(_summary(old)[0]))
    as_recorded = read_session(old)  # format 1 still reads: log time = simulated time
    np.testing.assert_array_equal(as_recorded.channels["/puppet/state"]["log_time"],
                                  np.round(as_recorded.channels["/puppet/state"]["t"] * 1e9).astype(np.int64))
    assert session_info(old)["start"] == 0.0 and session_info(old)["end"] == pytest.approx(trajectory.step_time[-1])
    out = tmp_path / "converted.mcap"
    assert main(["session", "index", str(old), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["converted_from"] == 1 and report["foxglove_added"] == 3 * len(trajectory.frame_time)
    _check_indexed(out, len(trajectory.frame_time), len(trajectory.step_time))
    converted, original = read_session(out), read_session(path)
    created = converted.metadata["log_time_origin_ns"]
    assert created == int(datetime.datetime.fromisoformat(meta["created"]).timestamp()) * 10**9
    for topic in JSON_TOPICS:
        for key, values in original.channels[topic].items():
            if key != "log_time":
                np.testing.assert_array_equal(converted.channels[topic][key], values, err_msg=f"{topic} {key}")
        np.testing.assert_array_equal(converted.channels[topic]["log_time"] - created,
                                      np.round(original.channels[topic]["t"] * 1e9).astype(np.int64))
    # the added transforms are those the writer would have written
    FrameTransforms = _decoders(out)["foxglove.FrameTransforms"]
    added = [FrameTransforms.FromString(d) for _, d in _messages(out, "/foxglove/transforms")]
    written = [FrameTransforms.FromString(d) for _, d in _messages(path, "/foxglove/transforms")]
    for a, w in zip(added, written):
        assert [(t.child_frame_id, t.translation, t.rotation) for t in a.transforms] == \
               [(t.child_frame_id, t.translation, t.rotation) for t in w.transforms]
    assert len(_rerun_transforms(out)) == len(_rerun_transforms(path))


def test_a_failed_rewrite_on_close_leaves_the_unchunked_file(recorded, tmp_path, monkeypatch):
    import dmarionette.io.session.index as index

    def broken(*args, **kwargs):
        raise ImportError("no zstandard")

    monkeypatch.setattr(index, "index_session", broken)  # the writer imports it when it closes
    session = read_session(recorded[1])
    writer = SessionWriter(tmp_path / "take.mcap", session.scene, session.scene_record["toml"])
    writer.write_bar_pose("main", 0.0, [0, 1, 0], [0, 0, 0])
    with pytest.warns(UserWarning, match=r"take\.mcap: left unchunked.*no zstandard.*session index"):
        writer.close()
    assert [p.name for p in tmp_path.iterdir()] == ["take.mcap"]  # no temporary file left
    assert not read_session(tmp_path / "take.mcap").truncated
    assert _summary(tmp_path / "take.mcap")[0].statistics.chunk_count == 0


@pytest.mark.parametrize("fraction", [0.3, 0.5, 0.9])
def test_an_indexed_file_cut_short_reads_back_a_prefix(recorded, tmp_path, fraction):
    """Cut inside a zstd chunk: the reader decompresses what is there and stops at the last
    complete record; at equal times the messages keep the order they were written in."""
    _, path = recorded
    whole = read_session(path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * fraction)])
    session = read_session(cut)
    assert session.truncated
    pose, state = session.channels["/bar/main/pose"], session.channels["/puppet/state"]
    assert len(pose["t"]) > 10
    np.testing.assert_array_equal(pose["position"], whole.channels["/bar/main/pose"]["position"][:len(pose["t"])])
    np.testing.assert_array_equal(state["body_pos"], whole.channels["/puppet/state"]["body_pos"][:len(state["t"])])
    # written per step: bar poses, then feedback, taut, then the puppet state; the cut keeps that
    assert session.channels["/bar/main/feedback"]["t"][-1] >= state["t"][-1]


def test_an_indexed_file_cut_anywhere_reads_back_a_prefix(recorded, tmp_path):
    _, path = recorded
    data = path.read_bytes()
    whole = read_session(path).channels["/bar/main/pose"]["position"]
    cut = tmp_path / "cut.mcap"
    for end in np.linspace(30_000, len(data) - 1, 41).astype(int):  # past the metadata (scene, constants)
        cut.write_bytes(data[:end])
        session = read_session(cut)
        # cut inside the data: truncated; cut after its DataEnd (every message there): a note on the footer
        assert session.truncated or any("footer" in note for note in session.notes), (end, session.notes)
        pose = session.channels.get("/bar/main/pose", {"position": np.zeros((0, 3))})["position"]
        np.testing.assert_array_equal(pose, whole[:len(pose)], err_msg=f"cut at {end}")


def test_session_index_refuses_a_file_that_is_not_a_session(tmp_path, capsys):
    bad = tmp_path / "notes.mcap"
    bad.write_text("not an mcap file")
    assert main(["session", "index", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not an MCAP file" in err
    assert bad.read_text() == "not an mcap file"
