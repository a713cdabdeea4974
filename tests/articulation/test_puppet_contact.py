"""Contacts at the paper's body rate (30 Hz): ground, chair, ball."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.articulation.solver import (
    BallDescription,
    ContactSettings,
    SolverArticulation,
    build_articulation_model,
)
from dmarionette.scene.puppet import load_puppet


H30 = 1.0 / 30.0
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


def _rot(q):
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def lowest_points(model, solver, state, skip=()):
    """Lowest shape point of each body and the fastest shape-point speed [m], [m/s]."""
    solver.eval_kinematics(state)
    pos, rot = state.body_pos.numpy()[0], state.body_rot.numpy()[0]
    w, v = state.body_w.numpy()[0], state.body_v.numpy()[0]
    low, speed = [], 0.0
    for b, (shape, size) in enumerate(model.body_shape):
        if b in skip:
            continue
        R = _rot(rot[b])
        if shape == "sphere":
            low.append(pos[b, 1] - size[0])
            speed = max(speed, np.linalg.norm(v[b]) + np.linalg.norm(w[b]) * size[0])
        else:
            r = (_CORNERS * np.asarray(size) / 2) @ R.T
            low.append(np.min(pos[b, 1] + r[:, 1]))
            speed = max(speed, np.max(np.linalg.norm(v[b] + np.cross(w[b], r), axis=1)))
    return np.array(low), speed


def _simulate(model, solver, q0, qd0, dt, duration, probe=None):
    a, b = model.state(), model.state()
    c = model.control()
    a.joint_q.assign(q0[None])
    a.joint_qd.assign(qd0[None])
    for _ in range(int(round(duration / dt))):
        solver.step(a, b, c, dt)
        a, b = b, a
        assert np.all(np.isfinite(a.joint_q.numpy())), "NaN in the state"
        if probe is not None:
            probe(a)
    return a


@pytest.mark.parametrize("smooth", [False, True])
def test_puppet_dropped_on_ground_comes_to_rest(smooth):
    """Dropped from 5 cm with bent joints, the limp puppet falls, collapses and lies still
    after 10 s at 30 Hz. Penetration tolerances: at rest, at most M g / k (the whole
    weight on one contact point, the worst case; 3.7 mm); while falling, at most the
    distance the fastest shape point moves in one step plus that (a penalty contact only
    reacts after a point is below the surface), and never more than 6 cm."""
    # (kinetic-energy bound at rest: see below)
    s = ContactSettings(ground=True, smooth=smooth)
    model = build_articulation_model(load_puppet(), contacts=s)
    solver = SolverArticulation(model, optimization_level=0)
    rng = np.random.default_rng(0)
    q0 = model.q_rest.copy()
    q0[1] += 0.05
    q0[11:] += rng.uniform(-0.2, 0.2, size=model.q_count - 11)
    static = model.body_mass.numpy().sum() * 9.81 / s.stiffness
    worst = {"pen": 0.0, "allowed": 0.0}

    def probe(state):
        low, speed = lowest_points(model, solver, state)
        worst["pen"] = max(worst["pen"], -low.min())
        worst["allowed"] = max(worst["allowed"], speed * H30 + static)

    end = _simulate(model, solver, q0, np.zeros(model.qd_count), H30, 10.0, probe)
    low, _ = lowest_points(model, solver, end)
    qd = end.joint_qd.numpy()[0]
    print(f"smooth={smooth}: max transient penetration {worst['pen'] * 1e3:.1f} mm "
          f"(allowed {worst['allowed'] * 1e3:.1f} mm), at rest {-low.min() * 1e3:.2f} mm "
          f"(allowed {static * 1e3:.2f}), final max |qd| {np.abs(qd).max():.3g}")
    assert -low.min() <= static
    assert worst["pen"] <= min(worst["allowed"], 0.06)
    # at rest: regularised friction lets resting contacts creep at up to v_eps, so the
    # kinetic energy left is at most that of the whole puppet moving at v_eps
    kinetic = 0.5 * qd @ solver.eval_mass_matrix(end)[0] @ qd
    bound = 0.5 * model.body_mass.numpy().sum() * s.friction_velocity**2
    print(f"kinetic energy at 10 s {kinetic:.2e} J (bound {bound:.2e} J)")
    assert kinetic <= bound


def test_ball_pushed_along_ground_rolls_and_slows():
    """A solid ball pushed at 1 m/s without spin slides, friction slows it and spins it
    up until it rolls: v = 5/7 v0, omega r = -v (angular momentum about the contact
    point is conserved, whatever the friction law). Tolerances: 2e-3 v0 on v (the
    contact point sits on the sphere, so only the normal penetration ~ m g / k = 0.25 mm
    changes the lever arm) and v_eps (the friction's regularisation velocity) on the
    residual slip."""
    ball = BallDescription(radius=0.05, mass=0.05, position=(0.5, 0.05, 0.0))
    s = ContactSettings(ground=True, ball=True)
    model = build_articulation_model(load_puppet(), ball=ball, contacts=s)
    solver = SolverArticulation(model, optimization_level=0)
    qd0 = np.zeros(model.qd_count)
    qd0[23] = 1.0
    end = _simulate(model, solver, model.q_rest, qd0, H30, 1.0)
    solver.eval_kinematics(end)
    v = end.body_v.numpy()[0, 12]
    w = end.body_w.numpy()[0, 12]
    print(f"ball: v {v[0]:.5f} m/s (5/7 = {5 / 7:.5f}), slip {v[0] + w[2] * ball.radius:.2e} m/s")
    assert abs(v[0] - 5.0 / 7.0) <= 2e-3
    assert abs(v[0] + w[2] * ball.radius) <= s.friction_velocity
    assert abs(end.body_pos.numpy()[0, 12, 1] - ball.radius) < 1e-3


def test_ball_puppet_contact_forces_are_equal_and_opposite():
    """Without gravity or ground, a ball thrown at the floating puppet: the contact
    wrenches on the ball and on the puppet bodies sum to zero (same point, opposite
    forces: 1e-12 relative) at every step, and the ball is slowed or bounced.
    (Total momentum itself is conserved by the continuous equations only; the
    semi-implicit step in reduced coordinates moves it by O(h), reported below.)"""
    ball = BallDescription(radius=0.05, mass=0.1, position=(0.0, 0.39, 0.3))
    model = build_articulation_model(load_puppet(), ball=ball,
                                     contacts=ContactSettings(ball=True), gravity=(0.0, 0.0, 0.0))
    solver = SolverArticulation(model, optimization_level=0)
    m = model.body_mass.numpy()
    a, b = model.state(), model.state()
    c = model.control()
    qd0 = np.zeros(model.qd_count)
    qd0[25] = -2.0  # ball towards the torso (-z)
    a.joint_qd.assign(qd0[None])
    worst, largest = 0.0, 0.0
    for _ in range(72):  # 0.3 s at 240 Hz
        solver.step(a, b, c, 1.0 / 240.0)
        wrench = solver.default_workspace().body_wrench.numpy()[0]
        worst = max(worst, np.abs(wrench.sum(axis=0)).max())
        largest = max(largest, np.abs(wrench).max())
        a, b = b, a
    solver.eval_kinematics(a)
    vb = a.body_v.numpy()[0, 12]
    p1 = m @ a.body_v.numpy()[0]
    print(f"net contact wrench {worst:.2e} (largest {largest:.2e}); momentum {p1} (start [0, 0, -0.2]); "
          f"ball v {vb}")
    assert largest > 0.1  # they did touch
    assert worst <= 1e-12 * largest
    assert vb[2] > -1.0  # slowed down or bounced


def test_puppet_lands_on_chair():
    """Dropped above a chair (a static box), the puppet comes to rest on its seat, above
    the ground: its lowest point ends at the seat height within the static sag M g / k."""
    seat_top = 0.25
    chair = ((0.0, seat_top / 2, 0.0), (0.5, seat_top / 2, 0.5))  # wide enough to fall onto
    s = ContactSettings(ground=True, chair=chair)
    model = build_articulation_model(load_puppet(), contacts=s)
    solver = SolverArticulation(model, optimization_level=0)
    q0 = model.q_rest.copy()
    q0[1] += seat_top + 0.03
    end = _simulate(model, solver, q0, np.zeros(model.qd_count), H30, 3.0)
    low, _ = lowest_points(model, solver, end)
    static = model.body_mass.numpy().sum() * 9.81 / s.stiffness
    print(f"lowest point {low.min():.4f} m, seat {seat_top} m")
    assert seat_top - static <= low.min() <= seat_top + 0.05
