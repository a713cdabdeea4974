"""Issue 18, the files the program reads: one test per class of bad input.

Scene and keyframes TOML (encoding, tested ranges, memory, misspelt names), session files
(metadata types, message types and lengths, damage vs cut off), NPZ trajectories (arrays,
dtypes, shapes, finiteness; a non-finite result refused before it is written) and puppet
names in the MJCF export (each case loads in MuJoCo). No Warp kernel is compiled.
"""

from __future__ import annotations

import copy
import json
import math
import re
import zipfile

import mujoco
import numpy as np
import pytest

from tests.support.bad_files import (
    edit_json,
    hanging_table,
    puppet_table,
    rewrite_session,
    synthetic_marionette_trajectory,
    synthetic_string_trajectory,
    write_session,
)
from dmarionette.articulation.mjcf import mjcf_names, puppet_to_mjcf
from dmarionette.articulation.solver import BallDescription
from dmarionette.io.export.common import ExportError, read_marionette_trajectory
from dmarionette.io.session import read_session, replay_session, session_bar_trajectories, session_info
from dmarionette.io.session.read import SessionError
from dmarionette.io.trajectory import (
    NonFiniteTrajectoryError,
    TrajectoryFileError,
    read_trajectory,
    write_marionette_trajectory,
    write_trajectory,
)
from dmarionette.scene.fields import SceneError
from dmarionette.scene.limits import TESTED_RANGES, check_duration, trajectory_bytes
from dmarionette.scene.puppet import puppet_from_table
from dmarionette.scene.scene import load_scene, scene_from_table


# ----------------------------------------------------------------------------- scenes


def _scene(edit, source="bad.toml", **kwargs):
    table = hanging_table()
    edit(table)
    return scene_from_table(table, source, **kwargs)


@pytest.mark.parametrize("edit, key, fragment", [
    (lambda t: t["string_defaults"].update(load_mass=1e30), "load_mass", "0 <= value <= 10 kg"),
    (lambda t: t["string_defaults"].update(stiffness=1e300), "stiffness", "<= 1e+06 N/m"),
    (lambda t: t.setdefault("world", {}).update(gravity=[0.0, -1e300, 0.0]), "gravity", "m/s^2"),
    (lambda t: t["puppet"]["bodies"]["head"].update(mass=1e30), "mass", "[puppet.bodies.head]"),
    (lambda t: t["strings"][0].update(mass=1e-30), "mass", "kg"),
    (lambda t: t.setdefault("contact", {}).update(stiffness=1e300), "stiffness", "[contact]"),
])
def test_finite_nonsense_is_refused_with_the_tested_range(edit, key, fragment):
    with pytest.raises(SceneError) as info:
        _scene(edit)
    message = str(info.value)
    assert message.startswith("bad.toml: [") and f"key '{key}'" in message and fragment in message
    assert "tested for" in message and "allow_untested = true" in message


def test_allow_untested_runs_a_scene_outside_the_tested_ranges():
    def edit(t):
        t["string_defaults"]["load_mass"] = 1e3
        t.setdefault("solver", {})["allow_untested"] = True
    assert _scene(edit).strings[0].load_mass == 1e3
    assert _scene(lambda t: t["string_defaults"].update(load_mass=1e3), allow_untested=True).strings[0].load_mass == 1e3
    with pytest.raises(SceneError, match="allow_untested.*true or false"):
        _scene(lambda t: t.setdefault("solver", {}).update(allow_untested="yes"))


def test_every_builtin_scene_is_inside_the_tested_ranges():
    for name in ("hanging", "strings", "chair", "ball"):
        load_scene(name)
    assert all(r.low <= r.high and r.reason for r in TESTED_RANGES.values())


def test_a_duration_that_does_not_fit_in_memory_is_refused_with_the_estimate():
    with pytest.raises(SceneError) as info:
        _scene(lambda t: t["scene"].update(duration=1e9))
    message = str(info.value)
    assert "bad.toml: [scene]: key 'duration': got 1000000000.0" in message
    assert "TiB" in message and "at most about" in message
    scene = load_scene("hanging")
    assert trajectory_bytes(scene, 1e9) > 1 << 40
    check_duration(scene, 10.0, "command line", "--duration")  # fine
    for bad in (math.inf, math.nan, 0.0, -1.0, "5"):
        with pytest.raises(SceneError, match="command line: key '--duration'"):
            check_duration(scene, bad, "command line", "--duration")


