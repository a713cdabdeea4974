"""Session files (docs/session.md): round trip, standard MCAP readers, cut-off files, errors.

These write synthetic sessions (no simulation); ``test_session_replay.py`` records and
replays simulated ones.
"""

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.decoder import DecoderFactory
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import Writer

import dmarionette as dm
from dmarionette.hw.device import HapticSample
from dmarionette.io.session import SCHEMAS, SessionWriter, read_session, session_info

BODIES = 12


@pytest.fixture(scope="module")
def scene():
    return dm.load_scene("hanging")


@pytest.fixture(scope="module")
def scene_text(scene):
    return Path(scene.source).read_text()


def _synthetic(seed=0, steps=500, substeps=33):
    """Values of a 1 kHz session with two bars: every channel, random but reproducible."""
    rng = np.random.default_rng(seed)
    t = 1e-3 * np.arange(steps)
    q = rng.normal(size=(steps, 4))
    return {
        "t": t,
        "device_position": rng.normal(size=(2, steps, 3)),
        "device_orientation": q / np.linalg.norm(q, axis=1, keepdims=True),
        "buttons": rng.integers(0, 4, size=steps),
        "force": rng.normal(size=(2, steps, 3)),
        "bar_position": rng.normal(size=(2, steps, 3)),
        "bar_rotation": rng.normal(scale=10.0, size=(2, steps, 3)),
        "eq4": rng.normal(size=(2, steps, 3)),
        "reaction": rng.normal(size=(2, steps, 3)),
        "taut": rng.integers(0, 2, size=(steps, 6)),
        "puppet_t": t[::substeps],
        "joint_q": rng.normal(size=(len(t[::substeps]), 25)),
        "body_pos": rng.normal(size=(len(t[::substeps]), BODIES, 3)),
        "body_rot": rng.normal(size=(len(t[::substeps]), BODIES, 4)),
    }


def _write_tick(writer, v, k, bars=("main", "hand")):
    t = float(v["t"][k])
    for b, bar in enumerate(bars):
        writer.write_device_sample(bar, HapticSample(time=t, position=v["device_position"][b, k],
                                                     orientation=v["device_orientation"][k],
                                                     buttons=int(v["buttons"][k])))
        writer.write_force(bar, t, v["force"][b, k])
        writer.write_bar_pose(bar, t, v["bar_position"][b, k], v["bar_rotation"][b, k])
        writer.write_feedback(bar, t, v["eq4"][b, k], v["reaction"][b, k])
    writer.write_taut(t, v["taut"][k])
    if k % 33 == 0:
        f = k // 33
        writer.write_puppet_state(t, v["joint_q"][f], v["body_pos"][f], v["body_rot"][f])


@pytest.fixture(scope="module")
def synthetic_file(tmp_path_factory, scene, scene_text):
    values = _synthetic()
    path = tmp_path_factory.mktemp("session") / "synthetic.mcap"
    with SessionWriter(path, scene, scene_text) as writer:
        for k in range(len(values["t"])):
            _write_tick(writer, values, k)
    return path, values


TOPICS = ["/device/main/sample", "/device/main/force", "/bar/main/pose", "/bar/main/feedback",
          "/device/hand/sample", "/device/hand/force", "/bar/hand/pose", "/bar/hand/feedback",
          "/strings/taut", "/puppet/state"]


def test_round_trip_gives_back_every_value_exactly(synthetic_file, scene):
    path, v = synthetic_file
    session = read_session(path)
    assert not session.truncated
    assert sorted(session.channels) == sorted(TOPICS)
    for b, bar in enumerate(["main", "hand"]):
        sample = session.channels[f"/device/{bar}/sample"]
        np.testing.assert_array_equal(sample["t"], v["t"])
        origin = session.metadata["log_time_origin_ns"]  # wall clock at the start (format 2)
        np.testing.assert_array_equal(sample["log_time"] - origin, np.round(v["t"] * 1e9).astype(np.int64))
        np.testing.assert_array_equal(sample["position"], v["device_position"][b])
        np.testing.assert_array_equal(sample["orientation"], v["device_orientation"])
        np.testing.assert_array_equal(sample["buttons"], v["buttons"])
        assert sample["buttons"].dtype == np.int64
        np.testing.assert_array_equal(session.channels[f"/device/{bar}/force"]["force"], v["force"][b])
        pose = session.channels[f"/bar/{bar}/pose"]
        np.testing.assert_array_equal(pose["position"], v["bar_position"][b])
        np.testing.assert_array_equal(pose["rotation"], v["bar_rotation"][b])
        feedback = session.channels[f"/bar/{bar}/feedback"]
        np.testing.assert_array_equal(feedback["eq4"], v["eq4"][b])
        np.testing.assert_array_equal(feedback["reaction"], v["reaction"][b])
    np.testing.assert_array_equal(session.channels["/strings/taut"]["taut"], v["taut"])
    puppet = session.channels["/puppet/state"]
    np.testing.assert_array_equal(puppet["t"], v["puppet_t"])
    for key in ("joint_q", "body_pos", "body_rot"):
        np.testing.assert_array_equal(puppet[key], v[key])
    # Metadata and the scene, rebuilt from the embedded (self-contained) TOML.
    assert session.metadata["string_hz"] == 1000.0 and session.metadata["puppet_hz"] == 30.0
    assert session.bars == ["main", "hand"] and session.strings == [s.name for s in scene.strings]
    assert len(session.bodies) == BODIES and session.metadata["recorder"] == "live"
    assert session.scene.source == f"{path}#scene" and session.scene.name == scene.name
    assert session.scene.strings == scene.strings and session.scene.puppet == scene.puppet
    assert session.metadata["constants"]["feedback"] == {"stiffness": 5.0, "damping": 0.5}
    assert session.scene_record["toml"] == Path(scene.source).read_text()


