"""Gradients of whole marionette rollouts (``MarionetteGradient``, ``fitting.marionette_rollout``).

The problem: the ``hanging`` scene's puppet on its main bar (head, back and knee strings;
the hand strings and hand bar are left out: with the hand bar still, the hands bounce on
their strings and the bottom segments pass through slack, a kink of the step, see
``string_terms.compute_string_spring``), 10 particles per string, the paper's rates
(strings 1 kHz, puppet 30 Hz: 33 string steps per puppet step), a 1 s rollout (30 puppet
steps, 990 string steps), joint limits off. The strings are shortened by ``F / k`` with
``F = (3, 2, 2, 2) N`` so that they start under tension (9 N against the puppet's 7.4 N;
with (6, 4, 4, 4) N the puppet, pulled up hard at the start, bounced and a segment passed
through slack once the coupling's trial step passed the strings' pull on at once): then no
segment goes slack and every string stays taut over the rollout (both checked below), and the loss is smooth over
the finite-difference steps. Puppet kernels are compiled at ``optimization_level=0``.

The loss is a fixed random linear function of every output. Each gradient is checked as
directional derivatives ``g . u`` against central differences, Richardson-extrapolated
from steps ``e`` and ``e/2`` (truncation ``O(e^4)``). The steps come from a sweep over
``e = 1e-3 ... 1e-7`` of the input (no contact): for the bar inputs and the puppet's initial
state (random directions) ``e = 1e-6`` m, m/s, rad agrees to 1e-9; for the strings' initial
particle positions and velocities (three random directions each) ``e = 1e-5`` m (agrees
to 1e-8 here, 2e-9 in ``test_tension_only_gradients.py``; at 1e-3 m a segment's 0.1 mm
pre-stretch is undone and the differences are off by 0.3 at the string rate) and
``e = 1e-2`` m/s (the velocities' effect on the loss is small, so their differences are
rounding-limited: with the puppet at the string rate one direction's derivative is 1e-4 of
the others' and agrees to 1e-4 at 1e-3 m/s, 4e-6 at 1e-2; the others to 2e-8); for the string constants
(one string at a time) the differences are rounding-limited at small steps (k_d: 1e-5 at
``e = 1e-5 k_d``, 2e-4 at 1e-7) and agree to 1e-8 at ``e = 1e-3`` of the value, which is
used. The tolerances (1e-5 without contact, 1e-3 with the smoothed contact) therefore test
the gradient, not the differences.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from dmarionette.marionette.solver import MarionetteModel
from dmarionette.grad.engine import (INPUT_FIELDS, OPTIONAL_INPUT_FIELDS, OUTPUT_FIELDS, MarionetteGradient,
                                         SEGMENT_STRING_STEPS, RolloutInputs)
from dmarionette.marionette.rollout import simulate_marionette
from tests.support.marionette_gradients import CONTACT_GROUND, PUPPET_STEPS, Problem, string_margins

wp.config.log_level = wp.LOG_WARNING


@pytest.fixture(scope="module")
def smooth():
    return Problem(contact=False)


@pytest.fixture(scope="module")
def contact():
    return Problem(contact=True)


def test_the_strings_stay_taut_so_the_loss_is_smooth(smooth, contact):
    """No segment passes through slack and no string goes slack (measured: >= 6.7e-4)."""
    for problem in (smooth, contact):
        problem.engine.forward(problem.engine.scene_inputs())
        smallest, taut = string_margins(problem.model)
        print(f"smallest segment stretch {smallest:.2e}, taut {taut}")
        assert taut
        assert smallest > 1e-4


def test_forward_equals_the_ordinary_rollout(smooth):
    """For the scene's own inputs the engine's outputs are ``simulate_marionette``'s (same kernels)."""
    e = smooth.engine
    out = e.forward(e.scene_inputs())
    m = smooth.model
    ref = simulate_marionette(m, PUPPET_STEPS * m.puppet_dt, progress=False, frame_hz=1.0 / m.puppet_dt)
    assert ref.frame_steps == m.substeps and len(ref.joint_q) == PUPPET_STEPS + 1
    for name, want in (("joint_q", ref.joint_q), ("body_pos", ref.body_pos), ("body_rot", ref.body_rot),
                       ("tie_force", ref.tie_force), ("bar_feedback", ref.bar_feedback),
                       ("bar_reaction", ref.bar_reaction)):
        got = getattr(out, name)
        assert got.shape == want.shape, name
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12 * max(1.0, np.abs(want).max()), err_msg=name)
    points = np.stack([m.eval_points(_puppet_at(m, q))[0] for q in ref.joint_q[[0, -1]]])
    np.testing.assert_allclose(out.point_pos[[0, -1]], points, rtol=0.0, atol=1e-12)


