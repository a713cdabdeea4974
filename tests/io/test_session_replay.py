"""Recording a simulated run as a session, and replaying sessions (docs/session.md).

Puppet kernels compile with ``optimization_level=0`` (fast compile; same physics).
"""

import dataclasses
import shutil

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.io.session import (
    SessionWriter,
    format_session_info,
    read_session,
    record_simulation,
    replay_session,
    session_bar_trajectories,
    session_info,
)
from dmarionette.rotations import euler_to_matrix

wp.config.log_level = wp.LOG_WARNING
DURATION = 1.6  # the main bar of "hanging" starts to rock at t = 1 s


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    scene = dm.load_scene("hanging")
    model = dm.MarionetteModel(scene, optimization_level=0)
    path = tmp_path_factory.mktemp("replay") / "hanging.mcap"
    trajectory, _ = record_simulation(model, DURATION, path)
    return model, trajectory, path


def test_a_simulated_session_holds_the_run(recorded):
    model, trajectory, path = recorded
    info = session_info(path)
    steps, frames = len(trajectory.step_time), len(trajectory.frame_time)
    assert steps == 49 * 33 and frames == 50  # 1.6 s rounded up to whole puppet steps of 33 ms
    assert info["recorder"] == "simulation" and info["device_channels"] is False
    assert any("a simulated session" in note for note in info["notes"])
    assert info["duration"] == pytest.approx(trajectory.step_time[-1])
    for bar in ("main", "hand"):
        assert info["topics"][f"/bar/{bar}/pose"]["count"] == steps + 1  # t = 0 and after each step
        assert info["topics"][f"/bar/{bar}/feedback"]["count"] == steps
        assert info["topics"][f"/bar/{bar}/pose"]["rate_hz"] == pytest.approx(1000.0)
    assert info["topics"]["/strings/taut"]["count"] == steps
    assert info["topics"]["/puppet/state"]["count"] == frames
    assert info["topics"]["/puppet/state"]["rate_hz"] == pytest.approx(1000.0 / 33)
    text = format_session_info(info)
    assert "scene 'hanging'" in text and "/puppet/state" in text and "a simulated session" in text
    session = read_session(path)
    puppet = session.channels["/puppet/state"]
    np.testing.assert_array_equal(puppet["t"], trajectory.frame_time)
    np.testing.assert_array_equal(puppet["body_pos"], trajectory.body_pos)
    np.testing.assert_array_equal(puppet["body_rot"], trajectory.body_rot)
    np.testing.assert_array_equal(puppet["joint_q"], trajectory.joint_q)
    np.testing.assert_array_equal(session.channels["/bar/main/feedback"]["eq4"], trajectory.bar_feedback[:, 0])
    np.testing.assert_array_equal(session.channels["/bar/hand/feedback"]["reaction"], trajectory.bar_reaction[:, 1])
    np.testing.assert_array_equal(session.channels["/strings/taut"]["taut"], trajectory.string_taut)
    assert session.bodies == list(trajectory.body_names)
    # Recorded poses = the bar trajectories the simulator used, at the string steps.
    pose = session.channels["/bar/main/pose"]
    position, _, rotation = model.scene.bars[0].trajectory.pose(pose["t"])
    np.testing.assert_array_equal(pose["position"], position)
    np.testing.assert_array_equal(euler_to_matrix(pose["rotation"]), rotation)


def test_recorded_bar_poses_become_the_same_bar_trajectories(recorded):
    model, trajectory, path = recorded
    bars = session_bar_trajectories(read_session(path))
    assert sorted(bars) == ["hand", "main"]
    times = trajectory.step_time
    for bar in model.scene.bars:
        original = bar.trajectory.pose(times)
        again = bars[bar.name].pose(times)
        np.testing.assert_array_equal(again[0], original[0])  # exact at the recorded times
        np.testing.assert_array_equal(again[2], original[2])
        # Velocities (eq. 4's proxy velocity only) come from central differences: O(dt^2) off,
        # except at the last pose, where a BarTrajectory comes to rest (measured 0.04 m/s there).
        assert np.abs(again[1][:-1] - original[1][:-1]).max() < 1e-4


