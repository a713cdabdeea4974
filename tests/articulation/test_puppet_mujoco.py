"""Agreement with MuJoCo on the exported MJCF model (tier iii: an independent engine)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

mujoco = pytest.importorskip("mujoco")

from dmarionette.articulation.solver import BallDescription, SolverArticulation, build_articulation_model
from dmarionette.articulation.mjcf import puppet_to_mjcf
from dmarionette.scene.puppet import load_puppet

wp.config.log_level = wp.LOG_WARNING


def _random_unit_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _random_state(model, rng):
    """Random joint coordinates (unit quaternions for free/ball joints) and velocities."""
    q = np.empty(model.q_count)
    for j in model.topology.joints:
        s = j.q_start
        if j.type == "free":
            q[s:s + 3] = rng.normal(size=3) * 0.3
            q[s + 3:s + 7] = _random_unit_quat(rng)
        elif j.type == "ball":
            q[s:s + 4] = _random_unit_quat(rng)
        else:
            n = len(j.axes)
            q[s:s + n] = rng.uniform(-2.0, 2.0, size=n)
    qd = rng.normal(size=model.qd_count) * 2.0
    return q, qd


@pytest.fixture(scope="module")
def setup():
    puppet = load_puppet()
    ball = BallDescription(radius=0.06, mass=0.08, position=(0.3, 0.06, 0.2))
    model = build_articulation_model(puppet, ball=ball, joint_limits=False)
    solver = SolverArticulation(model, optimization_level=0)
    xml = puppet_to_mjcf(puppet, ball=ball, joint_limits=False, timestep=1e-3)
    mj = mujoco.MjModel.from_xml_string(xml)
    mj.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return model, solver, mj


def test_layout_matches(setup):
    model, _, mj = setup
    assert mj.nq == model.q_count == 25 + 7
    assert mj.nv == model.qd_count == 23 + 6
    np.testing.assert_allclose(mj.qpos0, model.q_rest, atol=1e-15)
    np.testing.assert_allclose(mj.dof_damping, model.dof_damping.numpy(), atol=0)


def test_default_puppet_has_23_dofs():
    model = build_articulation_model(load_puppet())
    assert model.body_count == 12 and model.qd_count == 23 and model.q_count == 25


def test_mass_matrix_and_accelerations(setup):
    """M and forward accelerations (gravity, damping, random joint forces) vs mj_forward,
    over 20 random states: relative error <= 1e-8 (both are exact algorithms in float64;
    the error is rounding, amplified by cond(M))."""
    model, solver, mj = setup
    rng = np.random.default_rng(0)
    data = mujoco.MjData(mj)
    n = 20
    qs, qds, fs = [], [], []
    for _ in range(n):
        q, qd = _random_state(model, rng)
        qs.append(q)
        qds.append(qd)
        fs.append(rng.normal(size=model.qd_count) * 0.05)
    state = model.state(world_count=n)
    out = model.state(world_count=n)
    control = model.control(world_count=n)
    state.joint_q.assign(np.array(qs))
    state.joint_qd.assign(np.array(qds))
    control.joint_f.assign(np.array(fs))
    M = solver.eval_mass_matrix(state)
    solver.step(state, out, control, 0.0)  # h = 0: the explicit forward dynamics
    qdd = out.joint_qdd.numpy()
    worst_m, worst_a = 0.0, 0.0
    for i in range(n):
        data.qpos[:] = qs[i]
        data.qvel[:] = qds[i]
        data.qfrc_applied[:] = fs[i]
        mujoco.mj_forward(mj, data)
        Mmj = np.zeros((mj.nv, mj.nv))
        mujoco.mj_fullM(mj, data, Mmj)
        worst_m = max(worst_m, np.linalg.norm(M[i] - Mmj) / np.linalg.norm(Mmj))
        worst_a = max(worst_a, np.linalg.norm(qdd[i] - data.qacc) / np.linalg.norm(data.qacc))
    print(f"mass matrix rel err {worst_m:.2e}, acceleration rel err {worst_a:.2e}")
    assert worst_m <= 1e-8
    assert worst_a <= 1e-8


def test_trajectory_matches_mujoco_euler(setup):
    """0.2 s (200 steps of 1 ms) from a random state, no contact. With only joint damping
    stiff, our linearised implicit step *is* MuJoCo's Euler integrator (implicit damping,
    semi-implicit positions, the same quaternion update), so the two agree to rounding
    error amplified by the dynamics; the tolerance 1e-8 on positions (relative to their
    scale) leaves 7 orders above float64 rounding for that growth."""
    model, solver, mj = setup
    rng = np.random.default_rng(1)
    q0, qd0 = _random_state(model, rng)
    data = mujoco.MjData(mj)
    data.qpos[:] = q0
    data.qvel[:] = qd0
    steps = 200
    states = [model.state() for _ in range(2)]
    control = model.control()
    states[0].joint_q.assign(q0[None])
    states[0].joint_qd.assign(qd0[None])
    for k in range(steps):
        solver.step(states[k % 2], states[(k + 1) % 2], control, mj.opt.timestep)
        mujoco.mj_step(mj, data)
    q = states[steps % 2].joint_q.numpy()[0]
    qd = states[steps % 2].joint_qd.numpy()[0]
    err_q = np.max(np.abs(q - data.qpos)) / np.max(np.abs(data.qpos))
    err_qd = np.max(np.abs(qd - data.qvel)) / np.max(np.abs(data.qvel))
    print(f"trajectory rel err q {err_q:.2e} qd {err_qd:.2e}")
    assert err_q <= 1e-8
    assert err_qd <= 1e-8


def test_export_with_limits_ground_and_ball_loads():
    """The full export (joint ranges, ground plane, ball) loads; ranges and damping match."""
    puppet = load_puppet()
    ball = BallDescription()
    model = build_articulation_model(puppet, ball=ball)
    mj = mujoco.MjModel.from_xml_string(puppet_to_mjcf(puppet, ball=ball))
    assert mj.nbody == 1 + 13 and mj.njnt == 1 + 1 + 4 * 2 + 6 + 1  # root, neck, universals as 2 hinges, hinges, ball
    assert np.allclose(mj.opt.gravity, [0.0, -9.81, 0.0])
    lower = model.dof_limit_lower.numpy()
    upper = model.dof_limit_upper.numpy()
    for j in range(mj.njnt):
        if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            d = mj.jnt_dofadr[j]
            assert mj.jnt_limited[j]
            assert mj.jnt_range[j, 0] == pytest.approx(lower[d]) and mj.jnt_range[j, 1] == pytest.approx(upper[d])
        if mj.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            assert mj.jnt_range[j, 1] == pytest.approx(upper[mj.jnt_dofadr[j]])
    np.testing.assert_allclose(mj.body_mass[1:], model.body_mass.numpy())


def test_other_puppet_oblique_axes_matches_mujoco():
    """Any tree is described the same way: a small creature with oblique universal axes,
    a ball joint, a hinge, an overridden inertia and a chain three deep agrees with
    MuJoCo as tightly as the marionette (mass matrix and accelerations, 1e-8)."""
    from dmarionette.scene.puppet import puppet_from_table

    table = {
        "root": "body",
        "root_position": [0.1, 0.5, -0.2],
        "bodies": {
            "body": {"shape": "box", "size": [0.2, 0.1, 0.3], "mass": 0.4},
            "neck": {"shape": "box", "size": [0.04, 0.12, 0.04], "mass": 0.05,
                     "inertia": [1e-4, 2e-5, 9e-5]},
            "head": {"shape": "sphere", "size": [0.05, 0.0, 0.0], "mass": 0.08},
            "tail": {"shape": "box", "size": [0.03, 0.03, 0.15], "mass": 0.03},
        },
        "joints": {
            "withers": {"type": "universal", "parent": "body", "child": "neck",
                        "axes": [[1.0, 1.0, 0.0], [0.0, 0.3, 1.0]],
                        "anchor_parent": [0.0, 0.05, 0.15], "anchor_child": [0.0, -0.06, 0.0],
                        "damping": 0.01},
            "poll": {"type": "ball", "parent": "neck", "child": "head",
                     "anchor_parent": [0.0, 0.06, 0.0], "anchor_child": [0.0, -0.04, 0.02],
                     "damping": 0.003},
            "dock": {"type": "hinge", "parent": "body", "child": "tail", "axes": [[0.2, 1.0, 0.1]],
                     "anchor_parent": [0.0, 0.0, -0.15], "anchor_child": [0.0, 0.0, 0.075]},
        },
    }
    puppet = puppet_from_table(table, "creature.toml: [puppet]")
    assert [b.name for b in puppet.bodies] == ["body", "neck", "head", "tail"]
    model = build_articulation_model(puppet, joint_limits=False)
    solver = SolverArticulation(model, optimization_level=0)
    mj = mujoco.MjModel.from_xml_string(puppet_to_mjcf(puppet, joint_limits=False))
    mj.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert (mj.nq, mj.nv) == (model.q_count, model.qd_count) == (7 + 2 + 4 + 1, 6 + 2 + 3 + 1)
    rng = np.random.default_rng(5)
    data = mujoco.MjData(mj)
    state, out, control = model.state(), model.state(), model.control()
    for _ in range(5):
        q, qd = _random_state(model, rng)
        f = rng.normal(size=model.qd_count) * 0.05
        state.joint_q.assign(q[None])
        state.joint_qd.assign(qd[None])
        control.joint_f.assign(f[None])
        M = solver.eval_mass_matrix(state)[0]
        solver.step(state, out, control, 0.0)
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q, qd, f
        mujoco.mj_forward(mj, data)
        Mmj = np.zeros((mj.nv, mj.nv))
        mujoco.mj_fullM(mj, data, Mmj)
        assert np.linalg.norm(M - Mmj) <= 1e-8 * np.linalg.norm(Mmj)
        qdd = out.joint_qdd.numpy()[0]
        assert np.linalg.norm(qdd - data.qacc) <= 1e-8 * np.linalg.norm(data.qacc)
