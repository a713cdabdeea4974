"""Bad command-line flags and outputs: refused before any work, with the flag named, exit 2.

One test per class of bad input (issue 18): flag values (non-numbers, NaN, infinities,
negatives, zero, out of range, non-integers), durations too long for memory, output paths
that cannot be written (under a file, a file where a folder is expected, a folder where a
file is expected, a place that cannot be written), a non-finite result, and Ctrl-C (in
process, and SIGINT to a running ``dmarionette simulate``).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest

from dmarionette.cli import find_commands, main
from dmarionette.cli_checks import Outputs, check_trajectory_fits
from dmarionette.io.trajectory import first_non_finite
from dmarionette.scene.limits import trajectory_bytes

ROOT = Path(__file__).resolve().parents[1]
KEYFRAMES = ROOT / "examples" / "keyframes_three_poses.toml"
COMMANDS = find_commands()
SLACK = 3.0  # the process exit after the line, on a loaded CI machine (interpreter teardown)


def _run(argv, capsys) -> tuple[int, str]:
    """main(argv) -> (exit code, stderr); an argparse refusal (SystemExit) counts as its code."""
    try:
        code = main([str(a) for a in argv], commands=COMMANDS)
    except SystemExit as exit_:
        code = exit_.code
    return code, capsys.readouterr().err


# Each row: a command line with one bad flag value, the flag, and a word the message must hold.
BAD_VALUES = [
    (["simulate", "strings", "--duration=inf"], "--duration", "finite"),
    (["simulate", "strings", "--duration=-inf"], "--duration", "finite"),
    (["simulate", "strings", "--duration=nan"], "--duration", "finite"),
    (["simulate", "strings", "--duration=0"], "--duration", "> 0"),
    (["simulate", "strings", "--duration=-1"], "--duration", "> 0"),
    (["simulate", "strings", "--duration=fast"], "--duration", "'fast'"),
    (["demo", "--fps=0"], "--fps", ">= 0.1"),
    (["simulate", "strings", "--fps=-5"], "--fps", ">= 0.1"),
    (["simulate", "strings", "--fps=1e300"], "--fps", "<= 1000"),
    (["live", "--duration=0"], "--duration", "> 0"),
    (["live", "--duration=-1"], "--duration", "> 0"),
    (["live", "--duration=nan"], "--duration", "finite"),
    (["live", "--force-scale=inf"], "--force-scale", "finite"),
    (["live", "--force-scale=-0.1"], "--force-scale", ">= 0"),
    (["live", "--workspace-scale=0"], "--workspace-scale", "> 0"),
    (["live", "--view-hz=nan"], "--view-hz", "finite"),
    (["live", "--view-port=70000"], "--view-port", "<= 65535"),
    (["live", "--view-port=-1"], "--view-port", ">= 0"),
    (["live", "--view-port=80.5"], "--view-port", "integer"),
    (["bench", "accuracy", "--repeats=0"], "--repeats", ">= 1"),
    (["bench", "accuracy", "--repeats=2.5"], "--repeats", "integer"),
    (["bench", "accuracy", "--seconds=-1"], "--seconds", ">= 0.1"),
    (["bench", "accuracy", "--seconds=1e9"], "--seconds", "<= 60"),
    (["export", "t.npz", "--fps=0"], "--fps", "> 0"),
    (["export", "t.npz", "--fps=-1"], "--fps", "> 0"),
    (["calibrate", "s.mcap", "--rows=0"], "--rows", ">= 1"),
    (["calibrate", "s.mcap", "--max-steps=0"], "--max-steps", ">= 1"),
    (["calibrate", "s.mcap", "--duration=-1"], "--duration", "> 0"),
    (["calibrate", "s.mcap", "--noise-position=0"], "--noise-position", "> 0"),
    (["calibrate", "s.mcap", "--noise-force=inf"], "--noise-force", "finite"),
    (["calibrate", "s.mcap", "--start=k=nan"], "--start", "finite"),
    (["calibrate", "s.mcap", "--start=k"], "--start", "NAME=VALUE"),
    (["author", "k.toml", "--max-steps=1e3"], "--max-steps", "integer"),
    (["author", "k.toml", "--checkpoint-steps=0"], "--checkpoint-steps", ">= 1"),
    (["author", "k.toml", "--fps=nan"], "--fps", "finite"),
]


@pytest.mark.parametrize("argv, flag, word", BAD_VALUES, ids=[" ".join(row[0]) for row in BAD_VALUES])
def test_a_bad_flag_value_is_refused_naming_the_flag_and_the_range(argv, flag, word, capsys, tmp_path):
    out = tmp_path / "out"
    code, err = _run([*argv, "--out" if argv[0] != "live" else "--record",
                      out if argv[0] != "live" else out / "s.mcap"], capsys)
    assert code == 2, err
    assert f"argument {flag}: got" in err or f"argument {flag}: '" in err, err
    assert word in err and "expected" in err, err
    assert "Traceback" not in err
    assert not out.exists()


@pytest.fixture
def no_work(monkeypatch):
    """Every command's work (simulation, fit, sweep, export) fails the test if it starts."""
    def tripwire(*args, **kwargs):
        raise AssertionError("the work started before the outputs were checked")

    import dmarionette.io.export.bvh
    import dmarionette.io.export.common
    import dmarionette.io.export.gltf
    import dmarionette.io.session
    import dmarionette.marionette.accuracy
    import dmarionette.marionette.solver
    import dmarionette.strings.simulate
    import fitting.calibration_fit

    author_module = importlib.import_module("fitting.author")  # fitting.author is also the function
    for module, name in [(dmarionette.strings.simulate, "simulate_strings"),
                         (dmarionette.marionette.solver, "MarionetteModel"),
                         (dmarionette.io.session, "replay_session"),
                         (dmarionette.marionette.accuracy, "run_sweep"),
                         (dmarionette.io.export.bvh, "export_bvh"), (dmarionette.io.export.gltf, "export_gltf"),
                         (fitting.calibration_fit, "calibrate_session"), (author_module, "author")]:
        monkeypatch.setattr(module, name, tripwire)
    fake = types.SimpleNamespace(puppet=None, source=None)
    monkeypatch.setattr(dmarionette.io.export.common, "read_marionette_trajectory", lambda path: fake)


