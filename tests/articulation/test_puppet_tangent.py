"""Forward-mode (tangent) kernels of the generated puppet step (``kernels/articulation_tangent``).

Each generated kernel (kinematics, dynamics with joint limits, integration, mass matrix) of
the shipped puppet is checked against

(a) Warp's reverse mode of the SAME primal kernel on a ``wp.Tape``, by the dot-product
    identity ``<u, J v> = <J^T u, v>`` for random ``u`` and P random directions ``v`` at
    once (P = 1, 3, 8). Both sides are sums of ~1e2..1e3 float64 products; their rounding
    error is ~1e-16 x (number of terms) x (sum of |terms|), so the tolerance is 1e-10
    relative to the sum of the absolute values of the terms of ``<u, J v>``.
(b) central finite differences of the primal kernel with a step-size study: the error
    falls like eps^2 (100x per decade) until rounding (~1e-16 |f| / eps) takes over.

Two worlds: world 0 generic (hinges and universals inside their limits, away from the
band), world 1 with joints inside the limit band (implicit part switched on partly), past
a limit (penalty spring on), and the neck's ball past its cone.
"""

from __future__ import annotations

import re
import zlib

import numpy as np
import pytest
import warp as wp

from dmarionette.articulation.solver import BallDescription, SolverArticulation, build_articulation_model
from dmarionette.kernels.articulation_codegen import LIMIT_BAND, build_articulation_kernels
from dmarionette.kernels.articulation_tangent import (
    TangentError,
    articulation_tangent_source,
    build_articulation_tangent_kernels,
    tangent_kernel_source,
)
from dmarionette.scene.puppet import load_puppet

wp.config.log_level = wp.LOG_WARNING

H = 0.01
WORLDS = 2


def _quat_mj(rng):
    q = rng.normal(size=4)
    q[0] = abs(q[0]) + 1.0
    return q / np.linalg.norm(q) * 1.1  # off the unit sphere: normalisation is part of the kernel


