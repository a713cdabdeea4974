"""Issue 18: property-based fuzzing of the file loaders (hypothesis).

Scene and keyframes tables (valid structure with random bad values; random damage to the
TOML text), sessions (valid recordings with metadata and message fields removed, retyped or
cut short; files cut off; bytes overwritten), NPZ trajectories (arrays removed, reshaped,
retyped, made non-finite; bytes overwritten). The property: the loader returns, or raises the
project's error type (SceneError / KeyframeError / SessionError / TrajectoryFileError)
whose message names the file and the key or array; never another exception, and nothing
is written. Bounded: 80 examples each, no Warp kernel (about 20 s in all).
"""

from __future__ import annotations

import copy
import json
import os
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.support.bad_files import (
    hanging_table,
    rewrite_session,
    synthetic_marionette_trajectory,
    synthetic_string_trajectory,
    write_session,
)
from dmarionette.io.session.read import SessionError, read_session, session_info
from dmarionette.io.trajectory import TrajectoryFileError, read_trajectory, write_marionette_trajectory, write_trajectory
from dmarionette.scene.fields import SceneError
from dmarionette.scene.scene import SCENE_DIR, load_scene, scene_from_table

# DMARIONETTE_FUZZ_EXAMPLES=1000 runs a longer, random (not derandomized) search locally.
_EXAMPLES = int(os.environ.get("DMARIONETTE_FUZZ_EXAMPLES", "0"))
FUZZ = settings(max_examples=_EXAMPLES or 80, deadline=None, derandomize=not _EXAMPLES,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

BAD_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e30, -1e30, 1e300, -1e300, 0.0, -0.0, -1.0, 1e-300, 1e9, 2**63, -(2**63)]),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.booleans(),
    st.text(max_size=8),
    st.lists(st.one_of(st.floats(), st.integers(), st.text(max_size=3)), max_size=5),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=3),
)


def _leaves(table, path=()):
    """Every (path, value) of a nested table: dict keys and list indices."""
    if isinstance(table, dict):
        for k, v in table.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(table, list) and table and isinstance(table[0], (dict, list)):
        for i, v in enumerate(table):
            yield from _leaves(v, path + (i,))
    else:
        yield path, table
    if path:
        yield path, table  # the table (or list) itself, replaced whole


def _set(table, path, value):
    for part in path[:-1]:
        table = table[part]
    table[path[-1]] = value


def _delete(table, path):
    for part in path[:-1]:
        table = table[part]
    if isinstance(table, dict):
        del table[path[-1]]
    else:
        table.pop(path[-1])


def _names_the_place(message: str, path: tuple) -> bool:
    """The message names a key or table of the mutated path (or the value's own key name)."""
    words = [str(p) for p in path if isinstance(p, str)]
    return any(w in message for w in words) or "[[strings]]" in message


def _damaged(table: dict, path: tuple, value, remove: bool) -> dict:
    """A copy of ``table`` with the leaf at ``path`` removed, or set to ``value``."""
    table = copy.deepcopy(table)
    if remove:
        _delete(table, path)
    else:
        _set(table, path, value)
    return table


def _refusal(load, error_type):
    """The project's error ``load()`` raised (None if it accepted the input), checked to name its key;
    any other exception fails the test."""
    try:
        load()
    except error_type as error:
        assert f"key '{error.key}'" in str(error), str(error)
        return error
    return None


HANGING = hanging_table()
SCENE_LEAVES = [p for p, _ in _leaves(HANGING)]


@FUZZ
@given(st.sampled_from(SCENE_LEAVES), BAD_VALUES, st.booleans())
def test_fuzz_scene_values(path, value, remove):
    error = _refusal(lambda: scene_from_table(_damaged(HANGING, path, value, remove), "fuzz.toml"), SceneError)
    if error is not None:
        message = str(error)
        assert message.startswith("fuzz.toml"), message
        assert _names_the_place(message, path) or remove, (path, message)


TOML_TEXT = (SCENE_DIR / "hanging.toml").read_bytes()


@FUZZ
@given(st.data())
def test_fuzz_scene_file_damage(tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("scene")
    text = bytearray(TOML_TEXT)
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(text) - 1))
        kind = data.draw(st.sampled_from(["delete", "insert", "replace", "cut"]))
        piece = data.draw(st.binary(min_size=1, max_size=6) | st.sampled_from([b"[", b"]", b"=", b'"', b"\n", b"\xff"]))
        if kind == "delete":
            del text[at:at + len(piece)]
        elif kind == "insert":
            text[at:at] = piece
        elif kind == "replace":
            text[at:at + len(piece)] = piece
        else:
            del text[at:]
        if not text:
            text = bytearray(b"\xff")
    path = folder / "damaged.toml"
    path.write_bytes(bytes(text))
    try:
        load_scene(path)
    except SceneError as error:
        assert str(path) in str(error) and f"key '{error.key}'" in str(error)
    assert sorted(p.name for p in folder.iterdir()) == ["damaged.toml"]