def test_replay_reproduces_the_recorded_motion(recorded):
    """Same scene, same bar poses at every string step, same float64 kernels: the replay is
    bit for bit the recording (measured RMS gap 0.0 m), eq. 4's feedback included: the recorded
    poses are exactly the scene's bar trajectories, so the replay drives the bars with those and
    the bar velocity (eq. 4's proxy) is the simulated one. (Before, the spline through the 1 kHz
    poses gave central-difference velocities: RMS 1.4e-3 N on forces up to 47 N.)"""
    model, trajectory, path = recorded
    replayed, report = replay_session(path, optimization_level=0)
    assert report["frames_compared"] == len(trajectory.frame_time)
    # 0.0 on the CPU; the margin is for devices whose atomic sums may change order.
    assert report["rms_body_gap"] < 1e-9 and report["max_body_gap"] < 1e-9, report
    np.testing.assert_allclose(replayed.body_pos, trajectory.body_pos, rtol=0, atol=1e-9)
    assert np.ptp(trajectory.body_pos[:, 0, 0]) > 1e-3  # the puppet moved
    assert report["rms_feedback_gap"] < 1e-9, report  # 0.0 on the CPU, as the bodies
    assert not report["truncated"]


def test_a_cut_off_session_replays_up_to_the_cut(recorded, tmp_path):
    model, trajectory, path = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(0.6 * len(data))])
    session = read_session(cut)
    assert session.truncated
    replayed, report = replay_session(cut, optimization_level=0)
    assert report["truncated"] and 0 < report["frames_compared"] < len(trajectory.frame_time)
    assert report["rms_body_gap"] < 1e-9, report
    assert replayed.frame_time[-1] <= session.channels["/bar/main/pose"]["t"][-1] + 1e-9


def test_replay_uses_the_recorded_constants_and_first_bar_pose(recorded, tmp_path):
    """A session recorded from a scene changed in Python (stiffer ties, bars moved) replays
    with the recorded constants, not those of the TOML text."""
    model, _, path = recorded
    scene = model.scene
    stiffer = tuple(dataclasses.replace(s, tie_stiffness=450.0) for s in scene.strings)
    changed = dataclasses.replace(scene, strings=stiffer, feedback_stiffness=7.0)
    session_path = tmp_path / "changed.mcap"
    with SessionWriter(session_path, changed, (scene.source and open(scene.source).read())) as writer:
        for k in range(3):
            writer.write_bar_pose("main", k * 1e-3, [0.01, 1.31, 0.0], [0.0, 0.0, 2.0])
            writer.write_bar_pose("hand", k * 1e-3, [0.0, 1.2, 0.12], [0.0, 0.0, 0.0])
    from dmarionette.io.session import scene_for_replay

    rebuilt = scene_for_replay(read_session(session_path))
    assert all(s.tie_stiffness == 450.0 for s in rebuilt.strings) and rebuilt.feedback_stiffness == 7.0
    head = next(s for s in rebuilt.strings if s.name == "head")  # attach (0, 0, 0) on the main bar
    np.testing.assert_allclose(head.top, [0.01, 1.31, 0.0])


def test_replay_refuses_a_session_without_bar_poses(tmp_path, recorded):
    model, _, path = recorded
    no_poses = tmp_path / "no_poses.mcap"
    with SessionWriter(no_poses, model.scene, open(model.scene.source).read()) as writer:
        writer.write_bar_pose("hand", 0.0, [0.0, 1.2, 0.12], [0.0, 0.0, 0.0])
        writer.write_taut(0.001, [1] * 6)
    with pytest.raises(ValueError, match=r"no_poses\.mcap: replay needs the channels \['/bar/main/pose'\]"):
        replay_session(no_poses, optimization_level=0)
    assert any("replay is not possible" in note for note in session_info(no_poses)["notes"])
    moved = tmp_path / "moved.mcap"
    shutil.copyfile(path, moved)
    assert read_session(moved).scene.source == f"{moved}#scene"