class Setup:
    def __init__(self, one_sided_limits: bool = False):
        self.model = build_articulation_model(load_puppet(), requires_grad=False, one_sided_limits=one_sided_limits)
        m = self.model
        topo = m.topology
        self.primal = build_articulation_kernels(topo, optimization_level=0)
        self.tangent = build_articulation_tangent_kernels(topo, optimization_level=0)
        rng = np.random.default_rng(11)
        lower, upper = m.dof_limit_lower.numpy(), m.dof_limit_upper.numpy()
        q = np.tile(m.q_rest, (WORLDS, 1))
        qd = rng.normal(size=(WORLDS, m.qd_count))
        self.band = []  # (world, dof, where) of the joints placed at the limits
        for w in range(WORLDS):
            q[w, 0:3] += rng.normal(size=3) * 0.05
            q[w, 3:7] = _quat_mj(rng)
            limit_case = 0
            for j in topo.joints[1:]:
                d, s = j.qd_start, j.q_start
                if j.type == "ball":
                    q[w, s:s + 4] = _quat_mj(rng)
                    if w == 1:  # past the cone: rotation angle upper + 0.1
                        n = rng.normal(size=3)
                        n /= np.linalg.norm(n)
                        th = upper[d] + 0.1
                        q[w, s:s + 4] = np.r_[np.cos(th / 2), np.sin(th / 2) * n]
                        self.band.append((w, d, "past the cone"))
                    continue
                for k in range(len(j.axes)):
                    lo, up = lower[d + k], upper[d + k]
                    if w == 0:
                        q[w, s + k] = rng.uniform(lo + 0.2 * (up - lo), up - 0.2 * (up - lo))
                    else:
                        # cycle: inside the band below the upper limit, past the lower limit, generic
                        case = limit_case % 3
                        limit_case += 1
                        if case == 0:
                            q[w, s + k] = up - 0.4 * LIMIT_BAND
                            qd[w, d + k] = abs(qd[w, d + k]) + 0.5  # q + h qd stays inside the band
                            self.band.append((w, d + k, "in the band"))
                        elif case == 1:
                            q[w, s + k] = lo - 0.03
                            qd[w, d + k] = -abs(qd[w, d + k]) - 0.5
                            self.band.append((w, d + k, "past the limit"))
                        else:
                            q[w, s + k] = rng.uniform(lo + 0.2 * (up - lo), up - 0.2 * (up - lo))
        self.q, self.qd = q, qd
        nb = m.body_count
        kin = self.run(self.primal.eval_body_kinematics, self.kinematics_values(q, qd))
        self.body = {k: kin[k].numpy() for k in ("body_pos", "body_rot", "body_w", "body_v")}
        self.wrench = rng.normal(size=(WORLDS, nb, 6)) * 0.1
        a = rng.normal(size=(WORLDS, nb, 6, 6)) * 0.1
        self.stiffness = np.einsum("wbij,wbkj->wbik", a, a) * 1e-3  # h D + h^2 K: small, symmetric PSD
        self.joint_f = rng.normal(size=(WORLDS, m.qd_count)) * 0.05
        self.rng = rng

    # ------------------------------------------------------------ kernel argument values
    def kinematics_values(self, q, qd):
        nb = self.model.body_count
        return dict(joint_q=q, joint_qd=qd, body_pos=np.zeros((WORLDS, nb, 3)), body_rot=np.zeros((WORLDS, nb, 4)),
                    body_w=np.zeros((WORLDS, nb, 3)), body_v=np.zeros((WORLDS, nb, 3)))

    def dynamics_values(self):
        m = self.model
        return dict(body_mass=m.body_mass.numpy(), body_inertia=m.body_inertia.numpy(),
                    dof_damping=m.dof_damping.numpy(), gravity=m.gravity.numpy(),
                    dof_limit_lower=m.dof_limit_lower.numpy(), dof_limit_upper=m.dof_limit_upper.numpy(),
                    limit_stiffness=m.limit_stiffness, limit_damping=m.limit_damping,
                    joint_q=self.q, joint_qd=self.qd, **self.body, body_wrench=self.wrench,
                    body_stiffness=self.stiffness, joint_f=self.joint_f, h=H, h_implicit=H,
                    joint_qdd=np.zeros((WORLDS, m.qd_count)), joint_qd_out=np.zeros((WORLDS, m.qd_count)))

    def integrate_values(self):
        m = self.model
        return dict(joint_q=self.q, joint_qd=self.qd, h=H, joint_q_out=np.zeros((WORLDS, m.q_count)))

    def mass_matrix_values(self):
        m = self.model
        return dict(body_mass=m.body_mass.numpy(), body_inertia=m.body_inertia.numpy(),
                    body_pos=self.body["body_pos"], body_rot=self.body["body_rot"],
                    mass_matrix=np.zeros((WORLDS, m.qd_count, m.qd_count)))

    # ------------------------------------------------------------ launches
    @staticmethod
    def run(kernel, values, requires_grad=False):
        """Launches ``kernel`` over the worlds with ``values`` by parameter name; returns the arrays."""
        arrays, args = {}, []
        for a in kernel.adj.args:
            v = values[a.label]
            if wp.types.is_array(a.type):
                arrays[a.label] = wp.array(np.ascontiguousarray(v), dtype=a.type.dtype, requires_grad=requires_grad)
                args.append(arrays[a.label])
            else:
                args.append(a.type(v))
        wp.launch(kernel, dim=WORLDS, inputs=args)
        return arrays


KERNELS = {  # name: (values method, active inputs, outputs)
    "eval_body_kinematics": ("kinematics_values", ("joint_q", "joint_qd"),
                             ("body_pos", "body_rot", "body_w", "body_v")),
    "solve_body_dynamics": ("dynamics_values", ("joint_q", "joint_qd", "body_pos", "body_rot", "body_w", "body_v",
                                                "body_wrench", "body_stiffness", "joint_f"),
                            ("joint_qdd", "joint_qd_out")),
    "integrate_joint_coordinates": ("integrate_values", ("joint_q", "joint_qd"), ("joint_q_out",)),
    "eval_mass_matrix": ("mass_matrix_values", ("body_pos", "body_rot"), ("mass_matrix",)),
}


@pytest.fixture(scope="module")
def setup():
    return Setup()


@pytest.fixture(scope="module")
def setup_one_sided():
    """The one-sided joint-limit look-ahead (``one_sided_limits``: a trial solve and a brake
    by the end angle inside the dynamics kernel; issue 13)."""
    return Setup(one_sided_limits=True)