KEYFRAMES = tomllib.loads((Path(__file__).parents[1] / "examples" / "keyframes_three_poses.toml").read_text())
KEYFRAME_LEAVES = [p for p, _ in _leaves(KEYFRAMES) if p[:2] != ("author", "scene")]


@FUZZ
@given(st.sampled_from(KEYFRAME_LEAVES), BAD_VALUES, st.booleans())
def test_fuzz_keyframes_values(path, value, remove):
    from fitting.keyframes import KeyframeError, keyframes_from_table

    error = _refusal(lambda: keyframes_from_table(_damaged(KEYFRAMES, path, value, remove), "fuzz_keys.toml"),
                     KeyframeError)
    if error is not None:
        message = str(error)
        assert "fuzz_keys.toml" in message or SCENE_DIR.name in message, message


# ----------------------------------------------------------------------------- sessions


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_sessions")
    plain = write_session(folder / "plain.mcap")
    crc = write_session(folder / "crc.mcap", enable_data_crcs=True)
    return plain, crc, read_session(plain)


def _same_channels(a, b) -> bool:
    if sorted(a.channels) != sorted(b.channels):
        return False
    for topic, fields in a.channels.items():
        other = b.channels[topic]
        if sorted(fields) != sorted(other):
            return False
        for key, value in fields.items():
            if value.shape != other[key].shape or not np.array_equal(value, other[key], equal_nan=True):
                return False
    return True


def _same_layout(a, b) -> bool:
    """The same channels, fields and array shapes (the values may differ)."""
    return sorted(a.channels) == sorted(b.channels) and all(
        sorted(f) == sorted(b.channels[t]) and all(v.shape == b.channels[t][k].shape for k, v in f.items())
        for t, f in a.channels.items())


def _read(path):
    """read_session, or the SessionError/SceneError it raises (checked to name the file)."""
    try:
        return read_session(path)
    except (SessionError, SceneError) as error:
        assert str(path) in str(error), str(error)
        assert f"key '{error.key}'" in str(error) or str(error).startswith(str(path))
        try:
            session_info(path)
        except (SessionError, SceneError) as info_error:
            assert str(path) in str(info_error)
        return None


META_KEYS = ["format", "format_version", "string_hz", "puppet_hz", "puppet_substeps", "bars", "bar_attach",
             "strings", "string_bars", "bodies", "joint_q_layout", "constants", "recorder"]
FIELDS = {"/bar/main/pose": ["t", "position", "rotation"], "/bar/hand/feedback": ["t", "eq4", "reaction"],
          "/strings/taut": ["t", "taut"], "/puppet/state": ["t", "joint_q", "body_pos", "body_rot"]}
