"""The command line: help on every command, a short simulation's files, clean errors, plug-in
commands found through entry points."""

import json
import os
import subprocess
import sys
from importlib import metadata

import numpy as np
import pytest

from dmarionette.cli import COMMAND_GROUP, find_commands, main
from dmarionette.io.trajectory import read_trajectory


@pytest.mark.parametrize("command", [[], ["simulate"], ["demo"], ["scenes"]])
def test_help_on_every_command(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    assert "usage: dmarionette" in capsys.readouterr().out


def test_simulate_writes_trajectory_summary_and_picture(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "strings", "--duration", "0.3", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["all_finite"] and summary["string_steps"] == 330  # 10 frames of 33 steps
    data = read_trajectory(out / "trajectory.npz")
    frames = data["particle_q"]
    assert frames.shape == (11, 300, 3) and np.all(np.isfinite(frames))
    assert data["tie_force"].shape == (330, 6, 3) and data["string_taut"].shape == (330, 6)
    assert list(data["string_names"]) == ["head", "back", "knee_left", "knee_right", "hand_left", "hand_right"]
    assert data["metadata"]["frame_steps"] == 33
    png = (out / "strings.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 20_000
    assert json.loads(capsys.readouterr().out)["scene"] == "strings"


def test_bad_scene_gives_a_clear_error_and_no_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "x"\n[[strings]]\nname = "a"\ntop = [0, 1, 0]\nbottom = [0, 0.5, 0]\nmass = -1\n')
    run = subprocess.run([sys.executable, "-m", "dmarionette.cli", "simulate", str(bad), "--quiet"],
                         capture_output=True, text=True)
    assert run.returncode == 2
    assert "Traceback" not in run.stderr
    assert str(bad) in run.stderr and "'mass'" in run.stderr and "> 0" in run.stderr


def test_output_into_a_closed_pipe_ends_quietly():
    """`dmarionette scenes | head -3` where head has gone: the status of a command ended by SIGPIPE
    (141), no traceback. The pipe's reading end is closed before the command starts."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        run = subprocess.run([sys.executable, "-m", "dmarionette.cli", "scenes"], stdout=write_end,
                             stderr=subprocess.PIPE, text=True)
    finally:
        os.close(write_end)
    assert run.returncode == 141, run.stderr
    assert run.stderr == ""


# ------------------------------------------------------------------ plug-in commands (entry points)

FITTING_COMMANDS = {"author": "fitting.cli:add_author_command", "calibrate": "fitting.cli:add_calibrate_command"}


def add_hello_command(commands):
    """A plug-in command for the tests below: 'hello NAME' prints a greeting; exit code 7."""
    hello = commands.add_parser("hello", help="greet NAME", description="Prints a greeting.")
    hello.add_argument("name")
    hello.add_argument("--refuse", action="store_true", help="raise a ValueError instead")

    def run(args):
        if args.refuse:
            raise ValueError(f"--refuse: {args.name} is not greeted")
        print(f"hello {args.name}")
        return 7

    hello.set_defaults(handler=run)


def _plugins(**entries):
    return {name: metadata.EntryPoint(name, value, COMMAND_GROUP) for name, value in entries.items()}


def test_fitting_declares_its_commands_in_the_source_tree():
    """pyproject.toml's entry points, which find_commands reads for a tree run without installing."""
    found = find_commands(installed=False)
    assert {name: entry.value for name, entry in found.items()} == FITTING_COMMANDS


def test_the_installed_metadata_declares_the_same_commands():
    installed = {entry.name: entry.value for entry in metadata.entry_points(group=COMMAND_GROUP)}
    if not installed:
        pytest.skip("dmarionette's metadata (with its entry points) is not installed: pip install -e '.[dev]'")
    assert installed == FITTING_COMMANDS
    assert find_commands() == find_commands(source_tree=None)


def test_a_plugin_command_runs_through_its_entry_point(capsys):
    plugins = _plugins(hello=f"{__name__}:add_hello_command")
    assert main(["hello", "puppet"], commands=plugins) == 7
    assert capsys.readouterr().out == "hello puppet\n"
    assert main(["hello", "puppet", "--refuse"], commands=plugins) == 2
    assert "error: --refuse: puppet is not greeted" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["--help"], commands=plugins)
    assert exit_.value.code == 0
    assert "greet NAME" in capsys.readouterr().out


def test_a_plugin_that_cannot_be_loaded_says_why(capsys):
    plugins = _plugins(broken="no_such_plugin_module:add")
    assert main(["broken", "anything", "--at-all"], commands=plugins) == 2
    err = capsys.readouterr().err
    assert "error: 'dmarionette broken' is a plug-in command (no_such_plugin_module:add" in err
    assert "could not be loaded" in err and "no_such_plugin_module" in err and "pip install" in err
    with pytest.raises(SystemExit):
        main(["--help"], commands=plugins)
    assert "(not available:" in capsys.readouterr().out


def test_without_plugins_the_help_and_an_unknown_command_say_how_to_install_them(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"], commands={})
    assert exit_.value.code == 0
    assert "no plug-in commands were found" in capsys.readouterr().out.replace("\n", " ").replace("  ", " ")
    with pytest.raises(SystemExit) as exit_:
        main(["author", "keyframes.toml"], commands={})
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "unknown command 'author'" in err and "pip install -e '.[fitting]'" in err


def test_only_the_command_named_is_loaded():
    """A built-in command loads no plug-in (so no JAX); a plug-in command loads its own."""
    code = ("import sys\nfrom dmarionette.cli import main\n"
            "try:\n    main([sys.argv[1], '--help'])\nexcept SystemExit:\n    pass\n"
            "print('fitting' in sys.modules, 'jax' in sys.modules, file=sys.stderr)")
    for command, loaded in (("simulate", ["False", "False"]), ("author", ["True", "True"])):
        run = subprocess.run([sys.executable, "-c", code, command], capture_output=True, text=True, check=True)
        assert run.stderr.split()[-2:] == loaded, (command, run.stderr)
