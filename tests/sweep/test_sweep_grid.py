"""``dmarionette sweep``'s grid: --set flags read, the cartesian product, every variant validated by the
scene loader; bad keys and values refused with the scene's named errors before any work (no simulation here)."""

from __future__ import annotations

import sys

import pytest

import dmarionette.first_run
from dmarionette.cli import main
from dmarionette.scene.fields import SceneError
from dmarionette.scene.scene import SCENE_DIR
from dmarionette.sweep.grid import parse_set, sweep_variants

HANGING = str(SCENE_DIR / "hanging.toml")


def test_values_are_toml_split_at_top_level_commas():
    axis = parse_set("bars.hand.position=[0.0, 1.2, 0.1],[0.0,1.25,0.1]")
    assert axis.key == "bars.hand.position" and axis.values == ([0.0, 1.2, 0.1], [0.0, 1.25, 0.1])
    assert parse_set("solver.precision=float32,\"float64\"").values == ("float32", "float64")
    assert parse_set("strings.k=200, 2.5e2 ,true").values == (200, 250.0, True)
    assert parse_set("strings.hand_left.k_d=2").key == "strings.hand_left.tie_damping"  # calibrate's names
    assert parse_set("strings.k_s=400").key == "strings.stiffness"
    assert parse_set("string_defaults.k=300").key == "string_defaults.tie_stiffness"


def test_the_grid_is_the_cartesian_product_first_key_slowest_and_each_scene_carries_its_values():
    variants = sweep_variants("hanging", [parse_set("strings.k=200,400"), parse_set("strings.hand_left.k_d=2,4.5"),
                                          parse_set("rates.puppet_hz=30,60")])
    assert [v.index for v in variants] == list(range(1, 9))
    assert [tuple(v.settings.values()) for v in variants[:3]] == [("200", "2", "30"), ("200", "2", "60"),
                                                                  ("200", "4.5", "30")]
    for v in variants:
        k, k_d, hz = (float(x) for x in v.settings.values())
        assert all(s.tie_stiffness == k for s in v.scene.strings)
        assert {s.name: s.tie_damping for s in v.scene.strings} == {
            "head": 3.0, "back": 3.0, "knee_left": 3.0, "knee_right": 3.0, "hand_left": k_d, "hand_right": 3.0}
        assert v.scene.puppet_hz == hz and v.scene.string_hz == 1000.0
        assert v.scene.source == HANGING and v.scene.bars and v.scene.puppet is not None
    # a key missing from the file ([contact] is not in hanging.toml) creates its table
    (v,) = sweep_variants("hanging", [parse_set("contact.friction=0.3")])
    assert v.scene.contact["friction"] == 0.3


def test_a_string_constant_for_all_strings_overrides_what_a_string_sets_itself(tmp_path):
    text = open(HANGING).read().replace('name = "head"\nbody_point = "head"',
                                        'name = "head"\nbody_point = "head"\ntie_stiffness = 900.0')
    (tmp_path / "scene.toml").write_text(text)  # its puppet include is found among the built-in files
    (one,) = sweep_variants(tmp_path / "scene.toml", [parse_set("string_defaults.k=250")])
    assert {s.name: s.tie_stiffness for s in one.scene.strings}["head"] == 900.0  # the default only
    (every,) = sweep_variants(tmp_path / "scene.toml", [parse_set("strings.k=250")])
    assert all(s.tie_stiffness == 250.0 for s in every.scene.strings)


# (--set flags, fragments the one-line error must hold)
BAD = [
    (["strings.kk=1"], ["hanging.toml: [[strings]] #1", "--set strings.kk=1", "key 'kk'", "got 1",
                        "expected one of the known keys", "'tie_stiffness'"]),
    (["strings.k=200,-1"], ["[[strings]] 'head'", "variant 2 of 2: --set strings.tie_stiffness=-1",
                            "key 'tie_stiffness'", "got -1.0", "expected a number >= 0.0"]),
    (["strings.k=abc"], ["key 'tie_stiffness'", "got 'abc'", "expected a number"]),
    (["strings.particle_count=8.5"], ["key 'particle_count'", "got 8.5", "expected an integer"]),
    (["strings.particle_count=1"], ["key 'particle_count'", "got 1", "expected an integer >= 2"]),
    (["strings.nose.k=1"], ["--set strings.nose.k=1", "key 'nose'", "NAME one of ['back', 'hand_left'"]),
    (["rates.puppet_hz=30,5000"], ["[rates] (variant 2 of 2", "key 'puppet_hz'", "got 5000.0",
                                   "expected a number <= 1000.0"]),
    (["rates.puppet_hz=5"], ["key 'puppet_hz'", "got 5.0"]),  # measured to blow up (settings_check)
    (["solver.puppet_hz=30"], ["[solver]", "key 'puppet_hz'", "expected one of the known keys ['allow_untested', "
                                                             "'precision']"]),
    (["solver.precision=float16"], ["key 'precision'", "got 'float16'", "expected one of ['float64', 'float32']"]),
    (["strings.k=1e11"], ["key 'tie_stiffness'", "got 100000000000.0", "tested for"]),
    (["nonsense.x=1"], ["top level", "key 'nonsense'", "expected one of the known keys"]),
    (["rates.puppet_hz.x=2"], ["--set rates.puppet_hz.x=2", "key 'rates.puppet_hz'", "got 30.0",
                               "expected a table to set 'x' in"]),
    (["strings.k=1,,2"], ["--set strings.k=1,,2", "expected values separated by commas, none empty (value 2"]),
    (["strings.k=200,200"], ["--set strings.k=200,200", "expected each value once"]),
    (["strings.k"], ["--set strings.k", "expected KEY=V1,V2,..."]),
    (["strings..k=1"], ["--set strings..k=1", "expected a dotted scene key"]),
    (["strings.k=200", "strings.tie_stiffness=300"], ["--set strings.tie_stiffness=300",
                                                      "expected each key in one --set only (--set strings.k=200"]),
    (["strings.k=" + ",".join(str(200 + i) for i in range(101)), "strings.k_d=" + ",".join(
        str(1 + i) for i in range(100))], ["(grid)", "got '10100 variants'", "expected at most 10000 variants"]),
]


