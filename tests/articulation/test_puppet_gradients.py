"""Gradients of the articulated step (Warp tape) against central finite differences.

float64, no contact, joint limits compiled out (the loss is then smooth). A 10-step
rollout at h = 10 ms with two point spring-dampers (the string coupling), random joint
forces and the default joint damping; the loss is a random linear function of the final
joint coordinates and velocities. Finite differences: central, Richardson-extrapolated
from steps eps and eps/2 (eps = 1e-4), so truncation is O(eps^4) (~1e-12 relative) and
rounding ~1e-16 |f| / eps; plain central differences were measured to sit at 1e-5..3e-5
from truncation (eps = 1e-4) or rounding (eps = 1e-6) on the smallest components, which
is the FD error, not the gradient's: the tolerance stays 1e-5.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import warp as wp

from dmarionette.articulation.solver import SolverArticulation, build_articulation_model
from dmarionette.scene.puppet import load_puppet

wp.config.log_level = wp.LOG_WARNING

STEPS = 10
DT = 0.01


@wp.kernel
def eval_linear_loss(
    q: wp.array2d(dtype=wp.float64),
    qd: wp.array2d(dtype=wp.float64),
    wq: wp.array(dtype=wp.float64),
    wqd: wp.array(dtype=wp.float64),
    loss: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    if i < wq.shape[0]:
        wp.atomic_add(loss, 0, wq[i] * q[0, i])
    if i < wqd.shape[0]:
        wp.atomic_add(loss, 0, wqd[i] * qd[0, i])


class Rollout:
    def __init__(self):
        self.model = build_articulation_model(
            load_puppet(), joint_limits=False,
            springs=(("head", 300.0, 2.0), ("hand_left", 150.0, 1.0)), requires_grad=True)
        self.solver = SolverArticulation(self.model, optimization_level=0)
        rng = np.random.default_rng(7)
        m = self.model
        self.q0 = m.q_rest.copy()
        self.q0[3:7] = [0.9, 0.1, -0.2, 0.3]
        self.q0[7:11] = [0.95, 0.05, 0.2, -0.1]
        self.q0[11:] = rng.uniform(-0.6, 0.6, size=m.q_count - 11)
        self.qd0 = rng.normal(size=m.qd_count)
        self.f = rng.normal(size=m.qd_count) * 0.02
        self.wq = wp.array(rng.normal(size=m.q_count), dtype=wp.float64)
        self.wqd = wp.array(rng.normal(size=m.qd_count) * 0.1, dtype=wp.float64)
        self.anchor = np.array([[0.0, 0.62, 0.02], [0.12, 0.3, 0.05]])
        self.anchor_v = np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.1]])
        self.body_force = rng.normal(size=(m.body_count, 3)) * 0.05
        self.mass = m.body_mass.numpy().copy()

    def run(self, q0, qd0, f, damping, k, tape=None):
        m = self.model
        states = [m.state(requires_grad=True) for _ in range(STEPS + 1)]
        c = m.control(requires_grad=True)
        states[0].joint_q.assign(q0[None])
        states[0].joint_qd.assign(qd0[None])
        c.joint_f.assign(f[None])
        c.spring_anchor_pos.assign(self.anchor[None])
        c.spring_anchor_vel.assign(self.anchor_v[None])
        c.body_force.assign(self.body_force[None])
        m.body_mass.assign(self.mass)
        m.dof_damping.assign(damping)
        m.spring_stiffness.assign(k)
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        with (tape if tape is not None else contextlib.nullcontext()):
            for i in range(STEPS):
                self.solver.step(states[i], states[i + 1], c, DT, tape=tape)
            wp.launch(eval_linear_loss, dim=max(m.q_count, m.qd_count),
                      inputs=[states[-1].joint_q, states[-1].joint_qd, self.wq, self.wqd], outputs=[loss])
        return loss, states, c

    def loss(self, *args):
        return self.run(*args)[0].numpy()[0]


@pytest.fixture(scope="module")
def rollout():
    return Rollout()


def _check(name, grad, fd_fn, x, idx, eps=1e-4):
    worst = 0.0
    scale = np.linalg.norm(grad)
    for i in idx:
        def central(e):
            xp, xm = x.copy(), x.copy()
            xp[i] += e
            xm[i] -= e
            return (fd_fn(xp) - fd_fn(xm)) / (2 * e)

        fd = (4.0 * central(eps / 2) - central(eps)) / 3.0  # Richardson: O(eps^4)
        err = abs(grad[i] - fd) / max(abs(fd), 1e-3 * scale)
        worst = max(worst, err)
    print(f"{name}: worst relative error {worst:.2e} over {len(idx)} components")
    assert worst <= 1e-5, name


def test_gradients_match_finite_differences(rollout):
    r = rollout
    m = r.model
    damping0 = m.dof_damping.numpy().copy()
    k0 = np.array([300.0, 150.0])
    tape = wp.Tape()
    loss, states, c = r.run(r.q0, r.qd0, r.f, damping0, k0, tape)
    tape.backward(loss)
    g_q = states[0].joint_q.grad.numpy()[0].copy()
    g_qd = states[0].joint_qd.grad.numpy()[0].copy()
    g_f = c.joint_f.grad.numpy()[0].copy()
    g_d = m.dof_damping.grad.numpy().copy()
    g_k = m.spring_stiffness.grad.numpy().copy()
    g_a = c.spring_anchor_pos.grad.numpy()[0].copy()
    g_b = c.body_force.grad.numpy()[0].copy()
    g_m = m.body_mass.grad.numpy().copy()
    tape.zero()
    assert np.all(np.isfinite(g_q)) and np.any(g_q != 0)

    # the loss depends on a unit quaternion only through its direction: compare along
    # all coordinates anyway (normalisation is part of the computation graph)
    _check("initial q", g_q, lambda x: r.loss(x, r.qd0, r.f, damping0, k0), r.q0, range(m.q_count))
    _check("initial qd", g_qd, lambda x: r.loss(r.q0, x, r.f, damping0, k0), r.qd0, range(m.qd_count))
    _check("joint forces", g_f, lambda x: r.loss(r.q0, r.qd0, x, damping0, k0), r.f, range(m.qd_count))
    _check("joint damping", g_d, lambda x: r.loss(r.q0, r.qd0, r.f, x, k0), damping0, range(6, m.qd_count),
           eps=1e-6)  # damping is ~1e-3: a step small relative to it
    _check("spring stiffness", g_k, lambda x: r.loss(r.q0, r.qd0, r.f, damping0, x), k0, range(2))

    def with_anchor(x):
        saved = r.anchor
        r.anchor = x.reshape(2, 3)
        try:
            return r.loss(r.q0, r.qd0, r.f, damping0, k0)
        finally:
            r.anchor = saved

    _check("spring anchor", g_a.ravel(), with_anchor, r.anchor.ravel().copy(), range(6))

    def with_attr(name, shape):
        def fn(x):
            saved = getattr(r, name)
            setattr(r, name, x.reshape(shape))
            try:
                return r.loss(r.q0, r.qd0, r.f, damping0, k0)
            finally:
                setattr(r, name, saved)
        return fn

    _check("body forces", g_b.ravel(), with_attr("body_force", (-1, 3)), r.body_force.ravel().copy(),
           range(g_b.size))
    _check("body masses", g_m, with_attr("mass", (-1,)), r.mass.copy(), range(m.body_count),
           eps=1e-6)  # masses are 0.02..0.3 kg: a step small relative to them


def test_smooth_ground_contact_gradients():
    """The smooth contact option (softplus penetration, approach-only damping,
    regularised friction) is differentiable: the puppet lands on the ground from 1 cm,
    10 steps at 60 Hz with feet and then more shapes touching; tape gradients of a
    linear loss w.r.t. initial velocities and joint forces match Richardson central
    differences to 1e-5 relative."""
    from dmarionette.articulation.solver import ContactSettings

    model = build_articulation_model(load_puppet(), joint_limits=False,
                                     contacts=ContactSettings(ground=True, smooth=True))
    solver = SolverArticulation(model, optimization_level=0)
    rng = np.random.default_rng(11)
    q0 = model.q_rest.copy()
    q0[1] += 0.01
    q0[11:] += rng.uniform(-0.3, 0.3, size=model.q_count - 11)
    qd0 = rng.normal(size=model.qd_count) * 0.5
    f0 = rng.normal(size=model.qd_count) * 0.01
    wq = wp.array(rng.normal(size=model.q_count), dtype=wp.float64)
    wqd = wp.array(rng.normal(size=model.qd_count) * 0.1, dtype=wp.float64)

    def run(qd, f, tape=None):
        states = [model.state(requires_grad=True) for _ in range(STEPS + 1)]
        c = model.control(requires_grad=True)
        states[0].joint_q.assign(q0[None])
        states[0].joint_qd.assign(qd[None])
        c.joint_f.assign(f[None])
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        with (tape if tape is not None else contextlib.nullcontext()):
            for i in range(STEPS):
                solver.step(states[i], states[i + 1], c, 1.0 / 60.0, tape=tape)
            wp.launch(eval_linear_loss, dim=max(model.q_count, model.qd_count),
                      inputs=[states[-1].joint_q, states[-1].joint_qd, wq, wqd], outputs=[loss])
        return loss, states, c

    tape = wp.Tape()
    loss, states, c = run(qd0, f0, tape)
    tape.backward(loss)
    g_qd = states[0].joint_qd.grad.numpy()[0].copy()
    g_f = c.joint_f.grad.numpy()[0].copy()
    tape.zero()
    assert np.all(np.isfinite(g_qd)) and np.all(np.isfinite(g_f))
    _check("initial qd (smooth contact)", g_qd, lambda x: run(x, f0)[0].numpy()[0], qd0, range(model.qd_count))
    _check("joint forces (smooth contact)", g_f, lambda x: run(qd0, x)[0].numpy()[0], f0, range(model.qd_count),
           eps=1e-5)  # forces are ~1e-2 and the contact response is stiff: a smaller step
