"""The marionette: balance at rest, slack legs and feedback, rates, scenes, animation (paper §2-4).

Puppet kernels are compiled without optimisation here (``optimization_level=0``: ~10 s
per puppet topology instead of ~1 min); the physics is the same.
"""

import dataclasses
import json

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.scene.bars import BarTrajectory, ControlBar
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.marionette.rollout import simulate_marionette
from dmarionette.rotations import quat_to_matrix

wp.config.log_level = wp.LOG_WARNING
G = 9.81


def _model(scene, **changes):
    return MarionetteModel(dataclasses.replace(scene, **changes), optimization_level=0)


def _still_bars(scene):
    """The scene's bars held at their t = 0 pose."""
    return tuple(dataclasses.replace(bar, trajectory=BarTrajectory.still(bar.trajectory.positions[0],
                                                                         bar.trajectory.rotations[0]))
                 for bar in scene.bars)


@pytest.fixture(scope="module")
def settled(hanging):
    """The hanging marionette after 6 s with still bars."""
    model = _model(hanging, bars=_still_bars(hanging))
    return model, simulate_marionette(model, 6.0, progress=False)


def test_at_rest_the_strings_carry_the_puppet(settled):
    """The ties' vertical pull balances the puppet's weight; the bars carry puppet + strings.

    After 6 s the torso moves at 0.35 mm/s (measured); that sway, at about 4 rad/s, leaves
    inertial forces of about 1e-3 N, 1.4e-4 of the weight, so the tolerance is 0.2 %.
    Measured: ties 1.2e-5, bars 3.4e-4 (the bars also hold the strings, less their top
    particles, which the bars move kinematically).
    """
    model, trajectory = settled
    weight = model.puppet_mass * G
    lift = trajectory.tie_force[-100:, :, 1].sum(axis=1).mean()  # upward pull of the strings on the bodies
    assert abs(lift - weight) <= 2e-3 * weight, (lift, weight)
    strings_weight = sum(s.mass for s in model.strings.specs) * G
    top_particles = sum(s.mass / (s.particle_count - 1) for s in model.strings.specs) * G
    bars = -trajectory.bar_reaction[-100:, :, 1].sum(axis=1).mean()
    assert abs(bars - (weight + strings_weight - top_particles)) <= 2e-3 * weight, bars
    torso_speed = np.linalg.norm(np.diff(trajectory.body_pos[-10:, 0], axis=0), axis=1).max() / (
        trajectory.frame_time[1] - trajectory.frame_time[0])
    assert torso_speed < 1e-3, torso_speed  # hangs still


def test_eq4_feedback_matches_a_hand_computation(hanging):
    """eq. 4 summed over the taut strings of each bar, from the state the step produced."""
    model = _model(hanging)
    solver = SolverMarionette(model)
    a, b = model.state(), model.state()
    control = model.control()
    for k in range(5):
        control.set_bars(model, k * model.puppet_dt)
        solver.step(a, b, control)
        a, b = b, a
    q, qd = a.strings.particle_q.numpy(), a.strings.particle_qd.numpy()
    taut = a.string_taut.numpy()[-1]
    bar_q, bar_qd = control.bar_q.numpy()[-1], control.bar_qd.numpy()[-1]
    k, kd, m = hanging.feedback_stiffness, hanging.feedback_damping, model.puppet_mass
    expected = np.zeros((model.bar_count, 3))
    for s, bar in enumerate(model.string_bar):
        last = model.strings.string_start_np[s + 1] - 1
        if taut[s]:
            # F_i = -k (x_proxy - x_string) - m g - k_d (v_proxy - v_string), g = 9.81 up
            expected[bar] += -k * (bar_q[bar] - q[last]) - m * np.array([0.0, G, 0.0]) - kd * (bar_qd[bar] - qd[last])
    np.testing.assert_allclose(a.bar_feedback.numpy()[-1], expected, rtol=1e-12, atol=1e-12)


