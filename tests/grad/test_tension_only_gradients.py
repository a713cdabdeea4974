"""Gradients through tension-only strings (``[effects] tension_only = true``, ``MarionetteGradient``).

The problem is ``test_marionette_gradients.py``'s (the ``hanging`` puppet on its main bar,
four pre-tensioned strings of 10 particles, joint limits off, no contact), with the puppet
at the string rate (``puppet_hz = string_hz = 1 kHz``, the only rate ``settings_check``
allows for tension-only strings), 0.2 s (200 puppet steps, ``C = 15``). The strings stay
taut (checked: every segment stretched, every segment in the active set at every step),
away from the tension-only spring's kink at the rest length, so the loss is smooth and the
finite differences (same method, steps and tolerance as there: 1e-5) test the gradient.
On such a problem the tension-only spring is the printed one (same force, same Jacobian:
``string_terms.compute_string_spring``), so its gradient equals the printed spring's.

A second problem has slack strings (the ``hanging`` scene's hand strings, still hand bar):
segments go slack and snap taut within a step, where the recorded pass (the active set
held fixed, the system assembled from scratch) and the untaped solve (the snapped
segment's block added in place) differ by rounding; the taped step integrates the
unrecorded pass's ``dv`` (``SolverStringImplicit.apply_active_set_dv``), so the taped step
still ends bit for bit where the plain one did. No finite differences there: the step has kinks.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.grad.engine import INPUT_FIELDS, OUTPUT_FIELDS, MarionetteGradient
from dmarionette.marionette.rollout import simulate_marionette
from tests.support.marionette_gradients import Problem, gradient_scene, string_margins

wp.config.log_level = wp.LOG_WARNING

STEPS = 200       # 0.2 s with the puppet at the string rate
SLACK_STEPS = 60  # the slack problem: 60 ms


def _at_string_rate(scene, tension_only: bool):
    return dataclasses.replace(scene, puppet_hz=scene.string_hz,
                               effects=dataclasses.replace(scene.effects, tension_only=tension_only))


@pytest.fixture(scope="module")
def tension_only():
    return Problem(False, _at_string_rate(gradient_scene(False), True), STEPS, checkpoint_steps=None)


@pytest.fixture(scope="module")
def printed():
    return Problem(False, _at_string_rate(gradient_scene(False), False), STEPS, checkpoint_steps=None)


def _inactive_segments(engine: MarionetteGradient) -> int:
    """Segments out of the active set over the first taped segment's puppet steps of the
    engine's rollout (the scene's inputs; a plain run, whose active sets the taped steps
    use), not counting each string's last particle (it starts no segment)."""
    model = engine.model
    solver = SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    last = model.strings.string_start_np[1:] - 1
    active_set = solver.workspace.string_workspaces[0].segment_active
    count = 0
    for p in range(engine.checkpoint_steps):
        control.set_bars(model, p * model.puppet_dt)
        solver.begin_step(a, b)
        for j in range(model.substeps):
            solver.step_string(a, b, control, j)
            active = active_set.numpy().copy()
            active[last] = 1
            count += int(np.sum(active == 0))
        solver.end_step(a, b)
        a, b = b, a
    return count


def test_the_strings_stay_taut_and_every_segment_active(tension_only):
    """Measured: smallest segment stretch 1.2e-3, every string taut, no segment inactive."""
    assert tension_only.engine.checkpoint_steps == 15 and tension_only.model.substeps == 1
    smallest, taut = string_margins(tension_only.model, STEPS)
    print(f"smallest segment stretch {smallest:.2e}, taut {taut}")
    assert taut
    assert smallest > 1e-4
    assert _inactive_segments(tension_only.engine) == 0


def test_tension_only_gradients_match_finite_differences(tension_only):
    tension_only.check(1e-5)


def test_tension_only_gradient_equals_the_printed_springs(tension_only, printed):
    """Measured: equal exactly (taut segments: the same floating-point operations)."""
    assert printed.model.strings.effects.tension_only is False
    for name in OUTPUT_FIELDS:
        want = getattr(printed.outputs, name)
        np.testing.assert_allclose(getattr(tension_only.outputs, name), want, rtol=0.0,
                                   atol=1e-12 * max(1.0, np.abs(want).max()), err_msg=name)
    for name in INPUT_FIELDS:
        want = getattr(printed.grads, name)
        np.testing.assert_allclose(getattr(tension_only.grads, name), want, rtol=0.0,
                                   atol=1e-12 * max(np.abs(want).max(), 1e-300), err_msg=name)


@pytest.fixture(scope="module")
def slack_model():
    scene = dm.load_scene("hanging")
    strings = tuple(dataclasses.replace(s, particle_count=10) for s in scene.strings)
    scene = dataclasses.replace(scene, strings=strings, body_effects=dict(scene.body_effects, joint_limits=False),
                                contact=dict(scene.contact, smooth=True))
    # Strings 5 mm longer than bar -> body point: they start slack (every segment compressed,
    # out of the active set) and snap taut as the puppet drops onto them.
    straight = MarionetteModel(scene, optimization_level=0)
    strings = tuple(dataclasses.replace(s, length=straight.strings.specs[i].length + 0.005)
                    for i, s in enumerate(scene.strings))
    scene = dataclasses.replace(scene, strings=strings)
    return MarionetteModel(_at_string_rate(scene, True), optimization_level=0, requires_grad=True)


def test_slack_strings_snapping_taut_replay_exactly(slack_model):
    """Segments leave and rejoin the active set: the engine's forward is the ordinary
    rollout's, the taped steps end exactly where the plain ones did, the gradients are
    finite. (Without the copy of the unrecorded ``dv`` the taped steps differ, measured:
    by 7e-18 m within the first 8 steps.)"""
    m = slack_model
    engine = MarionetteGradient(m, SLACK_STEPS)
    inputs = engine.scene_inputs()
    out = engine.forward(inputs)
    ref = simulate_marionette(m, SLACK_STEPS * m.puppet_dt, progress=False, frame_hz=1.0 / m.puppet_dt)
    np.testing.assert_array_equal(out.joint_q, ref.joint_q)
    np.testing.assert_array_equal(out.tie_force, ref.tie_force)
    rng = np.random.default_rng(1)
    weights = {k: rng.normal(size=s) for k, s in engine.output_shapes.items()}
    grads = engine.backward(weights)
    inactive = _inactive_segments(engine)
    print(f"inactive segment-steps in the first {engine.checkpoint_steps} steps: {inactive}")
    assert inactive > 0
    for name in INPUT_FIELDS:
        assert np.all(np.isfinite(getattr(grads, name))), name
    assert np.abs(grads.tie_stiffness).max() > 0.0

    solver = SolverMarionette(m)
    plain = [m.state(), m.state()]
    taped = [m.state(requires_grad=True) for _ in range(engine.checkpoint_steps + 1)]
    control = m.control()
    tape = wp.Tape()
    for p in range(engine.checkpoint_steps):
        control.set_bars(m, p * m.puppet_dt)
        solver.step(plain[p % 2], plain[(p + 1) % 2], control)
        with tape:
            solver.step(taped[p], taped[p + 1], control, tape=tape)
        end = plain[(p + 1) % 2]
        np.testing.assert_array_equal(taped[p + 1].strings.particle_q.numpy(), end.strings.particle_q.numpy())
        np.testing.assert_array_equal(taped[p + 1].puppet.joint_q.numpy(), end.puppet.joint_q.numpy())
