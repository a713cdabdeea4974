"""The command line: help on every command, a short simulation's files, clean errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from dmarionette.cli import main
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