def test_lowering_the_main_bar_slackens_the_leg_strings_and_feedback_drops(hanging):
    """Lowered 0.3 m, the feet stand on the ground: knee strings go slack, main-bar feedback drops."""
    main, hand = hanging.bars
    p0 = np.array(main.trajectory.positions[0])
    # Two keyframes: held until 1 s, then a smooth descent with zero end tangents (no overshoot).
    lowered = BarTrajectory(np.array([1.0, 3.0]), np.array([p0, p0 - [0.0, 0.3, 0.0]]), np.zeros((2, 3)))
    h0 = np.array(hand.trajectory.positions[0])
    hand_lowered = BarTrajectory(np.array([1.0, 3.0]), np.array([h0, h0 - [0.0, 0.3, 0.0]]), np.zeros((2, 3)))
    model = _model(hanging, bars=(dataclasses.replace(main, trajectory=lowered),
                                  dataclasses.replace(hand, trajectory=hand_lowered)))
    trajectory = simulate_marionette(model, 5.0, progress=False)
    knees = [trajectory.string_names.index(n) for n in ("knee_left", "knee_right")]
    before = trajectory.step_time < 1.0
    after = trajectory.step_time > 4.0
    assert trajectory.string_taut[before][:, knees].all()
    assert not trajectory.string_taut[after][:, knees].any()
    feet = [trajectory.body_names.index(n) for n in ("foot_left", "foot_right")]
    for f in feet:  # the feet are down on the ground: each foot box's lowest corner within 5 mm of it
        half = 0.5 * np.array(next(b.size for b in hanging.puppet.bodies if b.name == trajectory.body_names[f]))
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        world = trajectory.body_pos[-1, f] + corners @ quat_to_matrix(trajectory.body_rot[-1, f]).T
        assert world[:, 1].min() - hanging.ground_height < 0.005, (trajectory.body_names[f], world[:, 1].min())
    feedback = np.linalg.norm(trajectory.bar_feedback[:, 0], axis=1)
    assert feedback[after].max() < 0.8 * feedback[before].min()


def _torso_path(scene, puppet_hz, string_hz=None, seconds=3.0, frame_hz=30.0):
    changes = {"puppet_hz": puppet_hz}
    if string_hz is not None:
        changes["string_hz"] = string_hz
    model = _model(scene, **changes)
    trajectory = simulate_marionette(model, seconds, progress=False, frame_hz=frame_hz)
    return trajectory.frame_time, trajectory.body_pos[:, 0]


def test_slow_motion_at_30_hz_and_1_khz_agree_and_converge(hanging):
    """The default sway over 4 s: the puppet at ~30 Hz stays within 2.5 mm of the fully coupled
    1 kHz run, and the gap shrinks with the puppet step at first order or better.

    Rates 31.25 and 62.5 Hz (32 and 16 string steps per puppet step) share frames with the
    1 kHz run. Measured torso gaps, largest / RMS over the run: 1.42 / 0.80 mm at 31.25 Hz,
    1.11 / 0.39 mm at 62.5 Hz, ratio 2.07 (with the two-sided limit band of before issue 13:
    1.76 / 0.89 mm, 1.14 / 0.47 mm; 0.56 / 0.22 mm at 125 Hz, 0.27 / 0.08 mm at 250 Hz): the RMS
    gap halves or better with each halving of the step (ratios 1.9, 2.2, 2.6; first order is
    2); the largest is the start's transient (at 0.1 s), whose ratio here is 1.5. With the
    ``x + H v`` tie path of before (``string_body_coupling``) the largest gap was 21.7 mm at
    31.25 Hz. The bound 2.5 mm is the measured largest gap with 40 % headroom; the order
    check (on the RMS gap) is what guards the physics.
    """
    t_ref, x_ref = _torso_path(hanging, 1000.0, seconds=4.0, frame_hz=31.25)
    gaps, rms = {}, {}
    for hz in (31.25, 62.5):
        t, x = _torso_path(hanging, hz, seconds=4.0, frame_hz=31.25)
        np.testing.assert_allclose(t, t_ref)
        gap = np.linalg.norm(x - x_ref, axis=1)
        gaps[hz], rms[hz] = float(gap.max()), float(np.sqrt(np.mean(gap**2)))
    print(f"\ntorso gaps to 1 kHz, largest {gaps}, RMS {rms} [m]")
    assert gaps[31.25] < 0.0025, gaps
    assert 1.8 < rms[31.25] / rms[62.5] < 4.5, rms