@pytest.mark.parametrize("sets, fragments", BAD, ids=lambda v: " ".join(v)[:40] if isinstance(v, list) else None)
def test_bad_keys_and_values_are_refused_with_the_scenes_named_error_before_any_work(sets, fragments, tmp_path,
                                                                                    monkeypatch, capsys):
    def no_work(*args, **kwargs):
        raise AssertionError("the sweep started working before its variants were validated")

    monkeypatch.setattr(dmarionette.first_run, "build_marionette", no_work)
    argv = ["sweep", "hanging", "--out", str(tmp_path / "out"), "--ray", "off", "--quiet"]
    for flag in sets:
        argv += ["--set", flag]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    for fragment in fragments:
        assert fragment in err[0], (fragment, err[0])
    assert not (tmp_path / "out").exists()  # nothing written, not even the folder


def test_a_scene_without_a_puppet_is_refused_by_name(capsys, tmp_path):
    assert main(["sweep", "strings", "--set", "strings.k_s=400", "--out", str(tmp_path / "o"), "--ray", "off"]) == 2
    err = capsys.readouterr().err
    assert "strings.toml: key 'puppet'" in err and "expected a marionette scene" in err
    with pytest.raises(SceneError, match="expected a TOML file path or a built-in scene name"):
        sweep_variants("no_such_scene", [parse_set("strings.k=1")])


def test_ray_without_the_scale_extra_names_it_and_the_default_is_in_process(monkeypatch, capsys, tmp_path):
    from dmarionette.scale import default_ray_mode

    monkeypatch.setitem(sys.modules, "ray", None)
    assert default_ray_mode() == "off"
    assert main(["sweep", "hanging", "--set", "strings.k=200", "--ray", "local", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: 'dmarionette sweep --ray local' needs the ray package: pip install -e '.[scale]' (in the "
                   "source tree; or pip install 'dmarionette[scale]')"]
    assert not (tmp_path / "o").exists()


def test_resume_refuses_another_sweeps_table(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(dmarionette.first_run, "build_marionette", lambda *a, **k: None)
    (tmp_path / "sweep.csv").write_text("variant,strings.tie_damping,simulated_s\n1,2,1.5\n")
    assert main(["sweep", "hanging", "--set", "strings.k=200", "--resume", "--out", str(tmp_path), "--ray", "off",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--resume: '{tmp_path / 'sweep.csv'}' has the columns ['variant', 'strings.tie_damping'" in err
    assert "expected ['variant', 'strings.tie_stiffness', 'simulated_s', 'torso_min_m'" in err


@pytest.mark.parametrize("address, fragment", [
    ("127.0.0.1:1", "--ray: got '127.0.0.1:1'; nothing accepts a connection there (Connection refused)"),
    ("nonsense", "--ray: got 'nonsense'; expected 'local', 'off' or the address of a running Ray cluster"),
])
def test_a_ray_address_where_no_cluster_answers_is_refused_before_any_work(address, fragment, tmp_path, capsys):
    assert main(["sweep", "hanging", "--set", "strings.k=200", "--ray", address, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: " + fragment), err
    assert not (tmp_path / "o").exists()


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("the sweep started working before its outputs were checked")

    monkeypatch.setattr(dmarionette.first_run, "build_marionette", no_work)
    (tmp_path / "a_file").write_text("x")
    assert main(["sweep", "hanging", "--set", "strings.k=200", "--ray", "off", "--out", str(tmp_path / "a_file")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: --out: '{tmp_path / 'a_file'}' is a file; expected a folder (or a path to create one at)"]


@pytest.mark.parametrize("flag, value, expected", [
    ("--duration", "nan", "expected a finite number > 0 [s]"),
    ("--duration", "-1", "expected a finite number > 0 [s]"),
    ("--workers", "0", "expected an integer >= 1 and <= 100000"),
    ("--worlds-per-batch", "0", "expected an integer >= 1 and <= 100000"),
    ("--worlds-per-batch", "1.5", "expected an integer >= 1 and <= 100000"),
])
def test_a_bad_flag_is_refused_naming_the_flag_and_its_range(flag, value, expected, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(dmarionette.first_run, "build_marionette", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(SystemExit) as exit_:
        main(["sweep", "hanging", "--set", "strings.k=200", "--ray", "off", "--out", str(tmp_path / "o"),
              f"{flag}={value}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: got '{value}'; {expected}" in err, err
    assert not (tmp_path / "o").exists()
