"""Ray in ``calibrate`` and ``author`` (the ``scale`` extra): an embedded local cluster of 2 workers, started
once for this module, on loopback. A two-session calibration whose sessions' rollouts run on the workers
gives the in-process numbers, bit for bit, also when a worker is SIGKILLed in the middle of it, and exit
code 6 when every worker that starts a rollout is killed (past the retries); a two-file
batch ``author`` on the workers writes what two single-file runs write; bad ``--ray`` values are refused
before any work, and one session or one file never starts Ray."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("optimistix")
tomli_w = pytest.importorskip("tomli_w")

import dmarionette.scale.ray_map  # noqa: E402
from dmarionette.cli import main  # noqa: E402
from fitting.author_batch import worst_exit_code  # noqa: E402

from tests.support.calibration_problem import NOISE_POSITION, record_motion  # noqa: E402
from tests.support.scale import KillWorkerMidTask, without  # noqa: E402

TIMINGS = {"seconds", "total_seconds", "elapsed", "forward_s", "backward_s", "files"}


pytestmark = pytest.mark.usefixtures("ray")  # the cluster (tests/conftest.py), started once for the module


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sessions")
    return [record_motion(folder, "sway", 0.4, 31), record_motion(folder, "roll_yaw", 0.4, 32)]


def calibrate(sessions, out, *extra) -> dict:
    """``calibrate`` of 12 per-string constants on windows of 0.2 s, 3 solver steps; its calibration.json."""
    argv = ["calibrate", *map(str, sessions), "--params", "k,k_d", "--start", "k=300,k_d=3", "--window", "0.2",
            "--noise-position", str(NOISE_POSITION), "--known-noise", "--max-steps", "3", "--fast-compile",
            "--quiet", "--no-picture", "--out", str(out), *extra]
    assert main(argv) in (0, 3)  # 3: not converged in 3 steps (the numbers are what is compared)
    return json.loads((out / "calibration.json").read_text())


@pytest.fixture(scope="module")
def in_process(sessions, tmp_path_factory):
    out = tmp_path_factory.mktemp("off")
    return calibrate(sessions, out, "--ray", "off"), (out / "calibrated.toml").read_text()


def test_a_two_session_calibration_on_two_ray_workers_gives_the_in_process_numbers(sessions, in_process, tmp_path):
    summary, scene = in_process
    on_ray = calibrate(sessions, tmp_path, "--ray", "local")
    assert summary["solver"]["ray_workers"] == 0 and on_ray["solver"]["ray_workers"] == 2
    assert on_ray["solver"]["forward_passes"] == summary["solver"]["forward_passes"] > 2 * 13  # LM steps ran
    assert without(on_ray, TIMINGS | {"ray_workers"}) == without(summary, TIMINGS | {"ray_workers"})
    assert (tmp_path / "calibrated.toml").read_text() == scene


def test_a_worker_killed_mid_calibration_is_replaced_and_the_numbers_stay(sessions, in_process, tmp_path):
    # past the first tasks (each worker's: building its problem, choosing the windows): the restarted worker
    # rebuilds its session's problem and is put back in the windows by the retried rollout request
    with KillWorkerMidTask(b"ray::StateWorker.run", skip=4) as killer:
        on_ray = calibrate(sessions, tmp_path, "--ray", "local")
    assert killer.killed is not None
    assert without(on_ray, TIMINGS | {"ray_workers"}) == without(in_process[0], TIMINGS | {"ray_workers"})


def test_a_worker_that_keeps_dying_stops_calibrate_with_exit_code_6(sessions, tmp_path, capsys):
    """Past its retries (3 restarts) a lost worker is not the user's input (exit code 2) nor a fit that
    missed (3): exit code 6, one clear line, no calibration written."""
    out = tmp_path / "o"
    argv = ["calibrate", *map(str, sessions), "--params", "k,k_d", "--start", "k=300,k_d=3", "--window", "0.2",
            "--noise-position", str(NOISE_POSITION), "--known-noise", "--max-steps", "3", "--fast-compile",
            "--quiet", "--no-picture", "--ray", "local", "--out", str(out)]
    with KillWorkerMidTask(b"ray::StateWorker.run", skip=4, times=20) as killer:
        code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 6, err
    assert len(killer.kills) >= 4  # the first death and its 3 retries
    assert len(err) == 1 and "a Ray worker died more than 3 times" in err[0] and "nothing was written" in err[0], err
    assert not (out / "calibration.json").exists()


def test_one_session_never_starts_ray(sessions, tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("Ray was asked for")

    monkeypatch.setattr(dmarionette.scale.ray_map, "connect_ray", refuse)
    one = calibrate(sessions[:1], tmp_path, "--ray", "local", "--max-steps", "1")
    assert one["solver"]["ray_workers"] == 0 and one["sessions"] is None


@pytest.mark.parametrize("command", ["calibrate", "author"])
@pytest.mark.parametrize("address, fragment", [
    ("127.0.0.1:1", "--ray: got '127.0.0.1:1'; nothing accepts a connection there (Connection refused)"),
    ("nonsense", "--ray: got 'nonsense'; expected 'local', 'off' or the address of a running Ray cluster"),
])
def test_bad_ray_values_are_refused_before_any_work(command, address, fragment, sessions, tmp_path, capsys):
    inputs = [str(p) for p in sessions] if command == "calibrate" else ["a.toml", "b.toml"]
    assert main([command, *inputs, "--ray", address, "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0], err
    assert not (tmp_path / "o").exists()


def keyframes(folder, name: str, target: list[float], steps: int):
    """A small keyframes file: the left hand at ``target`` [m] at 0.35 s of 0.4 s, the hand bar's x, z free."""
    path = folder / f"{name}.toml"
    path.write_text(tomli_w.dumps({
        "author": {"scene": "hanging", "duration": 0.4, "particle_count": 6},
        "bars": {"hand": {"knots": [0.0, 0.4], "free": ["x", "z"]}},
        "keyframes": [{"t": 0.35, "points": {"hand_left": target}}],
        "weights": {"smoothness": 0.001},
        "solver": {"max_steps": steps, "position_tolerance": 0.005}}))
    return path