def _values(setup, name):
    if name == "eval_body_kinematics":
        return setup.kinematics_values(setup.q, setup.qd)
    return getattr(setup, KERNELS[name][0])()


def jvp(setup, name, values, directions):
    """Outputs' tangents (P, ...) for input tangents ``directions`` {name: (P, ...)}; one tangent launch."""
    _, ins, outs = KERNELS[name]
    P = next(iter(directions.values())).shape[0]
    tv = dict(values, direction_count=P)
    for n in ins:
        tv["tan_" + n] = directions[n]
    for n in outs:
        tv["tan_" + n] = np.zeros((P,) + np.shape(values[n]))
    arrays = setup.run(getattr(setup.tangent, name + "_tangent"), tv)
    primal = setup.run(getattr(setup.primal, name), values)
    for n in outs:  # the tangent kernel writes the primal outputs too
        np.testing.assert_array_equal(arrays[n].numpy(), primal[n].numpy())
    return {n: arrays["tan_" + n].numpy() for n in outs}


def vjp(setup, name, values, adjoints):
    """Inputs' adjoints J^T u by Warp's reverse mode of the primal kernel (wp.Tape)."""
    _, ins, outs = KERNELS[name]
    tape = wp.Tape()
    with tape:
        arrays = setup.run(getattr(setup.primal, name), values, requires_grad=True)
    tape.backward(grads={arrays[n]: wp.array(adjoints[n], dtype=arrays[n].dtype) for n in outs})
    return {n: arrays[n].grad.numpy() for n in ins}


def _directions(setup, name, values, P):
    rng = np.random.default_rng([zlib.crc32(name.encode()), P])  # the same directions however tests are selected
    v = {n: rng.normal(size=(P,) + np.shape(values[n])) for n in KERNELS[name][1]}
    if "body_stiffness" in v:  # symmetric and at the scale of the stiffness: H stays positive definite along it
        s = v["body_stiffness"]
        v["body_stiffness"] = (s + np.swapaxes(s, -1, -2)) * 1e-4
    return v


@pytest.mark.parametrize("P", [1, 3, 8])
@pytest.mark.parametrize("name", list(KERNELS))
def test_tangent_matches_reverse_mode(setup, name, P):
    values = _values(setup, name)
    _, ins, outs = KERNELS[name]
    v = _directions(setup, name, values, P)
    u = {n: setup.rng.normal(size=np.shape(values[n])) for n in outs}
    jv = jvp(setup, name, values, v)
    jtu = vjp(setup, name, values, u)
    for p in range(P):
        terms_f = np.concatenate([(u[n] * jv[n][p]).ravel() for n in outs])
        terms_r = np.concatenate([(jtu[n] * v[n][p]).ravel() for n in ins])
        lhs, rhs = terms_f.sum(), terms_r.sum()
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        print(f"{name} P={P} p={p}: <u, Jv> = {lhs:.15e}, <J^T u, v> = {rhs:.15e}, "
              f"|diff| / scale = {abs(lhs - rhs) / scale:.1e}")
        assert abs(lhs - rhs) <= 1e-10 * scale, (name, p)
    assert all(np.all(np.isfinite(jv[n])) for n in outs)


@pytest.mark.parametrize("P", [1, 3])
def test_one_sided_limits_tangent_matches_reverse_mode(setup, setup_one_sided, P):
    """The dynamics kernel with the one-sided look-ahead (its trial solve and end-angle brake)
    against reverse mode, in the same states as the default's; those states do switch the
    one-sided parts on (the accelerations differ from the band's)."""
    band = setup.run(setup.primal.solve_body_dynamics, setup.dynamics_values())["joint_qdd"].numpy()
    one_sided = setup_one_sided.run(setup_one_sided.primal.solve_body_dynamics,
                                    setup_one_sided.dynamics_values())["joint_qdd"].numpy()
    assert np.abs(one_sided - band).max() > 1e-3 * np.abs(band).max()
    test_tangent_matches_reverse_mode(setup_one_sided, "solve_body_dynamics", P)