JSONISH = st.one_of(st.none(), st.booleans(), st.integers(-10, 10**6), st.floats(allow_nan=False),
                    st.text(max_size=5), st.lists(st.integers(0, 3), max_size=4),
                    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@FUZZ
@given(st.sampled_from(META_KEYS), JSONISH, st.booleans())
def test_fuzz_session_metadata(sessions, tmp_path_factory, key, value, remove):
    plain, _, _ = sessions
    folder = tmp_path_factory.mktemp("meta")

    def edit(name, values):
        if name == "dmarionette":
            if remove:
                values.pop(key, None)
            else:
                values[key] = json.dumps(value)
        return values
    path = rewrite_session(plain, folder / "meta.mcap", metadata=edit)
    session = _read(path)
    if session is not None:  # accepted: the value is one the format allows
        assert session.metadata.get(key) == (None if remove else value)
        assert remove or key not in ("format", "format_version", "string_hz", "bars", "strings", "bodies") or \
            value == json.loads(json.dumps(value))
    assert sorted(p.name for p in folder.iterdir()) == ["meta.mcap"]


@FUZZ
@given(st.sampled_from(sorted(FIELDS)), st.data())
def test_fuzz_session_messages(sessions, tmp_path_factory, topic, data):
    plain, _, original = sessions
    key = data.draw(st.sampled_from(FIELDS[topic]))
    index = data.draw(st.integers(0, 2))
    how = data.draw(st.sampled_from(["remove", "retype", "shorten", "lengthen", "array", "garbage"]))
    replacement = data.draw(JSONISH)

    def message(t, i, raw):
        if t != topic or i != index:
            return raw
        if how == "garbage":
            return raw[: len(raw) // 2]
        if how == "array":
            return json.dumps(list(json.loads(raw).values())).encode()
        m = json.loads(raw)
        if how == "remove":
            m.pop(key)
        elif how == "retype":
            m[key] = replacement
        elif how == "shorten" and isinstance(m[key], list):
            m[key] = m[key][:-1]
        elif how == "lengthen" and isinstance(m[key], list):
            m[key] = m[key] + [m[key][-1]]
        return json.dumps(m).encode()
    path = rewrite_session(plain, tmp_path_factory.mktemp("msg") / "msg.mcap", message=message)
    session = _read(path)
    if session is not None:  # accepted only when the change was harmless or a value the schema allows
        assert how in ("retype", "shorten", "lengthen"), how
        assert key != "t" or how != "remove"


@FUZZ
@given(st.floats(0.0, 1.0), st.integers(1, 64))
def test_fuzz_session_overwritten_bytes(sessions, tmp_path_factory, where, count):
    plain, crc, original = sessions
    for source in (plain, crc):
        data = source.read_bytes()
        at = min(int(where * len(data)), len(data) - 1)
        damaged = bytearray(data)
        damaged[at:at + count] = bytes(b ^ 0xFF for b in damaged[at:at + count])
        path = tmp_path_factory.mktemp("flip") / source.name
        path.write_bytes(bytes(damaged))
        session = _read(path)
        # With data CRCs, never silently wrong: refused, flagged, or exactly the original's data.
        # Without them (the unchunked file a crash leaves) a flip inside a message's binary value is
        # undetectable by any reader: it may change values, never the channels, fields or shapes.
        ok = session is None or session.notes or _same_channels(session, original)
        if source is plain and not ok:
            ok = _same_layout(session, original)
        assert ok, (source.name, at, count)


@FUZZ
@given(st.floats(0.0, 0.999))
def test_fuzz_session_cut_off(sessions, tmp_path_factory, where):
    plain, _, original = sessions
    data = plain.read_bytes()
    path = tmp_path_factory.mktemp("cut") / "cut.mcap"
    path.write_bytes(data[: max(1, int(where * len(data)))])
    session = _read(path)
    if session is not None:
        assert session.notes, "a cut-off file is read with a note"
        for topic, fields in session.channels.items():  # a prefix of what was recorded
            n = len(fields["t"])
            assert np.array_equal(fields["t"], original.channels[topic]["t"][:n])


# ----------------------------------------------------------------------------- NPZ trajectories


@pytest.fixture(scope="module")
def npz_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_npz")
    strings = write_trajectory(folder / "strings.npz", synthetic_string_trajectory(), load_scene("strings"))
    marionette = write_marionette_trajectory(folder / "marionette.npz", synthetic_marionette_trajectory(),
                                             load_scene("hanging"))
    return strings, marionette


def _arrays(path):
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


@FUZZ
@given(st.booleans(), st.data())
def test_fuzz_npz_arrays(npz_files, tmp_path_factory, marionette, data):
    source = npz_files[1 if marionette else 0]
    arrays = _arrays(source)
    name = data.draw(st.sampled_from(sorted(arrays)))
    how = data.draw(st.sampled_from(["remove", "reshape", "retype", "nan", "shorten", "scalar"]))
    a = arrays[name]
    if how == "remove":
        arrays.pop(name)
    elif how == "reshape" and a.ndim > 0:
        arrays[name] = a.reshape(-1)[..., None] if a.ndim == 1 else a.reshape(a.shape[0], -1)
    elif how == "retype":
        try:
            arrays[name] = a.astype(data.draw(st.sampled_from([np.float32, np.int32, str, bool, np.complex64])))
        except (ValueError, TypeError, OverflowError):
            arrays[name] = np.array(["x"] * max(1, a.size))
    elif how == "nan" and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.reshape(-1)[data.draw(st.integers(0, a.size - 1))] = data.draw(st.sampled_from([np.nan, np.inf]))
        arrays[name] = a
    elif how == "shorten" and a.ndim > 0 and len(a):
        arrays[name] = a[:-1]
    elif how == "scalar":
        arrays[name] = np.array(data.draw(st.integers(-3, 3)))
    path = tmp_path_factory.mktemp("npz") / "fuzz.npz"
    np.savez(path, **arrays)
    try:
        read_trajectory(path)
    except TrajectoryFileError as error:
        message = str(error)
        assert message.startswith(str(path)), message
        assert name in message or "metadata" in message, (name, how, message)


@FUZZ
@given(st.floats(0.0, 1.0), st.integers(1, 64))
def test_fuzz_npz_overwritten_bytes(npz_files, tmp_path_factory, where, count):
    source = npz_files[0]
    data = source.read_bytes()
    at = min(int(where * len(data)), len(data) - 1)
    damaged = bytearray(data)
    damaged[at:at + count] = bytes(b ^ 0xFF for b in damaged[at:at + count])
    path = tmp_path_factory.mktemp("npzflip") / "flipped.npz"
    path.write_bytes(bytes(damaged))
    try:
        got = read_trajectory(path)
    except TrajectoryFileError as error:
        assert str(path) in str(error)
    else:  # the zip's CRCs cover every array: what reads is the original
        want = read_trajectory(source)
        assert all(np.array_equal(got[k], want[k]) for k in want if k != "metadata")
