"""JVP of a puppet rollout with point springs and ground contact (``articulation/step_tangent``:
``PuppetStepTangent``, P = 3 directions) against the tape's VJP of the same rollout of
``SolverArticulation.step``, by the dot-product identity (1e-10 of the terms' magnitudes, as
``tests/articulation/test_puppet_tangent.py``'s rollout test).

Inputs differentiated: the initial ``joint_q`` and ``joint_qd``, the joint forces, the applied
body forces and torques, the two springs' anchors and anchor velocities and their stiffness
and damping. Two worlds, the shipped puppet with joint limits, hard and smooth ground contact
placed so that the lowest body centre is 2 cm under the ground (some corners in, others out).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.articulation.solver import ContactSettings, SolverArticulation, build_articulation_model
from dmarionette.articulation.step_tangent import PuppetStepTangent
from dmarionette.scene.puppet import load_puppet

WORLDS, STEPS, DT, P = 2, 3, 0.01, 3
SPRINGS = (("head", 300.0, 2.0), ("hand_left", 150.0, 1.0))


def _initial(m, rng):
    q = np.tile(m.q_rest, (WORLDS, 1))
    q[:, 11:] += rng.uniform(-0.2, 0.2, size=(WORLDS, m.q_count - 11))
    return q, 0.3 * rng.normal(size=(WORLDS, m.qd_count))


def _ground_height(q):
    """2 cm above the lowest body centre of the initial states."""
    m = build_articulation_model(load_puppet())
    s = m.state(WORLDS)
    s.joint_q.assign(q)
    SolverArticulation(m, optimization_level=0).eval_kinematics(s)
    return float(s.body_pos.numpy()[..., 1].min()) + 0.02


def _problem(smooth: bool):
    """The model, solver, tangent step, control and its tangents, the directions and the start of the
    module doc's rollout."""
    rng = np.random.default_rng(3)
    q0, qd0 = _initial(build_articulation_model(load_puppet()), rng)
    m = build_articulation_model(load_puppet(), springs=SPRINGS, requires_grad=True,
                                 contacts=ContactSettings(ground=True, smooth=smooth, ground_height=_ground_height(q0)))
    solver = SolverArticulation(m, optimization_level=0)
    jvp = PuppetStepTangent(solver, P, WORLDS, optimization_level=0)
    S, B = m.spring_count, m.body_count
    control = m.control(WORLDS, requires_grad=True)
    values = {"joint_f": 0.02 * rng.normal(size=(WORLDS, m.qd_count)),
              "body_force": 0.1 * rng.normal(size=(WORLDS, B, 3)),
              "body_torque": 0.01 * rng.normal(size=(WORLDS, B, 3)),
              "spring_anchor_pos": np.array([[0.0, 0.62, 0.02], [0.12, 0.3, 0.05]])[None].repeat(WORLDS, 0),
              "spring_anchor_vel": 0.1 * rng.normal(size=(WORLDS, S, 3))}
    for n, v in values.items():
        getattr(control, n).assign(v)
    # directions: every input, at its own scale
    tc = jvp.control_tangent()
    v = {n: rng.normal(size=getattr(tc, n).shape + ((3,) if getattr(tc, n).dtype == wp.vec3d else ()))
         for n in ("joint_f", "body_force", "body_torque", "spring_anchor_pos", "spring_anchor_vel",
                   "spring_stiffness", "spring_damping")}
    v["spring_stiffness"] *= 30.0
    for n, x in v.items():
        getattr(tc, n).assign(x)
    v_q, v_qd = rng.normal(size=(P, WORLDS, m.q_count)), rng.normal(size=(P, WORLDS, m.qd_count))
    return m, solver, jvp, control, values, tc, v, (q0, qd0, v_q, v_qd), rng


def _rollout_arrays(m, jvp, start):
    """The rollout's states and tangents, the first set to ``start`` (``q0, qd0, v_q, v_qd``)."""
    states = [m.state(WORLDS) for _ in range(STEPS + 1)]
    tangents = [jvp.tangent_state() for _ in range(STEPS + 1)]
    for a, x in zip((states[0].joint_q, states[0].joint_qd, tangents[0].joint_q, tangents[0].joint_qd), start):
        a.assign(x)
    return states, tangents