def test_a_misspelt_bar_attach_name_is_named_as_such():
    def edit(t):
        attach = t["bars"]["main"]["attach"]
        attach["hed"] = attach.pop("head")
    with pytest.raises(SceneError) as info:
        _scene(edit)
    assert "[bars.main.attach]: key 'hed'" in str(info.value) and "'head'" in str(info.value)


def test_non_utf8_scene_puppet_and_keyframes_files_are_named(tmp_path):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('[scene]\nname = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(SceneError, match=r"latin1\.toml: key '\(file\)'.*not UTF-8.*expected a TOML file in UTF-8"):
        load_scene(bad)
    scene = tmp_path / "scene.toml"
    scene.write_text('[scene]\nname = "x"\n[puppet]\ninclude = "latin1.toml"\n[[strings]]\nname = "a"\n'
                     'top = [0, 1, 0]\nbottom = [0, 0, 0]\n')
    with pytest.raises(SceneError, match=r"latin1\.toml.*not UTF-8"):
        load_scene(scene)
    from dmarionette.scene.puppet import load_puppet
    with pytest.raises(SceneError, match=r"latin1\.toml.*not UTF-8"):
        load_puppet(bad)
    from fitting.keyframes import KeyframeError, load_keyframes
    with pytest.raises(KeyframeError, match=r"latin1\.toml.*not UTF-8"):
        load_keyframes(bad)


def _keyframes_table():
    import tomllib
    from pathlib import Path
    return tomllib.loads((Path(__file__).parents[1] / "examples" / "keyframes_three_poses.toml").read_text())


@pytest.mark.parametrize("edit, fragment", [
    (lambda t: t["keyframes"][0]["points"].update(hand_left=[0.0, 1e300, 0.0]), "points]: key 'hand_left'"),
    (lambda t: t["keyframes"][2]["bodies"].update(torso=[-1e5, 0.0, 0.0]), "bodies]: key 'torso'"),
    (lambda t: t["keyframes"][1]["joints"].update(elbow_left=[1e6]), "joints]: key 'elbow_left'"),
])
def test_keyframe_targets_beyond_the_puppet_scale_are_refused(edit, fragment, tmp_path):
    from fitting.keyframes import KeyframeError, keyframes_from_table
    table = _keyframes_table()
    keyframes_from_table(copy.deepcopy(table), str(tmp_path / "k.toml"))
    edit(table)
    with pytest.raises(KeyframeError) as info:
        keyframes_from_table(table, str(tmp_path / "k.toml"))
    assert "k.toml" in str(info.value) and fragment.replace("]", "") in str(info.value).replace("]", "")


# ----------------------------------------------------------------------------- sessions


@pytest.fixture(scope="module")
def session_file(tmp_path_factory):
    return write_session(tmp_path_factory.mktemp("valid") / "take.mcap")


def test_the_valid_session_reads_clean(session_file):
    session = read_session(session_file)
    assert not session.truncated and session.notes == []
    assert len(session.channels["/bar/main/pose"]["t"]) == 70
    assert not session_info(session_file)["truncated"]


def _meta(key, value):
    def edit(name, values):
        if name == "dmarionette":
            values[key] = json.dumps(value) if value is not ... else "not json {"
        return values
    return edit


@pytest.mark.parametrize("key, value, fragment", [
    ("format_version", [1], "an integer >= 1"),
    ("format_version", 99, "upgrade dmarionette"),
    ("bars", 5, "a list of distinct non-empty names"),
    ("strings", ["a", "a"], "distinct"),
    ("string_hz", 0, "a rate in Hz"),
    ("string_hz", "fast", "a rate in Hz"),
    ("string_hz", 1e300, "<= 1e6"),
    ("puppet_hz", 2000.0, "<= string_hz"),
    ("constants", [], "a table of the scene's constants"),
    ("string_bars", ["main"], "one bar name (or null) per string"),
    ("joint_q_layout", "x", "joint, type, coordinate count"),
    ("bar_attach", {"main": {"head": [0, 0]}}, "attach point"),
    ("puppet_substeps", 0, "an integer >= 1"),
    ("bodies", ["torso"], "the embedded scene's bodies"),
    ("strings", ["a", "b", "c", "d", "e", "f"], "the embedded scene's strings"),
    ("string_hz", ..., "a JSON value"),
])
def test_session_metadata_of_a_wrong_type_or_inconsistent_is_refused(session_file, tmp_path, key, value, fragment):
    bad = rewrite_session(session_file, tmp_path / "bad.mcap", metadata=_meta(key, value))
    with pytest.raises(SessionError) as info:
        read_session(bad)
    message = str(info.value)
    assert message.startswith(str(bad)) and f"'{key}'" in message and fragment in message
    if key not in ("bodies", "strings") or fragment == "distinct":
        with pytest.raises(SessionError):
            session_info(bad)  # info reads the same metadata


def test_a_broken_scene_record_is_named(session_file, tmp_path):
    def edit(name, values):
        if name == "scene":
            values["table_json"] = "{broken"
        return values
    with pytest.raises(SessionError, match=r"metadata record 'scene': key 'table_json'.*as JSON"):
        read_session(rewrite_session(session_file, tmp_path / "bad.mcap", metadata=edit))


def _on(topic, edit, index=None):
    def message(t, i, data):
        return edit(data) if t == topic and (index is None or i == index) else data
    return message


@pytest.mark.parametrize("topic, edit, key, fragment", [
    ("/bar/main/pose", lambda d: b"[1, 2, 3]", "(message)", "a JSON list"),
    ("/bar/main/pose", lambda d: b"not json", "(message)", "not JSON"),
    ("/bar/main/pose", edit_json(lambda m: {**m, "position": m["position"][:2]}), "position", "a list of 3 numbers"),
    ("/bar/main/pose", edit_json(lambda m: {k: v for k, v in m.items() if k != "rotation"}), "rotation", "required"),
    ("/bar/hand/feedback", edit_json(lambda m: {**m, "eq4": "x"}), "eq4", "a list of 3 numbers"),
    ("/strings/taut", edit_json(lambda m: {**m, "taut": [1, 0]}), "taut", "one flag 0 or 1 per string (6"),
    ("/strings/taut", edit_json(lambda m: {**m, "taut": [2] * 6}), "taut", "one flag 0 or 1"),
    ("/puppet/state", edit_json(lambda m: {**m, "body_pos": m["body_pos"][:-1]}), "body_pos", "per body (12)"),
    ("/puppet/state", edit_json(lambda m: {**m, "joint_q": m["joint_q"][:-1]}), "joint_q", "25 generalised"),
    ("/puppet/state", edit_json(lambda m: {**m, "body_rot": [[0, 0, 1]] * 12}), "body_rot", "row of 4 numbers"),
    ("/bar/main/pose", edit_json(lambda m: {**m, "t": m["t"] + 1.0}), "t", "the message's log time"),
    ("/bar/main/pose", edit_json(lambda m: {**m, "t": "now"}), "t", "a finite time"),
])
def test_a_session_message_of_a_wrong_type_or_length_is_refused(session_file, tmp_path, topic, edit, key, fragment):
    bad = rewrite_session(session_file, tmp_path / "bad.mcap", message=_on(topic, edit, index=1))
    with pytest.raises(SessionError) as info:
        read_session(bad)
    message = str(info.value)
    assert f"channel {topic}, message #2" in message and f"key '{key}'" in message and fragment in message
    with pytest.raises(SessionError, match=f"message #2.*key '{re.escape(key)}'"):
        session_info(bad)  # a damaged message does not pass `dmarionette info`


def test_nan_bar_poses_are_refused_by_name(session_file, tmp_path):
    nan = edit_json(lambda m: {**m, "position": [None, None, None]})
    bad = rewrite_session(session_file, tmp_path / "nan.mcap", message=_on("/bar/main/pose", nan))
    session = read_session(bad)  # null is how the writer stores a non-finite number
    with pytest.raises(SessionError, match=r"channel /bar/main/pose: key 'position/rotation'.*no finite pose"):
        session_bar_trajectories(session)
    with pytest.raises(SessionError, match="no finite pose"):
        replay_session(bad)  # refused before any kernel is built


def test_a_session_without_puppet_state_has_nothing_to_compare(session_file, tmp_path):
    bad = rewrite_session(session_file, tmp_path / "no_state.mcap", drop_topics=("/puppet/state",))
    with pytest.raises(ValueError, match=r"no_state\.mcap: replay \(to compare.*\['/puppet/state'\]"):
        replay_session(bad)


def _flip(data: bytes, offset: int, count: int = 64) -> bytes:
    out = bytearray(data)
    out[offset:offset + count] = bytes(b ^ 0xFF for b in out[offset:offset + count])
    return bytes(out)


def test_overwritten_bytes_are_refused_with_where(session_file, tmp_path):
    data = session_file.read_bytes()
    bad = tmp_path / "flipped.mcap"
    for offset in (8, 60, 2000, len(data) // 2):
        bad.write_bytes(_flip(data, offset))
        with pytest.raises(SessionError) as info:
            read_session(bad)
        assert str(bad) in str(info.value) and ("damaged" in str(info.value) or "not JSON" in str(info.value))
        with pytest.raises(SessionError):
            session_info(bad)
    # One byte of a schema record's inner length: the record swallows the ones after it.
    bad.write_bytes(_flip(data, data.index(b"jsonschema") + 10, 1))
    with pytest.raises(SessionError, match=r"damaged MCAP record at byte \d+ \(or the one before it"):
        read_session(bad)


def test_overwritten_bytes_of_an_indexed_session_are_refused(tmp_path):
    """A recording that closed normally is chunked and zstd-compressed: a byte flipped inside a
    chunk fails its decompression or its CRC, and the file is refused as damaged."""
    path = write_session(tmp_path / "indexed.mcap", indexed=True)
    read_session(path)
    data = path.read_bytes()
    chunk = data.index(b"zstd")  # the first chunk's compression name; its compressed records follow
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(_flip(data, chunk + 40))
    with pytest.raises(SessionError, match="damaged"):
        read_session(bad)


def test_the_data_section_crc_is_checked_when_the_writer_stored_one(tmp_path):
    path = write_session(tmp_path / "crc.mcap", enable_data_crcs=True)
    read_session(path)
    data = path.read_bytes()
    # A digit of a bar position changed: still valid JSON, caught by the CRC only.
    at = data.index(b'"position":[0.0,0.9')
    bad = tmp_path / "digit.mcap"
    bad.write_bytes(data[:at + 17] + b"8" + data[at + 18:])
    with pytest.raises(SessionError, match=r"CRC .* does not match|the file is damaged between"):
        read_session(bad)


def test_a_damaged_summary_is_flagged_and_a_cut_off_file_still_reads(session_file, tmp_path):
    data = session_file.read_bytes()
    damaged = tmp_path / "summary.mcap"
    damaged.write_bytes(_flip(data, len(data) - 200, 8))
    session = read_session(damaged)
    assert any("summary section" in n and "damaged" in n for n in session.notes)
    assert any("summary section" in n for n in session_info(damaged)["notes"])
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 3 // 4])  # inside the data section (the summary is the last ~10 %)
    session = read_session(cut)
    assert session.truncated and any("cut off" in n for n in session.notes)
    assert 0 < len(session.channels["/bar/main/pose"]["t"]) <= 70


# ----------------------------------------------------------------------------- NPZ trajectories


@pytest.fixture(scope="module")
def scenes():
    return load_scene("strings"), load_scene("hanging")


def _npz(path, arrays):
    np.savez(path, **arrays)
    return path


def _arrays(path):
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def test_a_non_finite_result_is_refused_before_it_is_written(scenes, tmp_path):
    strings, hanging = scenes
    good = write_trajectory(tmp_path / "good.npz", synthetic_string_trajectory(), strings)
    assert read_trajectory(good)["particle_q"].shape == (6, 6, 3)
    blown = synthetic_string_trajectory()
    blown.particle_q = blown.particle_q.copy()
    blown.particle_q[3, 4, 1] = np.nan
    with pytest.raises(NonFiniteTrajectoryError, match=r"particle_q\[3, 4, 1\] at t = 0\.03 s") as info:
        write_trajectory(tmp_path / "bad.npz", blown, strings)
    assert info.value.quantity == "particle_q" and info.value.time == pytest.approx(0.03)
    assert not (tmp_path / "bad.npz").exists()
    flagged = write_trajectory(tmp_path / "flagged.npz", blown, strings, allow_non_finite=True)
    assert read_trajectory(flagged, allow_non_finite=True)["metadata"]["finite"] is False
    with pytest.raises(TrajectoryFileError, match=r"flagged\.npz: field 'particle_q'.*non-finite.*\[3, 4, 1\]"):
        read_trajectory(flagged)
    m = synthetic_marionette_trajectory()
    m.tie_force = m.tie_force.copy()
    m.tie_force[7, 1, 0] = np.inf
    with pytest.raises(NonFiniteTrajectoryError, match=r"tie_force\[7, 1, 0\] at t = 0\.0266"):
        write_marionette_trajectory(tmp_path / "m.npz", m, hanging)
    assert not (tmp_path / "m.npz").exists()


@pytest.mark.parametrize("change, fragment", [
    (lambda a: a.pop("tie_force"), r"fields \['tie_force'\]: got nothing"),
    (lambda a: a.update(particle_q=a["particle_q"][:, :, :2]), r"field 'particle_q': got shape \(6, 6, 2\)"),
    (lambda a: a.update(tie_force=a["tie_force"][:-1]), r"field 'tie_force': got shape \(14, 2, 3\).*T = 15 \(as field 'step_time'"),
    (lambda a: a.update(top_q=a["top_q"][:, :1]), r"field 'tie_force'.*S = 1 \(as field 'top_q' has it\)"),
    (lambda a: a.update(string_names=np.array([1, 2])), r"field 'string_names': got dtype int64; expected strings"),
    (lambda a: a.update(frame_time=a["frame_time"].astype(str)), r"field 'frame_time': got dtype <U"),
    (lambda a: a.update(energy=np.full(6, np.inf)), r"field 'energy': got a non-finite value at index \[0\]"),
    (lambda a: a.update(step_time=a["step_time"][::-1].copy()), r"field 'step_time'.*strictly increasing"),
    (lambda a: a.update(string_start=np.array([0, 1, 6])), r"field 'string_start'"),
    (lambda a: a.update(metadata=np.array("{not json")), r"field 'metadata': not valid JSON"),
    (lambda a: a.update(metadata=np.array(json.dumps({"format": "x"}))), r"field 'metadata.format': got 'x'"),
    (lambda a: a.update(metadata=np.array(json.dumps({**json.loads(str(a["metadata"])), "string_dt": -1}))),
     r"field 'metadata.string_dt': got -1"),
    (lambda a: a.pop("metadata"), r"field 'metadata': got nothing"),
])
def test_a_bad_string_trajectory_file_is_refused_naming_the_array(scenes, tmp_path, change, fragment):
    good = write_trajectory(tmp_path / "good.npz", synthetic_string_trajectory(), scenes[0])
    arrays = _arrays(good)
    change(arrays)
    bad = _npz(tmp_path / "bad.npz", arrays)
    with pytest.raises(TrajectoryFileError, match=r"bad\.npz: " + fragment):
        read_trajectory(bad)


@pytest.mark.parametrize("change, fragment", [
    (lambda a: a.update(body_pos=a["body_pos"][:, :1]), r"field 'body_rot'.*B = 1 \(as field 'body_pos' has it\)"),
    (lambda a: a.update(bar_feedback=a["bar_feedback"][:3]), r"field 'bar_feedback'"),
    (lambda a: a.update(body_rot=np.full_like(a["body_rot"], np.nan)), r"field 'body_rot'.*non-finite"),
    (lambda a: a.update(metadata=np.array(json.dumps({**json.loads(str(a["metadata"])), "body_shape": 5}))),
     r"metadata.body_shape': got 5"),
    (lambda a: a.update(metadata=np.array(json.dumps({**json.loads(str(a["metadata"])), "kind": "x"}))),
     r"metadata.kind': got 'x'"),
])
def test_a_bad_marionette_trajectory_file_is_refused_for_export(scenes, tmp_path, change, fragment):
    good = write_marionette_trajectory(tmp_path / "good.npz", synthetic_marionette_trajectory(), scenes[1])
    assert read_marionette_trajectory(good).body_pos.shape == (6, 2, 3)
    arrays = _arrays(good)
    change(arrays)
    with pytest.raises(ExportError, match=r"bad\.npz: .*" + fragment):
        read_marionette_trajectory(_npz(tmp_path / "bad.npz", arrays))


def test_a_damaged_npz_is_refused(scenes, tmp_path):
    good = write_trajectory(tmp_path / "good.npz", synthetic_string_trajectory(), scenes[0])
    data = good.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(TrajectoryFileError, match=r"cut\.npz: not a NumPy \.npz archive|cut\.npz: cannot be read"):
        read_trajectory(cut)
    flipped = tmp_path / "flipped.npz"
    flipped.write_bytes(data[:200] + bytes(b ^ 0xFF for b in data[200:264]) + data[264:])
    with pytest.raises(TrajectoryFileError, match=r"flipped\.npz"):
        read_trajectory(flipped)
    assert zipfile.is_zipfile(good)


# ----------------------------------------------------------------------------- puppet names in MJCF


def _rename_body(table, old, new):
    table["bodies"][new] = table["bodies"].pop(old)
    if table["root"] == old:
        table["root"] = new
    for joint in table["joints"].values():
        for key in ("parent", "child"):
            if joint[key] == old:
                joint[key] = new
    for point in table.get("points", {}).values():
        if point["body"] == old:
            point["body"] = new


def _rename_joint(table, old, new):
    table["joints"][new] = table["joints"].pop(old)


@pytest.mark.parametrize("edit, ball", [
    (lambda t: _rename_body(t, "head", "ground"), False),
    (lambda t: _rename_joint(t, "elbow_left", "shoulder_left_0"), False),
    (lambda t: _rename_joint(t, "knee_left", "root"), False),
    (lambda t: _rename_body(t, "head", "ball"), True),
    (lambda t: _rename_joint(t, "neck", "ball"), True),
    (lambda t: _rename_body(t, "torso", "world"), True),
    (lambda t: (_rename_body(t, "head", "ball"), _rename_body(t, "upper_arm_left", "ball_1")), True),
])
def test_puppet_names_that_clash_with_the_exporter_still_load_in_mujoco(edit, ball):
    table = puppet_table()
    edit(table)
    puppet = puppet_from_table(table, "renamed.toml: [puppet]")
    description = BallDescription(radius=0.06, mass=0.08, position=(0.3, 0.06, 0.2)) if ball else None
    model = mujoco.MjModel.from_xml_string(puppet_to_mjcf(puppet, ball=description))
    names = mjcf_names(puppet)
    assert model.nbody == 1 + len(puppet.bodies) + (1 if ball else 0)
    for body in puppet.bodies:  # every puppet body maps to its MJCF body, in order
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, names.bodies[body.name]) >= 1
    for joint in puppet.joints:
        for jname in names.joints[joint.name]:
            assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname) >= 0
    kept = [b.name for b in puppet.bodies if b.name != "world"]
    assert all(names.bodies[n] == n for n in kept)  # the puppet's own names are kept


def test_default_puppet_names_are_unchanged():
    puppet = puppet_from_table(puppet_table(), "puppet.toml: [puppet]")
    names = mjcf_names(puppet)
    assert names.root_joint == "root" and names.ground == "ground" and names.ball == ("ball", "ball", "ball")
    assert names.joints["shoulder_left"] == ("shoulder_left_0", "shoulder_left_1")