@pytest.mark.parametrize("name", list(KERNELS))
def test_tangent_matches_finite_differences(setup, name):
    values = _values(setup, name)
    _, ins, outs = KERNELS[name]
    v = _directions(setup, name, values, 1)
    jv = jvp(setup, name, values, v)
    ref = np.concatenate([jv[n][0].ravel() for n in outs])

    def f(eps):
        shifted = dict(values)
        for n in ins:
            shifted[n] = values[n] + eps * v[n][0]
        out = setup.run(getattr(setup.primal, name), shifted)
        return np.concatenate([out[n].numpy().ravel() for n in outs])

    steps = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
    err = [np.linalg.norm((f(e) - f(-e)) / (2 * e) - ref) / np.linalg.norm(ref) for e in steps]
    print(name, "relative FD error per step:", ", ".join(f"{e:.0e}: {x:.1e}" for e, x in zip(steps, err)))
    # truncation regime: eps^2, 100x per decade (>= 50x allowed for the next-order terms)
    assert all(err[i + 1] <= err[i] / 50 for i in range(3)), err
    # at the best step the error is what central differences can give: truncation (eps^2, scaled from
    # eps = 1e-3) plus rounding (1/eps, scaled from eps = 1e-8, where rounding dominates), within 3x
    # (the dynamics' curvature is large: a 25 g forearm's inertia, so its best error is ~1e-9)
    best = min(err[1] * (e / steps[1]) ** 2 + err[-1] * steps[-1] / e for e in steps)
    print(f"best central-difference error expected: {best:.1e}")
    assert min(err) <= 3 * best, (err, best)


def test_limit_state_exercises_the_switches(setup):
    """World 1 really has joints inside the band and past a limit (the switches' active branches)."""
    kinds = {k for w, _, k in setup.band if w == 1}
    assert kinds == {"in the band", "past the limit", "past the cone"}


@pytest.mark.parametrize("variant", ["ball", "no limits"])
def test_transformer_covers_the_shipped_topologies(variant):
    """The other shipped topologies (the ball scenes' extra free body; limits compiled out) transform."""
    if variant == "ball":
        model = build_articulation_model(load_puppet(), ball=BallDescription())
    else:
        model = build_articulation_model(load_puppet(), joint_limits=False)
    source = articulation_tangent_source(model.topology)
    for name in KERNELS:
        assert f"def {name}_tangent(" in source


@pytest.mark.parametrize("line, construct", [
    ("y = joint_q[w, 0] ** wp.float64(2.0)", "binary operator Pow"),
    ("y = wp.sin(joint_q[w, 0])", "no rule for function wp.sin"),
    ("y = wp.normalize(wp.vec3d(joint_q[w, 0], zero, zero))", "no rule for function wp.normalize"),
    ("out[w, 1] += joint_q[w, 0]", "statement kind AugAssign"),
    ("y = wp.float64(joint_q[w, 0])", "wp.float64 of an active value"),
])
def test_unknown_constructs_raise(line, construct):
    source = f'''@wp.kernel
def k(
    # State in:
    joint_q: wp.array2d(dtype=wp.float64),
    # Control:
    h: wp.float64,
    # State out:
    out: wp.array2d(dtype=wp.float64),
):
    w = wp.tid()
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    {line}
    out[w, 0] = wp.float64(1.0)
'''
    with pytest.raises(TangentError, match=re.escape(construct)):
        tangent_kernel_source(source)


def test_tangent_matches_reverse_mode_at_exact_ties(setup):
    """Switches at exact ties take the branch Warp's adjoint takes: world 1 at rest (``max(q, q + h qd)``
    and the ball's ``max(th, th + h n.om)`` tie) with the in-band joints exactly at their upper limit
    (``max(q - upper, 0)`` ties, and the band weight's ``clamp(1, 0, 1)`` sits on its upper bound)."""
    name = "solve_body_dynamics"
    upper = setup.model.dof_limit_upper.numpy()
    q, qd = setup.q.copy(), setup.qd.copy()
    qd[1] = 0.0
    for j in setup.model.topology.joints:
        for k in range(len(j.axes) if j.type in ("hinge", "universal") else 0):
            if (1, j.qd_start + k, "in the band") in setup.band:
                q[1, j.q_start + k] = upper[j.qd_start + k]
    values = dict(setup.dynamics_values(), joint_q=q, joint_qd=qd)
    v = _directions(setup, name, values, 3)
    u = {n: setup.rng.normal(size=np.shape(values[n])) for n in KERNELS[name][2]}
    jv = jvp(setup, name, values, v)
    jtu = vjp(setup, name, values, u)
    for p in range(3):
        terms_f = np.concatenate([(u[n] * jv[n][p]).ravel() for n in KERNELS[name][2]])
        terms_r = np.concatenate([(jtu[n] * v[n][p]).ravel() for n in KERNELS[name][1]])
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        assert abs(terms_f.sum() - terms_r.sum()) <= 1e-10 * scale, p