def _output_argv(command: str, out: Path, a_file: Path) -> list:
    """The command line of ``command`` with ``out`` as its output: a folder, or for live a file in it."""
    if command.startswith("live"):
        flag, name = ("--record", "s.mcap") if command.endswith("record") else ("--snapshot", "s.png")
        return ["live", flag, out if out.suffix else out / name]
    return {
        "simulate": ["simulate", "strings", "--out", out],
        "demo": ["demo", "--out", out],
        "export": ["export", "t.npz", "--out", out],
        "replay": ["replay", "s.mcap", "--out", out],
        "calibrate": ["calibrate", "s.mcap", "--out", out, "--quiet"],
        "author": ["author", KEYFRAMES, "--out", out, "--quiet"],
        "bench": ["bench", "accuracy", "--out", out],
    }[command]


FOLDER_COMMANDS = ["simulate", "demo", "export", "replay", "calibrate", "author", "bench"]
FILE_COMMANDS = ["live --record", "live --snapshot"]
OUTPUT_CASES = ([(c, case) for c in FOLDER_COMMANDS + FILE_COMMANDS
                 for case in ("under a file", "an existing file", "cannot be created")]
                + [(c, "a folder for a file") for c in FILE_COMMANDS])


@pytest.mark.parametrize("command, case", OUTPUT_CASES, ids=[f"{c}: {case}" for c, case in OUTPUT_CASES])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(command, case, tmp_path, capsys, no_work):
    a_file = tmp_path / "file.txt"
    a_file.write_text("not a folder\n")
    suffix = ".png" if command.endswith("snapshot") else ".mcap"
    out = {"under a file": a_file / "sub",
           "an existing file": a_file if command in FOLDER_COMMANDS else a_file / f"s{suffix}",
           "cannot be created": Path("/proc/dmarionette-no-such/sub"),
           "a folder for a file": tmp_path / f"folder{suffix}"}[case]
    if case == "a folder for a file":
        out.mkdir()
    argv = _output_argv(command, out, a_file)
    code, err = _run(argv, capsys)
    flag = next(a for a in argv if str(a).startswith("--") and a != "--quiet")
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {flag}: "), err
    assert re.search(r"is a file|is a folder|cannot (create|write)", err), err
    assert "Traceback" not in err
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(["file.txt"] + ([out.name] if case == "a folder for a file" else [])), "something written"
    assert a_file.read_text() == "not a folder\n"
    if case == "a folder for a file":
        assert list(out.iterdir()) == []