def test_info_counts_messages_and_rates(synthetic_file):
    path, v = synthetic_file
    info = session_info(path)
    assert info["truncated"] is False and info["scene"] == "hanging" and info["device_channels"] is True
    assert info["bars"] == ["main", "hand"] and info["duration"] == pytest.approx(v["t"][-1])
    steps, frames = len(v["t"]), len(v["puppet_t"])
    for topic in TOPICS:
        expected = frames if topic == "/puppet/state" else steps
        assert info["topics"][topic]["count"] == expected, topic
    assert info["topics"]["/bar/main/pose"]["rate_hz"] == pytest.approx(1000.0)
    assert info["topics"]["/puppet/state"]["rate_hz"] == pytest.approx(1000.0 / 33)
    assert info["messages"] == 9 * steps + 4 * frames  # and /foxglove/transforms, scene, points per frame
    json.dumps(info)  # JSON-ready


class _JsonDecoderFactory(DecoderFactory):
    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def test_the_standard_mcap_reader_opens_the_file(synthetic_file):
    path, v = synthetic_file
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[_JsonDecoderFactory()])
        header, summary = reader.get_header(), reader.get_summary()
        assert header.profile == "" and header.library.startswith("dmarionette")
        counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
                  if not summary.channels[c].topic.startswith("/foxglove/")}  # tests/io/test_session_foxglove.py
        assert sorted(counts) == sorted(TOPICS)
        json_channels = [c for c in summary.channels.values() if c.topic in TOPICS]
        assert all(summary.schemas[c.schema_id].encoding == "jsonschema" for c in json_channels)
        assert all(c.message_encoding == "json" for c in json_channels)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert set(metadata) == {"scene", "dmarionette"}
        assert json.loads(metadata["dmarionette"]["bars"]) == ["main", "hand"]
        origin = json.loads(metadata["dmarionette"]["log_time_origin_ns"])
        seen = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=TOPICS):
            assert message.log_time == origin + round(decoded["t"] * 1e9)
            spec = json.loads(schema.data)
            assert set(spec["required"]) <= set(decoded), channel.topic
            for key, prop in spec["properties"].items():  # a small JSON Schema check: array lengths
                if "minItems" in prop:
                    assert len(decoded[key]) == prop["minItems"], (channel.topic, key)
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
        assert seen == counts
        assert counts["/bar/main/pose"] == len(v["t"])
    assert {s["title"] for s in SCHEMAS.values()} == set(SCHEMAS)


