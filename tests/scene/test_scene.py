"""Scene files: the built-in scenes load; bad input is refused with a clear error."""

from pathlib import Path

import pytest

from dmarionette.scene.scene import builtin_scenes, load_scene
from dmarionette.scene.fields import SceneError

MINIMAL = """
[scene]
name = "tiny"

[[strings]]
name = "a"
top = [0.0, 1.0, 0.0]
bottom = [0.0, 0.5, 0.0]
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


def test_builtin_scenes_load():
    assert {"hanging", "strings"} <= set(builtin_scenes())
    for name in builtin_scenes():
        scene = load_scene(name)
        assert scene.strings and scene.string_hz > 0


def test_minimal_scene_gets_documented_defaults(tmp_path):
    scene = load_scene(_write(tmp_path, MINIMAL))
    (string,) = scene.strings
    assert string.particle_count == 50 and string.length == pytest.approx(0.5)
    assert scene.string_hz == 1000.0 and scene.puppet_hz == 30.0 and scene.precision == "float64"


@pytest.mark.parametrize(
    "edit,key,expected",
    [
        (lambda t: t.replace('bottom = [0.0, 0.5, 0.0]', 'bottom = [0.0, 0.5, 0.0]\nstifness = 3.0'),
         "stifness", "one of the known keys"),
        (lambda t: t + "\n[string_defaults]\nstiffness = -5.0\n", "stiffness", "> 0"),
        (lambda t: t.replace('bottom = [0.0, 0.5, 0.0]', 'bottom = [0.0, 0.5, 0.0]\nparticle_count = 0'),
         "particle_count", ">= 2"),
        (lambda t: t.replace('bottom = [0.0, 0.5, 0.0]', 'bottom = [0.0, 0.5, 0.0]\nmass = nan'),
         "mass", "finite"),
        (lambda t: t.replace('bottom = [0.0, 0.5, 0.0]', 'bottom = [0.0, "x", 0.0]'), "bottom", "three numbers"),
        (lambda t: t + "\n[rates]\nstring_hz = 100.0\npuppet_hz = 200.0\n", "puppet_hz", "<= 100.0"),
        (lambda t: t + "\n[solver]\nprecision = \"float16\"\n", "precision", "float64"),
        (lambda t: t + "\n[effects]\nair_drag = 1\n", "air_drag", "true or false"),
        (lambda t: t.replace('top = [0.0, 1.0, 0.0]', 'top = [0.0, 0.5, 0.0]'), "length", "required"),
        (lambda t: t.replace('name = "tiny"', 'nme = "tiny"'), "nme", "one of the known keys"),
    ],
)
def test_bad_scene_is_refused_naming_file_key_value_and_expectation(tmp_path, edit, key, expected):
    path = _write(tmp_path, edit(MINIMAL))
    with pytest.raises(SceneError) as error:
        load_scene(path)
    message = str(error.value)
    assert str(path) in message
    assert f"'{key}'" in message
    assert expected in message


def test_duplicate_string_names_are_refused(tmp_path):
    text = MINIMAL + '\n[[strings]]\nname = "a"\ntop = [1.0, 1.0, 0.0]\nbottom = [1.0, 0.5, 0.0]\n'
    with pytest.raises(SceneError, match="no other string has"):
        load_scene(_write(tmp_path, text))


def test_unknown_scene_name_lists_the_builtin_ones():
    with pytest.raises(SceneError, match="hanging"):
        load_scene("no_such_scene")  # the message lists the built-in scenes, "hanging" among them


def test_invalid_toml_is_refused(tmp_path):
    with pytest.raises(SceneError, match="valid TOML"):
        load_scene(_write(tmp_path, "[scene\nname = 1"))
