"""The puppet description: the default marionette and refusal of malformed puppets."""

from __future__ import annotations

import copy
import math
import tomllib

import pytest

from dmarionette.scene.puppet import default_puppet_path, load_puppet, puppet_from_table
from dmarionette.scene.fields import SceneError


@pytest.fixture()
def table():
    with open(default_puppet_path(), "rb") as f:
        return copy.deepcopy(tomllib.load(f)["puppet"])


def test_default_marionette_matches_paper():
    p = load_puppet()
    assert len(p.bodies) == 12 and len(p.joints) == 11
    shapes = [b.shape for b in p.bodies]
    assert shapes.count("sphere") == 1 and shapes.count("box") == 11
    assert p.bodies[p.body_index("head")].shape == "sphere"
    types = {j.name: j.type for j in p.joints}
    assert types["neck"] == "ball"
    assert all(types[f"{j}_{s}"] == "universal" for j in ("shoulder", "hip") for s in ("left", "right"))
    assert all(types[f"{j}_{s}"] == "hinge" for j in ("elbow", "knee", "ankle") for s in ("left", "right"))
    assert {pt.name for pt in p.points} == {"head", "back", "hand_left", "hand_right", "knee_left", "knee_right"}
    assert p.total_mass() < 1.0
    # height: top of the head above the soles, about 0.6 m
    rest = p.rest_positions()
    top = rest[p.body_index("head")][1] + p.bodies[p.body_index("head")].size[0]
    bottom = min(rest[i][1] - b.size[1] / 2 for i, b in enumerate(p.bodies) if b.shape == "box")
    assert bottom == pytest.approx(0.0, abs=1e-12)
    assert 0.55 <= top - bottom <= 0.65


def test_default_inertia_from_shape():
    p = load_puppet()
    torso = p.bodies[p.body_index("torso")]
    sx, sy, sz = torso.size
    assert torso.inertia[0] == pytest.approx(torso.mass * (sy**2 + sz**2) / 12)
    head = p.bodies[p.body_index("head")]
    assert head.inertia[1] == pytest.approx(0.4 * head.mass * head.size[0] ** 2)


def test_inertia_override(table):
    table["bodies"]["torso"]["inertia"] = [1e-3, 2e-3, 2.5e-3]
    p = puppet_from_table(table, "t.toml: [puppet]")
    assert p.bodies[p.body_index("torso")].inertia == (1e-3, 2e-3, 2.5e-3)


def _refused(table, *fragments):
    with pytest.raises(SceneError) as err:
        puppet_from_table(table, "bad.toml: [puppet]")
    msg = str(err.value)
    assert "bad.toml" in msg
    for f in fragments:
        assert f in msg, msg
    return err.value


def test_joint_naming_missing_body(table):
    table["joints"]["knee_left"]["child"] = "shin_left"
    e = _refused(table, "knee_left", "'child'", "'shin_left'", "the name of a body")
    assert e.key == "child"


def test_cycle(table):
    # the lower leg becomes the parent of the upper leg, which is its parent: a cycle
    table["joints"]["hip_left"]["parent"] = "lower_leg_left"
    _refused(table, "cycle", "upper_leg_left")


def test_two_parents(table):
    table["joints"]["extra"] = dict(table["joints"]["knee_left"], parent="torso")
    _refused(table, "extra", "one parent", "knee_left")


def test_more_than_one_root(table):
    del table["joints"]["neck"]
    _refused(table, "head", "no parent joint", "one root")


@pytest.mark.parametrize("value", [0.0, -0.1, math.nan])
def test_non_positive_or_nan_mass(table, value):
    table["bodies"]["torso"]["mass"] = value
    _refused(table, "bodies.torso", "'mass'")


def test_non_positive_inertia(table):
    table["bodies"]["head"]["inertia"] = [1e-4, 0.0, 1e-4]
    _refused(table, "bodies.head", "'inertia'", "> 0")


def test_limit_lower_above_upper(table):
    table["joints"]["elbow_left"]["lower_deg"] = [10.0]
    table["joints"]["elbow_left"]["upper_deg"] = [5.0]
    _refused(table, "elbow_left", "'lower_deg'", "lower <= upper")


def test_unknown_key(table):
    table["joints"]["knee_left"]["dampin"] = 0.1
    _refused(table, "knee_left", "'dampin'", "known keys")


def test_nan_anchor(table):
    table["joints"]["neck"]["anchor_parent"] = [0.0, math.nan, 0.0]
    _refused(table, "neck", "anchor_parent", "finite")


def test_wrong_axis_count(table):
    table["joints"]["hip_left"]["axes"] = [[1.0, 0.0, 0.0]]
    _refused(table, "hip_left", "'axes'", "2 axis")