def test_fast_motion_is_more_accurate_fully_coupled(hanging):
    """A fast jerk (bar 8 cm sideways in 0.15 s): against a 2 kHz fully coupled reference, the
    puppet at 1 kHz is closer than the puppet at 30 Hz."""
    main, hand = hanging.bars
    p0 = np.array(main.trajectory.positions[0])
    jerk = BarTrajectory(np.array([0.0, 0.3, 0.45]), np.array([p0, p0, p0 + [0.08, 0.0, 0.0]]), np.zeros((3, 3)))
    scene = dataclasses.replace(hanging, bars=(dataclasses.replace(main, trajectory=jerk), hand))
    t_ref, x_ref = _torso_path(scene, 2000.0, string_hz=2000.0, seconds=1.5)
    errors = {}
    for hz in (30.0, 1000.0):
        t, x = _torso_path(scene, hz, seconds=1.5)
        reference = np.stack([np.interp(t, t_ref, x_ref[:, i]) for i in range(3)], axis=1)
        errors[hz] = float(np.sqrt(np.mean(np.sum((x - reference) ** 2, axis=1))))
    assert errors[1000.0] < errors[30.0], errors


def test_30_hz_coupling_stays_stable_with_10x_stiffer_strings(hanging):
    strings = tuple(dataclasses.replace(s, stiffness=10 * s.stiffness, tie_stiffness=10 * s.tie_stiffness,
                                        tie_damping=10 * s.tie_damping) for s in hanging.strings)
    model = _model(hanging, strings=strings)
    trajectory = simulate_marionette(model, 4.0, progress=False)
    assert np.all(np.isfinite(trajectory.body_pos))
    weight = model.puppet_mass * G
    assert np.abs(trajectory.tie_force[-50:, :, 1].sum(axis=1) - weight).max() < 0.2 * weight


@pytest.mark.parametrize("name", ["hanging", "chair", "ball"])
def test_every_shipped_scene_runs_10_s(name):
    scene = dm.load_scene(name)
    model = _model(scene)
    trajectory = simulate_marionette(model, 10.0, progress=False)
    for array in (trajectory.particle_q, trajectory.body_pos, trajectory.tie_force, trajectory.bar_feedback,
                  trajectory.bar_reaction):
        assert np.all(np.isfinite(array))
    t = trajectory.frame_time
    if name == "ball":
        ball = trajectory.body_pos[:, -1]
        before, after = np.searchsorted(t, 1.0), np.searchsorted(t, 3.0)
        assert np.linalg.norm(ball[after] - ball[before]) > 0.1  # kicked
    if name == "chair":
        pelvis = trajectory.body_pos[:, 0, 1]
        assert pelvis[-1] > pelvis[0] + 0.1  # it rises from the seat


def test_simulate_writes_an_animation_with_the_expected_frames(tmp_path):
    import imageio.v2 as imageio

    from dmarionette.cli import main

    out = tmp_path / "hanging"
    assert main(["simulate", "hanging", "--duration", "1.0", "--out", str(out), "--quiet", "--fast-compile",
                 "--fps", "15"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    frames = imageio.mimread(out / "animation.gif")
    # 1 s in frames of 33 string steps: 31 frames (rounded up) plus the initial one = 32 kept;
    # at 15 fps every 2nd is drawn: 16.
    assert len(frames) == summary["files"]["animation_frames"] == 16
    first, last = np.asarray(frames[0], dtype=float), np.asarray(frames[-1], dtype=float)
    assert first.std() > 10.0  # not blank
    assert np.abs(first - last).mean() > 0.01  # it moves
    data = dm.read_trajectory(out / "trajectory.npz")
    assert data["metadata"]["kind"] == "marionette" and data["body_pos"].shape == (32, 12, 3)