def test_an_existing_output_file_is_overwritten(tmp_path, capsys):
    """Files the command owns are replaced (a re-run into the same folder); the folder stays."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.npz").write_text("an old run\n")
    (out / "notes.txt").write_text("mine\n")
    assert main(["simulate", "strings", "--duration", "0.1", "--out", str(out), "--quiet", "--no-picture"]) == 0
    capsys.readouterr()
    with np.load(out / "trajectory.npz") as data:
        assert "particle_q" in data.files
    assert (out / "notes.txt").read_text() == "mine\n"
    assert not [p for p in out.iterdir() if p.name.startswith(".dmarionette-probe")]


def test_a_duration_too_long_for_memory_is_refused_with_the_estimate(tmp_path, capsys, no_work):
    code, err = _run(["simulate", "strings", "--duration", "1e9", "--out", tmp_path / "out"], capsys)
    assert code == 2 and err.startswith("error: --duration: got 1e+09 s"), err
    assert re.search(r"about [\d.]+ (TiB|PiB|EiB)", err) and "at most about" in err, err
    code, err = _run(["live", "--duration", "1e9"], capsys)
    assert code == 2 and err.startswith("error: --duration: got 1e+09 s") and "iB in memory" in err, err
    # The scene's own duration: the file and its key named.
    text = (ROOT / "dmarionette" / "scene" / "builtin" / "strings.toml").read_text()
    scene = tmp_path / "long.toml"
    scene.write_text(re.sub(r"(?m)^duration = .*$", "duration = 1e9", text, count=1))
    code, err = _run(["simulate", scene, "--out", tmp_path / "out"], capsys)
    assert code == 2 and str(scene) in err and "duration" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_the_size_estimate_bounds_what_a_run_keeps(tmp_path, capsys):
    """The estimate is at least the arrays a real run returns, and not far above them."""
    from dmarionette.scene.scene import load_scene
    from dmarionette.strings.simulate import simulate_strings

    scene = load_scene("strings")
    trajectory = simulate_strings(scene, 0.5, progress=False)
    kept = sum(v.nbytes for v in vars(trajectory).values() if isinstance(v, np.ndarray))
    estimate = trajectory_bytes(scene, 0.5)
    assert kept <= estimate <= 4 * kept, (kept, estimate)
    with pytest.raises(ValueError, match=r"--duration: got 2 s; the trajectory would take about 1 KiB .* at most "
                                         r"about 1 s"):
        check_trajectory_fits("--duration", 2.0, 1024.0, limit=512.0)


def test_first_non_finite_names_the_earliest_quantity_and_time():
    @dataclasses.dataclass
    class T:
        frame_time: np.ndarray
        step_time: np.ndarray
        particle_q: np.ndarray
        tie_force: np.ndarray

    t = T(np.arange(5) * 0.1, np.arange(1, 41) * 0.0125, np.zeros((5, 3, 3)), np.zeros((40, 2, 3)))
    assert first_non_finite(t) is None
    t.particle_q[3, 1, 2] = np.nan
    assert first_non_finite(t) == ("particle_q", (3, 1, 2), pytest.approx(0.3))
    t.tie_force[9, 0, 0] = np.inf  # t = 0.125 s: earlier than the particles' NaN
    assert first_non_finite(t) == ("tie_force", (9, 0, 0), pytest.approx(0.125))


def test_a_non_finite_result_writes_nothing(tmp_path, capsys, monkeypatch):
    """A rollout that diverges (here: NaN injected into a real run) is refused before writing, exit 1."""
    import dmarionette.strings.simulate as strings_simulate

    real = strings_simulate.simulate_strings

    def diverging(*args, **kwargs):
        trajectory = real(*args, **kwargs)
        trajectory.particle_q[2:, 0, 1] = np.nan
        return trajectory

    monkeypatch.setattr(strings_simulate, "simulate_strings", diverging)
    out = tmp_path / "out"
    code, err = _run(["simulate", "strings", "--duration", "0.2", "--out", out, "--quiet"], capsys)
    assert code == 1, err
    assert re.search(r"error: the simulation produced a non-finite value: particle_q first at t = 0.0\d+ s", err), err
    assert "nothing written" in err and "Traceback" not in err
    assert not out.exists()
    out.mkdir()  # an existing folder stays, with nothing in it
    code, err = _run(["simulate", "strings", "--duration", "0.2", "--out", out, "--quiet"], capsys)
    assert code == 1 and list(out.iterdir()) == []


def test_ctrl_c_in_process_stops_with_one_line(tmp_path, capsys, monkeypatch):
    import dmarionette.render.strings
    import dmarionette.strings.simulate as strings_simulate

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(strings_simulate.StringRollout, "run", interrupted)
    out = tmp_path / "out"
    code, err = _run(["simulate", "strings", "--duration", "0.2", "--out", out, "--quiet"], capsys)
    assert (code, err.strip()) == (130, "interrupted; nothing written")
    assert not out.exists()
    # Interrupted after the trajectory was written (while drawing): says what was kept.
    monkeypatch.undo()
    monkeypatch.setattr(dmarionette.render.strings, "render_string_picture", interrupted)
    code, err = _run(["simulate", "strings", "--duration", "0.1", "--out", out, "--quiet"], capsys)
    assert code == 130 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("interrupted; kept") and str(out / "trajectory.npz") in err, err


def test_outputs_discard_removes_only_the_folders_it_created(tmp_path):
    (tmp_path / "a").mkdir()
    outputs = Outputs()
    outputs.folder("--out", tmp_path / "a" / "b" / "c")
    assert (tmp_path / "a" / "b" / "c").is_dir()
    outputs.discard()
    assert (tmp_path / "a").is_dir() and not (tmp_path / "a" / "b").exists()


def _interrupt(argv, tmp_path, ready: bytes, env=None, wait: float = 0.5) -> tuple[int, float, float, str]:
    """Starts ``dmarionette ARGV`` and sends SIGINT once stderr matches ``ready``.

    Returns (exit code, seconds from the signal to the "interrupted" line, to the exit, stderr).
    """
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env or {}))
    process = subprocess.Popen([sys.executable, "-m", "dmarionette.cli", *map(str, argv)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, env=env, cwd=tmp_path)
    started = threading.Event()
    err = bytearray()
    said = []

    def read() -> None:
        while chunk := process.stderr.read1(4096):
            err.extend(chunk)
            if re.search(ready, bytes(err)):
                started.set()
            if not said and b"interrupted;" in err:
                said.append(time.monotonic())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert started.wait(120), bytes(err).decode(errors="replace")
        time.sleep(wait)
        sent = time.monotonic()
        process.send_signal(signal.SIGINT)
        code = process.wait(30)
        stopped = time.monotonic() - sent
    finally:
        process.kill()
        process.wait()
    reader.join(5)
    said = (said[0] - sent) if said else math.inf
    print(f"{argv[0]}: SIGINT -> the line {said:.3f} s, the exit {stopped:.3f} s")  # pytest -s shows it
    return code, said, stopped, bytes(err).decode(errors="replace")


def test_sigint_stops_a_running_simulation_within_a_second(tmp_path):
    """SIGINT to ``dmarionette simulate`` while it steps: one line, exit 130, nothing left."""
    out = tmp_path / "out"
    code, said, stopped, err = _interrupt(["simulate", "strings", "--duration", "300", "--out", out, "--no-picture"],
                                          tmp_path, rb"\d+/\d+ \[[^\]]*\d+\.\d+step/s")  # tqdm: stepping
    assert code == 130, err
    assert said < 1.0 and stopped < SLACK * 1.0, (said, stopped)
    assert "Traceback" not in err and err.rstrip().splitlines()[-1] == "interrupted; nothing written", err
    assert not out.exists()


@pytest.mark.parametrize("command", ["demo", "live"])
def test_sigint_during_a_kernel_compile_stops_within_a_second(command, tmp_path):
    """SIGINT while Warp compiles the puppet kernels (one long call into the compiler; an empty kernel cache)."""
    out = tmp_path / "out"
    argv = ["demo", "--fast-compile", "--out", out] if command == "demo" else [
        "live", "--fast-compile", "--duration", "5", "--record", out / "s.mcap"]
    code, said, stopped, err = _interrupt(argv, tmp_path, rb"building the marionette" if command == "demo" else b"",
                                          env={"WARP_CACHE_PATH": str(tmp_path / "cache")}, wait=3.0)
    assert code == 130, err
    assert said < 1.0 and stopped < SLACK * 1.0, (said, stopped)
    assert "Traceback" not in err and err.rstrip().splitlines()[-1] == "interrupted; nothing written", err
    assert not out.exists()


def test_sigint_during_live_turns_the_motors_off_and_keeps_the_recording(tmp_path):
    """SIGINT in the servo loop: the loop stops the device (as before), then one line names the recording kept."""
    from dmarionette.io.session import read_session

    record = tmp_path / "s.mcap"
    code, said, stopped, err = _interrupt(["live", "--fast-compile", "--duration", "60", "--record", record],
                                          tmp_path, rb"servo loop starting", wait=1.0)
    assert code == 130, err
    assert said < 1.0 and stopped < SLACK * 1.0, (said, stopped)
    assert "Traceback" not in err, err
    assert err.rstrip().splitlines()[-1].startswith("interrupted; kept") and str(record) in err, err
    # The recording kept is readable (motors off on Ctrl-C: tests/hw/test_hw_servo.py, with a device that records it).
    assert len(read_session(record).channels["/device/main/force"]["t"]) > 0


def test_live_inputs_are_checked_before_the_kernels_compile(tmp_path, capsys, no_work):
    """A --session that does not exist, a --view-host that does not resolve: refused before the work."""
    code, err = _run(["live", "--device", "replay", "--session", tmp_path / "none.mcap"], capsys)
    assert code == 2 and err.startswith("error: --session: got ") and "expected an existing session file" in err, err
    code, err = _run(["live", "--view", "browser", "--view-host", "999.1.1.1"], capsys)
    assert code == 2 and err.startswith("error: --view-host: got '999.1.1.1'; expected an address"), err
    code, err = _run(["live", "--duration=--"], capsys)
    assert code == 2 and "argument --duration: got '--'; expected a value" in err, err