def test_rollout_jvp_matches_reverse_mode(setup):
    """JVP of a 10-step rollout (``PuppetStepTangent``, P = 3) against the tape's VJP of the same
    rollout of ``SolverArticulation.step``: d(final q, qd) / d(initial q, qd, joint forces)."""
    from dmarionette.articulation.step_tangent import PuppetStepTangent

    m = setup.model
    solver = SolverArticulation(m, optimization_level=0)
    P, steps, dt = 3, 10, 0.01
    jvp_stepper = PuppetStepTangent(solver, P, WORLDS, optimization_level=0)
    rng = np.random.default_rng(5)
    v_q = rng.normal(size=(P, WORLDS, m.q_count))
    v_qd = rng.normal(size=(P, WORLDS, m.qd_count))
    v_f = rng.normal(size=(P, WORLDS, m.qd_count)) * 0.01
    f = setup.joint_f

    states = [m.state(WORLDS, requires_grad=True) for _ in range(steps + 1)]
    control = m.control(WORLDS, requires_grad=True)
    states[0].joint_q.assign(setup.q)
    states[0].joint_qd.assign(setup.qd)
    control.joint_f.assign(f)
    tangents = [jvp_stepper.tangent_state() for _ in range(steps + 1)]
    tangents[0].joint_q.assign(v_q)
    tangents[0].joint_qd.assign(v_qd)
    tan_control = jvp_stepper.control_tangent()
    tan_control.joint_f.assign(v_f)
    for i in range(steps):
        jvp_stepper.step(states[i], tangents[i], states[i + 1], tangents[i + 1], control, tan_control, dt)
    q_end, qd_end = states[-1].joint_q.numpy(), states[-1].joint_qd.numpy()
    jq, jqd = tangents[-1].joint_q.numpy(), tangents[-1].joint_qd.numpy()

    taped = [m.state(WORLDS, requires_grad=True) for _ in range(steps + 1)]
    taped[0].joint_q.assign(setup.q)
    taped[0].joint_qd.assign(setup.qd)
    tape = wp.Tape()
    with tape:
        for i in range(steps):
            solver.step(taped[i], taped[i + 1], control, dt, tape=tape)
    np.testing.assert_array_equal(taped[-1].joint_q.numpy(), q_end)  # the tangent steps' primal is the step
    np.testing.assert_array_equal(taped[-1].joint_qd.numpy(), qd_end)
    u_q, u_qd = rng.normal(size=q_end.shape), rng.normal(size=qd_end.shape)
    tape.backward(grads={taped[-1].joint_q: wp.array(u_q, dtype=wp.float64),
                         taped[-1].joint_qd: wp.array(u_qd, dtype=wp.float64)})
    g_q, g_qd, g_f = (taped[0].joint_q.grad.numpy(), taped[0].joint_qd.grad.numpy(), control.joint_f.grad.numpy())
    for p in range(P):
        terms_f = np.concatenate([(u_q * jq[p]).ravel(), (u_qd * jqd[p]).ravel()])
        terms_r = np.concatenate([(g_q * v_q[p]).ravel(), (g_qd * v_qd[p]).ravel(), (g_f * v_f[p]).ravel()])
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        print(f"rollout p={p}: <u, Jv> = {terms_f.sum():.15e}, <J^T u, v> = {terms_r.sum():.15e}, "
              f"|diff| / scale = {abs(terms_f.sum() - terms_r.sum()) / scale:.1e}")
        assert abs(terms_f.sum() - terms_r.sum()) <= 1e-10 * scale, p