AUTHOR = ["--no-animation", "--no-export", "--fast-compile", "--quiet"]


def test_a_batch_author_on_two_ray_workers_writes_what_single_runs_write(tmp_path, capsys):
    near = keyframes(tmp_path, "near", [0.11, 0.3437, 0.05], 20)  # ~1.3 cm from where the hand is: reached
    far = keyframes(tmp_path, "far", [0.1, 0.45, 0.1], 3)  # 12 cm: not in 3 steps
    single = {p.stem: main(["author", str(p), "--out", str(tmp_path / "single" / p.stem), *AUTHOR])
              for p in (near, far)}
    assert single == {"near": 0, "far": 3}
    capsys.readouterr()
    code = main(["author", str(near), str(far), "--ray", "local", "--out", str(tmp_path / "batch"), *AUTHOR])
    assert code == 3  # the worst job's
    out = capsys.readouterr().out
    jobs = json.loads(out[out.index("{"):])
    assert [(j["file"], j["status"], j["exit_code"]) for j in jobs["jobs"]] == [
        (str(near), "reached", 0), (str(far), "not_converged", 3)] and jobs["exit_code"] == 3
    assert f"| {near} | reached |" in out and f"| {far} | not_converged |" in out
    for name in ("near", "far"):
        a, b = tmp_path / "single" / name, tmp_path / "batch" / name
        summaries = [without(json.loads((f / "summary.json").read_text()), TIMINGS) for f in (a, b)]
        assert summaries[0] == summaries[1]
        assert (a / "authored_scene.toml").read_text() == (b / "authored_scene.toml").read_text()
        with np.load(a / "trajectory.npz") as x, np.load(b / "trajectory.npz") as y:
            assert sorted(x.files) == sorted(y.files)
            assert all(np.array_equal(x[k], y[k]) for k in x.files if k != "metadata")  # it names the folder
    assert json.loads((tmp_path / "batch" / "far" / "summary.json").read_text())["files"]["trajectory"] == str(
        tmp_path / "batch" / "far" / "trajectory.npz")


def test_batch_author_refuses_two_files_of_one_name_before_any_work(tmp_path, capsys):
    (tmp_path / "a").mkdir()
    first = keyframes(tmp_path, "same", [0.1, 0.34, 0.05], 1)
    second = keyframes(tmp_path / "a", "same", [0.1, 0.34, 0.05], 1)
    assert main(["author", str(first), str(second), "--ray", "off", "--out", str(tmp_path / "o"), *AUTHOR]) == 2
    err = capsys.readouterr().err
    assert f"keyframes: '{first}' and '{second}' would both write '{tmp_path / 'o' / 'same'}'" in err
    assert not (tmp_path / "o").exists()


def test_the_worst_exit_code_of_a_batch():
    assert worst_exit_code([0, 4, 0]) == 4
    assert worst_exit_code([4, 3]) == 3 and worst_exit_code([3, 5]) == 5 and worst_exit_code([5, 2, 0]) == 2
    assert worst_exit_code([]) == 0
