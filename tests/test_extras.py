"""Every command checks its extras before any work: one line naming the extra, exit 2 (issue 17)."""

from __future__ import annotations

import sys

import pytest

import dmarionette
from dmarionette import extras
from dmarionette.cli import main

# (command line, the module made unimportable, the extra the hint names); {tmp} is the test's folder
CASES = [
    (["info", "{tmp}/take.mcap"], "mcap", "io"),
    (["replay", "{tmp}/take.mcap", "--out", "{tmp}/replay"], "mcap", "io"),
    (["live", "--record", "{tmp}/take.mcap", "--duration", "0.1"], "mcap", "io"),
    (["live", "--device", "replay", "--session", "{tmp}/take.mcap"], "mcap", "io"),
    (["live", "--view", "browser", "--duration", "0.1"], "viser", "view"),
    (["live", "--snapshot", "{tmp}/last.png", "--duration", "0.1"], "matplotlib", "viz"),
    (["live", "--device", "falcon"], "usb", "hw"),
    (["live", "--device", "spacemouse"], "hid", "hw"),
    (["demo", "--out", "{tmp}/demo"], "matplotlib", "viz"),
    (["demo", "--out", "{tmp}/demo"], "imageio", "viz"),
    (["simulate", "strings", "--out", "{tmp}/strings"], "matplotlib", "viz"),
    (["simulate", "hanging", "--animation", "mp4", "--out", "{tmp}/mp4"], "imageio_ffmpeg", "mp4"),
    (["bench", "accuracy", "--grid", "reduced", "--out", "{tmp}/bench"], "matplotlib", "viz"),
    (["author", "{tmp}/keyframes.toml", "--out", "{tmp}/author"], "jax", "fitting"),
    (["calibrate", "{tmp}/take.mcap", "--out", "{tmp}/calibrate"], "optimistix", "fitting"),
]


@pytest.fixture(scope="module", autouse=True)
def _every_module_imported_before_any_patch():
    """Import every module of the package before a test patches ``load_scene`` or hides an extra:
    a module first imported under the patch (``from ... import load_scene``) would keep the patched
    function, or its fallback for a missing extra, for the rest of the test session."""
    import importlib
    import pkgutil

    import fitting

    for package in (dmarionette, fitting):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            try:
                importlib.import_module(info.name)
            except ImportError:  # an optional extra not installed here: nothing of it to keep
                pass


@pytest.mark.parametrize("argv, module, extra", CASES, ids=lambda v: v if isinstance(v, str) else " ".join(v)[:40])
def test_a_command_without_its_extra_says_which_to_install_before_any_work(argv, module, extra, tmp_path,
                                                                          monkeypatch, capsys):
    import dmarionette.cli
    import dmarionette.scene.scene

    def no_work(*args, **kwargs):
        raise AssertionError("the command started working before checking its extras")

    monkeypatch.setitem(sys.modules, module, None)  # import raises ImportError, find_spec finds nothing
    for name in [m for m in sys.modules if m.startswith(module + ".")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setattr(dmarionette.scene.scene, "load_scene", no_work)
    monkeypatch.setattr(dmarionette.cli, "build_marionette", no_work)
    monkeypatch.setattr(dmarionette.cli, "init_warp", no_work)  # Warp is not even started
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"error: 'dmarionette {argv[0]}") and f"pip install -e '.[{extra}]'" in err[0], err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_commands_name_only_the_extras_they_use():
    import argparse

    need = lambda **kw: [e for _, e in extras.command_extras(argparse.Namespace(**kw))]  # noqa: E731
    assert need(command="demo", no_picture=True, animation="gif") == []
    assert need(command="demo", no_picture=False, animation="gif") == ["viz"]
    assert need(command="simulate", no_picture=False, animation="mp4") == ["viz", "mp4"]
    assert need(command="live", device=None, record=None, session=None, view="none", snapshot=None) == []
    assert need(command="scenes") == []
    assert need(command="export", format="all") == []
    for command in ("info", "replay"):
        assert need(command=command) == ["io"]


def test_installed_extras_pass_and_a_missing_one_is_found(monkeypatch):
    assert not extras.missing_module("numpy")
    assert extras.missing_module("dmarionette_no_such_module")
    monkeypatch.setitem(sys.modules, "mcap", None)
    assert extras.missing_module("mcap")
    with pytest.raises(extras.MissingExtraError, match=r"'dmarionette info' needs the mcap package: "
                                                       r"pip install -e '\.\[io\]'"):
        extras.check_extras("info", ["io"])


def test_every_extra_named_is_declared_in_pyproject():
    import tomllib
    from pathlib import Path

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    declared = pyproject["project"]["optional-dependencies"]
    for extra in extras.EXTRAS:
        if extra == "usd":  # added with the USD export (issue 17, item 3)
            continue
        assert extra.split("-")[0] in declared, extra
    assert not any("imageio-ffmpeg" in p for p in declared["viz"])  # MP4's ffmpeg binary has its own extra
    assert any("imageio-ffmpeg" in p for p in declared["mp4"]) and any("imageio-ffmpeg" in p for p in declared["dev"])