@pytest.mark.parametrize("chunk_bytes", [None, 256 * 1024])
def test_a_file_copied_while_being_written_reads_back_to_within_a_second(tmp_path, scene, scene_text,
                                                                         chunk_bytes):
    """Copy the bytes of a session still open (no close, no footer), then cut them anywhere;
    unchunked (the default) and chunked."""
    values = _synthetic(seed=1, steps=3400)
    path = tmp_path / "live.mcap"
    writer = SessionWriter(path, scene, scene_text, flush_seconds=1.0, chunk_bytes=chunk_bytes)
    for k in range(len(values["t"])):
        _write_tick(writer, values, k)
    copy = tmp_path / "copy.mcap"
    shutil.copyfile(path, copy)  # the writer is still open
    last_written = values["t"][-1]
    session = read_session(copy)
    assert session.truncated
    pose = session.channels["/bar/main/pose"]
    lost = last_written - pose["t"][-1]
    assert 0.0 <= lost <= 1.0 + 1e-3, lost  # measured: unchunked 0-1 ms, chunked 0.06-0.16 s
    np.testing.assert_array_equal(pose["position"], values["bar_position"][0, :len(pose["t"])])
    assert session_info(copy)["truncated"] is True
    # The writer goes on and closes normally.
    writer.close()
    with path.open("rb") as f:
        assert make_reader(f).get_summary().statistics.chunk_count > 0  # closed: rewritten chunked (index.py)
    assert read_session(path).channels["/bar/main/pose"]["t"][-1] == last_written
    # Cut the copy at arbitrary bytes (mid-record): each cut reads back a prefix, no error.
    data = copy.read_bytes()
    cut = tmp_path / "cut.mcap"
    previous = -1
    with pytest.raises(ValueError, match="cut off after 2000 bytes, before its metadata"):
        cut.write_bytes(data[:2000])
        read_session(cut)
    for size in np.linspace(len(data) // 5, len(data), 9).astype(int):
        cut.write_bytes(data[:size])
        t = read_session(cut).channels.get("/bar/main/pose", {"t": np.zeros(0)})["t"]
        np.testing.assert_array_equal(t, values["t"][:len(t)])
        assert len(t) >= previous
        previous = len(t)
    assert previous == len(pose["t"])
    # The standard linear reader also reads an unterminated file up to the cut, then stops with an error.
    with copy.open("rb") as f:
        topics = []
        with pytest.raises(Exception):
            for _, channel, _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                topics.append(channel.topic)
        assert topics.count("/bar/main/pose") >= len(pose["t"])


_CRASH = textwrap.dedent("""
    import os, sys, time
    import numpy as np
    import dmarionette as dm
    from dmarionette.io.session import SessionWriter
    scene = dm.load_scene("hanging")
    writer = SessionWriter(sys.argv[1], scene, open(scene.source).read(), flush_seconds=1.0)
    steps, pause = int(sys.argv[2]), float(sys.argv[3])
    for k in range(steps):
        writer.write_bar_pose("main", k * 1e-3, [0.0, 1.3, k * 1e-3], [0.0, 0.0, 0.0])
    time.sleep(pause)   # the simulation stalls: the wall-clock flush must still write
    os._exit(1)         # a crash: no close, no Python buffers flushed
""")


@pytest.mark.parametrize("steps, pause", [(2700, 0.0), (300, 1.6)])
def test_a_crashed_recorder_loses_at_most_one_second(tmp_path, steps, pause):
    """A process that dies without closing: at most 1 s of simulated time lost; nothing when
    the crash comes more than a second (wall clock) after the last message."""
    path = tmp_path / "crash.mcap"
    run = subprocess.run([sys.executable, "-c", _CRASH, str(path), str(steps), str(pause)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1, run.stderr
    t = read_session(path).channels["/bar/main/pose"]["t"]
    last = (steps - 1) * 1e-3
    np.testing.assert_array_equal(t, 1e-3 * np.arange(len(t)))
    if pause:
        assert len(t) == steps
    else:
        assert last - t[-1] <= 1.0 + 1e-3, last - t[-1]


def test_bad_files_are_refused_with_clear_messages(tmp_path, scene, scene_text):
    text = tmp_path / "notes.mcap"
    text.write_text("hello, not an MCAP file\n")
    with pytest.raises(ValueError, match=r"notes\.mcap: not an MCAP file"):
        read_session(text)
    with pytest.raises(ValueError, match="no such session file"):
        read_session(tmp_path / "missing.mcap")
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel("/imu", "json", 0)
        writer.add_message(channel, 0, b"{}", 0)
        writer.finish()
    with pytest.raises(ValueError, match=r"foreign\.mcap: an MCAP file, but not a dmarionette session.*'/imu'"):
        session_info(foreign)
    # A session without its scene record.
    no_scene = tmp_path / "no_scene.mcap"
    with no_scene.open("wb") as f:
        writer = Writer(f)
        writer.start()
        writer.add_metadata("dmarionette", {"format": json.dumps("dmarionette-session"), "format_version": "1",
                                            "string_hz": "1000", "puppet_hz": "30", "bars": "[]",
                                            "strings": "[]", "bodies": "[]", "constants": "{}"})
        writer.finish()
    with pytest.raises(ValueError, match="without its 'scene' metadata record"):
        read_session(no_scene)
    # A channel a reader needs that the session lacks.
    poses_only = tmp_path / "poses.mcap"
    with SessionWriter(poses_only, scene, scene_text) as writer:
        writer.write_taut(0.0, [0] * 6)
    session = read_session(poses_only)
    with pytest.raises(ValueError, match=r"poses\.mcap: calibration needs the channels \['/bar/main/pose'\]"):
        session.require(["/bar/main/pose", "/strings/taut"], "calibration")
    with pytest.raises(ValueError):  # a scene text that is not TOML: refused before the file is made
        SessionWriter(tmp_path / "never.mcap", scene, "name = [unclosed")
    assert not (tmp_path / "never.mcap").exists()
    with pytest.raises(ValueError, match="reserved"):
        SessionWriter(tmp_path / "x.mcap", scene, scene_text).write_metadata("scene", {})


def test_the_embedded_scene_is_self_contained(tmp_path, scene):
    """A scene with an included puppet and a CSV bar trajectory still loads from the session
    when the session file is moved away from them."""
    folder = tmp_path / "scenes"
    folder.mkdir()
    shutil.copyfile(Path(scene.source).parent / "puppet.toml", folder / "my_puppet.toml")
    (folder / "sway.csv").write_text("t,x,y,z,rx,ry,rz\n0,0,1.3,0,0,0,0\n1,0.05,1.3,0,0,0,5\n")
    text = Path(scene.source).read_text().replace('include = "puppet.toml"', 'include = "my_puppet.toml"')
    start = text.index("[[bars.main.keyframes]]")
    text = text[:start] + 'trajectory_file = "sway.csv"\n' + text[text.index("# Hand bar"):]
    text = text.replace("[bars.main.attach]", "[bars.main]\n" + 'trajectory_file = "sway.csv"\n\n[bars.main.attach]', 1)
    text = text.replace('\ntrajectory_file = "sway.csv"\n# Hand bar', "\n# Hand bar")
    (folder / "mine.toml").write_text(text)
    mine = dm.load_scene(folder / "mine.toml")
    away = tmp_path / "elsewhere"
    away.mkdir()
    with SessionWriter(away / "s.mcap", mine, text, recorder="simulation") as writer:
        writer.write_metadata("device", {"name": "simulated", "max_force": 3.3})
    shutil.rmtree(folder)
    session = read_session(away / "s.mcap")
    assert session.scene.puppet == mine.puppet and session.scene.strings == mine.strings
    main = session.scene.bars[0].trajectory
    np.testing.assert_array_equal(main.times, [0.0, 1.0])
    np.testing.assert_array_equal(main.rotations[1], [0.0, 0.0, 5.0])
    assert session.extra_metadata["device"] == {"name": "simulated", "max_force": 3.3}
    assert 'include = "my_puppet.toml"' in session.scene_record["toml"]  # the text is kept verbatim


def test_device_samples_keep_their_own_clock_and_bad_times_are_refused(tmp_path, scene, scene_text):
    path = tmp_path / "clock.mcap"
    with SessionWriter(path, scene, scene_text) as writer:
        sample = HapticSample(time=12.5, position=np.zeros(3), orientation=np.array([1.0, 0, 0, 0]), buttons=2)
        writer.write_device_sample("main", sample, t=0.25)
        writer.write_device_sample("main", sample)
        with pytest.raises(ValueError, match=r"/bar/main/pose: time t = -0.001"):
            writer.write_bar_pose("main", -0.001, [0, 0, 0], [0, 0, 0])
        with pytest.raises(ValueError, match="time t = nan"):
            writer.write_force("main", float("nan"), [0, 0, 0])
        writer.write_force("main", 0.25, [np.nan, 1.0, np.inf])  # non-finite values: JSON null, read as NaN
    channel = read_session(path).channels["/device/main/sample"]
    np.testing.assert_array_equal(channel["t"], [0.25, 12.5])
    np.testing.assert_array_equal(channel["device_time"], [12.5, np.nan])
    force = read_session(path).channels["/device/main/force"]["force"]
    assert np.isnan(force[0, 0]) and force[0, 1] == 1.0 and np.isnan(force[0, 2])


def test_without_writer_flush_the_file_is_written_unchunked(tmp_path, scene, scene_text, monkeypatch):
    """Older mcap releases lack ``Writer.flush``: chunks asked for, the writer writes unchunked,
    and a copy of the open file still reads back."""
    monkeypatch.delattr(Writer, "flush")
    values = _synthetic(seed=2, steps=1500)
    path = tmp_path / "unchunked.mcap"
    writer = SessionWriter(path, scene, scene_text, chunk_bytes=64 * 1024, index_on_close=False)
    for k in range(len(values["t"])):
        _write_tick(writer, values, k)
    shutil.copyfile(path, tmp_path / "copy.mcap")
    lost = values["t"][-1] - read_session(tmp_path / "copy.mcap").channels["/bar/main/pose"]["t"][-1]
    assert 0.0 <= lost <= 1.0 + 1e-3
    writer.close()
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary.statistics.chunk_count == 0 and summary.statistics.message_count > 9 * 1500
    np.testing.assert_array_equal(read_session(path).channels["/bar/hand/pose"]["position"], values["bar_position"][1])