@pytest.mark.parametrize("smooth", [False, True])
def test_puppet_rollout_jvp_with_springs_and_contact(smooth):
    m, solver, jvp, control, values, tc, v, (q0, qd0, v_q, v_qd), rng = _problem(smooth)
    states, tangents = _rollout_arrays(m, jvp, (q0, qd0, v_q, v_qd))
    for i in range(STEPS):
        jvp.step(states[i], tangents[i], states[i + 1], tangents[i + 1], control, tc, DT)

    taped = [m.state(WORLDS, requires_grad=True) for _ in range(STEPS + 1)]
    taped[0].joint_q.assign(q0)
    taped[0].joint_qd.assign(qd0)
    tape = wp.Tape()
    with tape:
        for i in range(STEPS):
            solver.step(taped[i], taped[i + 1], control, DT, tape=tape)
    np.testing.assert_array_equal(taped[-1].joint_q.numpy(), states[-1].joint_q.numpy())
    np.testing.assert_array_equal(taped[-1].joint_qd.numpy(), states[-1].joint_qd.numpy())
    # the contact acts in the first step (its wrench alone, from the initial state's kinematics)
    ws = m.workspace(WORLDS)
    solver.eval_kinematics(states[0], ws)
    solver.contacts.eval(ws, wp.float64(DT))
    assert np.abs(ws.body_wrench.numpy()).max() > 1.0
    u_q, u_qd = rng.normal(size=(WORLDS, m.q_count)), rng.normal(size=(WORLDS, m.qd_count))
    tape.backward(grads={taped[-1].joint_q: wp.array(u_q, dtype=wp.float64),
                         taped[-1].joint_qd: wp.array(u_qd, dtype=wp.float64)})
    grads = {"joint_q": taped[0].joint_q.grad.numpy(), "joint_qd": taped[0].joint_qd.grad.numpy(),
             **{n: getattr(control, n).grad.numpy() for n in values},
             "spring_stiffness": m.spring_stiffness.grad.numpy(), "spring_damping": m.spring_damping.grad.numpy()}
    dirs = {"joint_q": v_q, "joint_qd": v_qd, **v}
    jq, jqd = tangents[-1].joint_q.numpy(), tangents[-1].joint_qd.numpy()
    for p in range(P):
        terms_f = np.concatenate([(u_q * jq[p]).ravel(), (u_qd * jqd[p]).ravel()])
        terms_r = np.concatenate([(grads[n] * dirs[n][p]).ravel() for n in grads])
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        print(f"smooth={smooth} p={p}: <u, Jv> = {terms_f.sum():.15e}, <J^T u, v> = {terms_r.sum():.15e}, "
              f"|diff| / scale = {abs(terms_f.sum() - terms_r.sum()) / scale:.1e}")
        for n in grads:
            assert np.any(grads[n]), f"no gradient reaches {n}"
        assert abs(terms_f.sum() - terms_r.sum()) <= 1e-10 * scale, p


@pytest.mark.parametrize("smooth", [False, True])
def test_kept_contact_tangents_give_the_step_its_own(smooth):
    """``step(..., contacts_kept=True)`` after ``eval_contacts(..., keep=True)`` of the same kinematics
    (what the marionette's trial and puppet steps do, ``grad/marionette_tangent``): the primal to the
    bit, the tangents to rounding (the kept contact tangents are summed apart and then added, the
    plain step adds them point by point: about 100 terms of one rounding each per body, through 3
    steps). Without the kept tangents added the step's tangents move by the contacts' (checked to be
    far above rounding here)."""
    m, solver, jvp, control, values, tc, v, (q0, qd0, v_q, v_qd), rng = _problem(smooth)
    trial, trial_body = m.workspace(WORLDS), jvp.body_tangents()
    h, hi = solver.step_sizes(DT)
    runs = {}
    for kept in (False, True):
        states, tangents = _rollout_arrays(m, jvp, (q0, qd0, v_q, v_qd))
        for i in range(STEPS):
            if kept:  # a pass of the same kinematics before the step (the trial's, without its other loads)
                jvp.eval_kinematics(states[i], tangents[i], trial, trial_body)
                jvp.eval_external_forces(trial, trial_body, control, tc)
                jvp.eval_contacts(trial, trial_body, hi, keep=True)
            jvp.step(states[i], tangents[i], states[i + 1], tangents[i + 1], control, tc, DT, contacts_kept=kept)
        runs[kept] = (states[-1], tangents[-1])
    (plain, plain_t), (kept, kept_t) = runs[False], runs[True]
    np.testing.assert_array_equal(kept.joint_q.numpy(), plain.joint_q.numpy())
    np.testing.assert_array_equal(kept.joint_qd.numpy(), plain.joint_qd.numpy())
    contact = np.abs(jvp.kept_contacts["body_wrench"].numpy()).max()
    for n in ("joint_q", "joint_qd"):
        want, got = getattr(plain_t, n).numpy(), getattr(kept_t, n).numpy()
        err = np.abs(got - want).max() / np.abs(want).max()
        print(f"smooth={smooth} {n}: max |kept - plain| / max |plain| = {err:.1e}; kept contact wrench tangent "
              f"{contact:.1e}")
        assert err <= 1e-12, n
    assert contact > 1e-3 * np.abs(jvp.tan_body["body_wrench"].numpy()).max()