def _rotate(quat, v):
    """Rotates vectors ``v`` (N, 3) by unit quaternions ``(x, y, z, w)`` (N, 4)."""
    u, w = quat[:, :3], quat[:, 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _puppet_at(model, q):
    state = model.puppet.state()
    state.joint_q.assign(q[None])
    return state


def test_gradients_without_contact_match_finite_differences(smooth):
    smooth.check(1e-5)


def test_gradients_with_smoothed_contact_match_finite_differences(contact, smooth):
    """The feet come down on the ground: without contact the lowest contact point would go
    more than 1 cm below it; with it, it rests within 4 softplus widths of it for the last
    0.6 s (the smooth contact's force carries the feet). The gradients still match."""
    m = contact.model
    cs = m.puppet_solver.contacts
    body, local = cs.point_body.numpy(), cs.point_local.numpy()

    def lowest(out):
        return np.array([np.min((pos[body] + _rotate(rot[body], local))[:, 1])
                         for pos, rot in zip(out.body_pos, out.body_rot)])

    with_contact = lowest(contact.engine.forward(contact.engine.scene_inputs()))
    without = lowest(smooth.engine.forward(smooth.engine.scene_inputs()))
    delta = m.scene.contact["smooth_distance"]
    print(f"lowest point - ground: without contact {without.min() - CONTACT_GROUND:.4f} m, with contact "
          f"{with_contact[-18:].min() - CONTACT_GROUND:.4f} .. {with_contact[-18:].max() - CONTACT_GROUND:.4f} m")
    assert with_contact[0] - CONTACT_GROUND > 0.015  # the feet start 2 cm above it
    assert without.min() < CONTACT_GROUND - 0.01
    assert np.all(with_contact[-18:] - CONTACT_GROUND < 4.0 * delta), with_contact
    contact.check(1e-3)


def test_checkpointing_does_not_change_the_gradient(smooth):
    """``checkpoint_steps = puppet_steps`` (one taped segment) against 8 segments (7 of 4 steps, one of 2),
    against the default (``ceil(sqrt(30)) = 6`` capped at ``SEGMENT_STRING_STEPS // substeps``: 6 segments of
    5 at 33 substeps), and without graph capture."""
    assert len(smooth.engine.segments) == 8 and smooth.engine.segments[-1] == (28, 30)
    default = MarionetteGradient(smooth.model, PUPPET_STEPS)
    assert smooth.model.substeps == 33 and SEGMENT_STRING_STEPS // 33 == 5
    assert default.checkpoint_steps == 5 and len(default.segments) == 6
    whole = MarionetteGradient(smooth.model, PUPPET_STEPS, checkpoint_steps=PUPPET_STEPS)
    assert len(whole.segments) == 1
    plain = MarionetteGradient(smooth.model, PUPPET_STEPS, checkpoint_steps=4, capture=False)
    for engine in (whole, default, plain):
        engine.forward(smooth.inputs)
        g = engine.backward(smooth.weights)
        for name in INPUT_FIELDS:
            want = getattr(smooth.grads, name)
            np.testing.assert_allclose(getattr(g, name), want, rtol=0.0, atol=1e-12 * np.abs(want).max(),
                                       err_msg=name)
    # Engines share the model's constant arrays: a backward after another engine's forward
    # (other constants) still differentiates its own forward.
    smooth.engine.forward(smooth.inputs)
    whole.forward(dataclasses.replace(smooth.inputs, tie_stiffness=1.05 * smooth.inputs.tie_stiffness))
    g = smooth.engine.backward(smooth.weights)
    np.testing.assert_allclose(g.tie_damping, smooth.grads.tie_damping, rtol=0.0,
                               atol=1e-12 * np.abs(smooth.grads.tie_damping).max())


def test_jax_wrapper_gradient_equals_the_engine(smooth):
    import jax
    import jax.numpy as jnp

    from fitting import marionette_rollout

    f = marionette_rollout(smooth.engine)
    weights = {k: jnp.asarray(w) for k, w in smooth.weights.items()}

    def loss(x):
        out = f(x)
        return sum(jnp.sum(w * out[k]) for k, w in weights.items())

    x = {k: jnp.asarray(getattr(smooth.inputs, k)) for k in INPUT_FIELDS}
    grads = jax.jit(jax.grad(loss))(x)
    value, grads_vg = jax.value_and_grad(loss)(x)
    for name in INPUT_FIELDS:
        want = getattr(smooth.grads, name)
        for got in (grads[name], grads_vg[name]):
            np.testing.assert_allclose(np.asarray(got), want, rtol=0.0, atol=1e-12 * np.abs(want).max(),
                                       err_msg=name)
    np.testing.assert_allclose(float(value), smooth.loss(smooth.inputs), rtol=1e-12)
    out, vjp = jax.vjp(f, x)
    np.testing.assert_array_equal(np.asarray(out["joint_q"]), smooth.outputs.joint_q)
    (pulled,) = vjp({k: jnp.asarray(w) for k, w in smooth.weights.items()})
    np.testing.assert_allclose(np.asarray(pulled["tie_stiffness"]), smooth.grads.tie_stiffness, rtol=1e-12)
    # A direct engine.forward for other inputs between the wrapped forward and its reverse pass:
    # the wrapper must notice and differentiate its own inputs again.
    other = dataclasses.replace(smooth.inputs, tie_stiffness=1.1 * smooth.inputs.tie_stiffness)
    smooth.engine.forward(other)
    (pulled,) = vjp({k: jnp.asarray(w) for k, w in smooth.weights.items()})
    np.testing.assert_allclose(np.asarray(pulled["tie_stiffness"]), smooth.grads.tie_stiffness, rtol=1e-12)

    # A reverse-mode Jacobian (Gauss-Newton's): three residuals w.r.t. the tie stiffnesses, the
    # other inputs closed over (concrete arrays inside a jit).
    def residuals(k):
        return f({**x, "tie_stiffness": k})["joint_q"][-1, :3]

    jacobian = np.asarray(jax.jit(jax.jacrev(residuals))(x["tie_stiffness"]))
    smooth.engine.forward(smooth.inputs)
    for row in range(3):
        cot = np.zeros(smooth.engine.output_shapes["joint_q"])
        cot[-1, row] = 1.0
        want = smooth.engine.backward({"joint_q": cot}).tie_stiffness
        np.testing.assert_allclose(jacobian[row], want, rtol=0.0, atol=1e-12 * np.abs(want).max())


def test_bad_inputs_are_refused(smooth):
    e = smooth.engine
    good = smooth.inputs
    t, s = e.input_shapes["top_q"][:2]
    with pytest.raises(ValueError, match=r"RolloutInputs.top_q: got shape \(989, 4, 3\); expected \(990, 4, 3\)"):
        e.forward(dataclasses.replace(good, top_q=good.top_q[1:]))
    bad = good.bar_qd.copy()
    bad[7, 0, 1] = np.nan
    with pytest.raises(ValueError, match=r"RolloutInputs.bar_qd: non-finite value nan at index \(7, 0, 1\)"):
        e.forward(dataclasses.replace(good, bar_qd=bad))
    with pytest.raises(ValueError, match=r"tie_stiffness\[2\] \(string 'knee_left'\): got -1.0; expected > 0"):
        e.forward(dataclasses.replace(good, tie_stiffness=np.array([300.0, 300.0, -1.0, 300.0])))
    with pytest.raises(ValueError, match=r"RolloutInputs.joint_qd0: got shape \(3,\)"):
        e.forward(dataclasses.replace(good, joint_qd0=np.zeros(3)))
    with pytest.raises(ValueError, match=r"RolloutInputs.particle_q0: got shape \(39, 3\); expected \(40, 3\)"):
        e.forward(dataclasses.replace(good, particle_q0=good.particle_q0[1:]))
    # The strings' initial state left out (None, as callers written before it was an input): the rest state.
    legacy = RolloutInputs(*(getattr(good, k) for k in INPUT_FIELDS[:8]))
    assert legacy.particle_q0 is None and legacy.particle_qd0 is None
    np.testing.assert_array_equal(e.forward(legacy).joint_q, smooth.outputs.joint_q)
    e.forward(good)
    with pytest.raises(ValueError, match=r"cotangents: unknown output 'particle_q'"):
        e.backward({"particle_q": np.zeros(3)})
    with pytest.raises(ValueError, match=r"cotangents\['joint_q'\]: got shape \(30, 25\); expected \(31, 25\)"):
        e.backward({"joint_q": np.zeros((30, 25))})
    with pytest.raises(ValueError, match="without gradients"):
        MarionetteGradient(MarionetteModel(smooth.model.scene, optimization_level=0), 3)
    with pytest.raises(ValueError, match="checkpoint_steps: got 0"):
        MarionetteGradient(smooth.model, 3, checkpoint_steps=0)

    import jax
    import jax.numpy as jnp

    from fitting import marionette_rollout

    f = marionette_rollout(e)
    x = {k: jnp.asarray(getattr(good, k)) for k in INPUT_FIELDS}
    with pytest.raises(ValueError, match=r"inputs\['bar_q'\]: got shape \(990, 2, 3\)"):
        f({**x, "bar_q": jnp.zeros((t, 2, 3))})
    with pytest.raises(ValueError, match=r"inputs\['tie_damping'\]: contains NaN"):
        f({**x, "tie_damping": x["tie_damping"].at[1].set(jnp.nan)})
    with pytest.raises(Exception, match=r"RolloutInputs.tie_damping: non-finite value nan at index \(1,\)"):
        jax.jit(f)({**x, "tie_damping": x["tie_damping"].at[1].set(jnp.nan)})
    with pytest.raises(ValueError, match=r"missing \['joint_q0'\]"):
        f({k: v for k, v in x.items() if k != "joint_q0"})
    without = f({k: v for k, v in x.items() if k not in OPTIONAL_INPUT_FIELDS})  # the rest state
    np.testing.assert_array_equal(np.asarray(without["joint_q"]), smooth.outputs.joint_q)
    assert set(OUTPUT_FIELDS) == set(f(x))
    assert s == 4
