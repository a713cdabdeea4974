"""JVP of marionette steps (``grad/marionette_tangent``: ``MarionetteTangent``, P = 3) against the
tape's VJP of the same steps of ``SolverMarionette.step``, by the dot-product identity, on the
``hanging`` scene as shipped (30 Hz puppet, 1 kHz strings: 33 string steps per puppet step,
ground contact, joint limits, bar feedback), and on ``chair`` as shipped (the puppet seated: its
ground and chair contacts act, which the hanging puppet's, far above the ground, do not; the
trial step's contact tangents, kept and added into the puppet step's, are checked only here).

Directions in every input the tangent takes: the initial state (the puppet's ``joint_q``,
``joint_qd``; the strings' particles; the previous step's tie forces; the tie target) and each
step's control (tops, bar proxies), and the calibrated constants (each string's tie ``k``,
``k_d`` and segment stiffness ``k_s``). Outputs: the final state and the last step's bar feedback
and reaction. Tolerance: 1e-10 of the sum of the terms' magnitudes, as the kernels' and the
puppet rollout's tests (measured: ~1e-15; a wrong or missing term of any pass is far above it).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.grad.marionette_tangent import MarionetteTangent
from dmarionette.marionette.solver import MarionetteControl, MarionetteModel, MarionetteState, SolverMarionette

P, STEPS = 3, 2
STATE = ("particle_q", "particle_qd", "tie_force", "tie_target")
CONTROL = ("top_q", "bar_q", "bar_qd")


def _numpy(a):
    """``(*shape, components)`` values of an array (a float array: one component)."""
    return a.numpy().reshape(*a.shape, -1)


def _values(a, x):
    """``x`` (``(*shape, components)``) shaped for an array like ``a``."""
    return x.reshape(a.shape + tuple(getattr(a.dtype, "_shape_", ())))


def _direction(a, rng, scale):
    x = rng.normal(size=_numpy(a).shape) * scale
    a.assign(_values(a, x))
    return x


@pytest.mark.parametrize("scene", ["hanging", "chair"])
def test_marionette_step_jvp_matches_reverse_mode(scene):
    model = MarionetteModel(dm.load_scene(scene), optimization_level=0, requires_grad=True)
    assert model.precision == "float64"
    solver = SolverMarionette(model)
    jvp = MarionetteTangent(solver, P, optimization_level=0)
    rng = np.random.default_rng(2)

    s0 = MarionetteState(model, requires_grad=True)
    controls = []
    for i in range(STEPS):
        c = MarionetteControl(model, requires_grad=True)
        c.set_bars(model, i * model.puppet_dt)
        controls.append(c)
    # directions, each input at a scale that keeps the step's linearisation meaningful
    t0 = jvp.tangent_state()
    v = {"joint_q": _direction(t0.puppet.joint_q, rng, 1e-2), "joint_qd": _direction(t0.puppet.joint_qd, rng, 1e-1)}
    for n in STATE:
        v[n] = _direction(getattr(t0, n), rng, 1e-3)
    tcs = [jvp.control_tangent() for _ in range(STEPS)]
    for i, tc in enumerate(tcs):
        for n in CONTROL:
            v[(n, i)] = _direction(getattr(tc, n), rng, 1e-3)

    tk = jvp.constants_tangent()  # the calibrated constants, at 1e-3 of their values
    s = model.strings
    for n, values in (("tie_stiffness", s.string_tie_stiffness), ("tie_damping", s.string_tie_damping),
                      ("string_stiffness", s.string_stiffness)):
        v[n] = rng.normal(size=(P, s.string_count, 1)) * 1e-3 * values.numpy()[None, :, None]
        getattr(tk, n).assign(v[n][..., 0])

    states = [s0] + [MarionetteState(model) for _ in range(STEPS)]
    tangents = [t0] + [jvp.tangent_state() for _ in range(STEPS)]
    for i in range(STEPS):
        jvp.step(states[i], tangents[i], states[i + 1], tangents[i + 1], controls[i], tcs[i], tk)

    taped = [s0] + [MarionetteState(model, requires_grad=True) for _ in range(STEPS)]
    tape = wp.Tape()
    with tape:
        for i in range(STEPS):
            solver.step(taped[i], taped[i + 1], controls[i], tape=tape, workspace=solver.new_workspace())
    end, tend = taped[-1], tangents[-1]
    outputs = {"joint_q": (end.puppet.joint_q, tend.puppet.joint_q),
               "joint_qd": (end.puppet.joint_qd, tend.puppet.joint_qd),
               "particle_q": (end.strings.particle_q, tend.particle_q),
               "particle_qd": (end.strings.particle_qd, tend.particle_qd),
               **{n: (getattr(end, n), getattr(tend, n)) for n in ("tie_force", "tie_target", "bar_feedback",
                                                                     "bar_reaction")}}
    for n, (a, _) in outputs.items():  # the tangent steps' primal is the step
        got = states[-1].puppet if n.startswith("joint") else (states[-1].strings if n.startswith("particle")
                                                               else states[-1])
        np.testing.assert_array_equal(_numpy(a), _numpy(getattr(got, n)), err_msg=n)
    u = {n: rng.normal(size=_numpy(a).shape) for n, (a, _) in outputs.items()}
    tape.backward(grads={a: wp.array(_values(a, u[n]), dtype=a.dtype) for n, (a, _) in outputs.items()})
    g = {"joint_q": _numpy(s0.puppet.joint_q.grad), "joint_qd": _numpy(s0.puppet.joint_qd.grad),
         "particle_q": _numpy(s0.strings.particle_q.grad), "particle_qd": _numpy(s0.strings.particle_qd.grad),
         "tie_force": _numpy(s0.tie_force.grad), "tie_target": _numpy(s0.tie_target.grad),
         **{(n, i): _numpy(getattr(controls[i], n).grad) for n in CONTROL for i in range(STEPS)}}
    # k and k_d act on both sides: the strings' arrays and the puppet's springs (one per tied string)
    pup = model.puppet
    g["tie_stiffness"] = _numpy(s.string_tie_stiffness.grad).copy()
    g["tie_damping"] = _numpy(s.string_tie_damping.grad).copy()
    np.add.at(g["tie_stiffness"], model.spring_string, _numpy(pup.spring_stiffness.grad))
    np.add.at(g["tie_damping"], model.spring_string, _numpy(pup.spring_damping.grad))
    g["string_stiffness"] = _numpy(s.string_stiffness.grad)
    for p in range(P):
        terms_f = np.concatenate([(u[n] * _numpy(t)[p]).ravel() for n, (_, t) in outputs.items()])
        terms_r = np.concatenate([(g[k] * v[k][p]).ravel() for k in g])
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        print(f"p={p}: <u, Jv> = {terms_f.sum():.15e}, <J^T u, v> = {terms_r.sum():.15e}, "
              f"|diff| / scale = {abs(terms_f.sum() - terms_r.sum()) / scale:.1e}")
        assert abs(terms_f.sum() - terms_r.sum()) <= 1e-10 * scale, p
    for n, (_, t) in outputs.items():  # every output has a tangent (nothing checked trivially)
        assert np.any(_numpy(t)), n
