"""Gradients of a batched marionette (``MarionetteGradient`` on ``W`` worlds; issue #16).

The worlds of a batched model do not interact, so the batched engine's outputs and gradients
must be, world by world, those of ``W`` separate one-world engines: the same kernels run the
same arithmetic per (world, string) and per (world, body), so the comparison is exact. The
problem is the gradient tests' (``tests/support/marionette_gradients.py``: the ``hanging``
puppet on its main bar, 10 particles per string, paper rates) over 8 puppet steps, with the
worlds' ``k``, ``k_d``, ``k_s``, bar inputs and initial joint velocities all different, and a
random linear loss per world. Joint limits and smooth ground contact are on in one world set
(the shipped scenes' effects) so that every kernel the shipped scenes run is compared.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from dmarionette.grad.engine import INPUT_FIELDS, OUTPUT_FIELDS, MarionetteGradient
from dmarionette.marionette.solver import MarionetteModel
from tests.support.marionette_gradients import gradient_scene

wp.config.log_level = wp.LOG_WARNING

WORLDS = 3
STEPS = 8  # puppet steps (264 string steps)


def _world_scenes(limits: bool):
    base = gradient_scene(contact=limits)
    if limits:
        base = dataclasses.replace(base, body_effects=dict(base.body_effects, joint_limits=True))
    scenes = []
    for w in range(WORLDS):
        strings = tuple(dataclasses.replace(s, tie_stiffness=s.tie_stiffness * (1.0 + 0.3 * w),
                                            tie_damping=s.tie_damping * (1.0 - 0.2 * w),
                                            stiffness=s.stiffness * (1.0 + 0.1 * w)) for s in base.strings)
        scenes.append(dataclasses.replace(base, strings=strings))
    return scenes


def _inputs(engine: MarionetteGradient, world_inputs, rng):
    """Each world's scene inputs with its own bar wiggle and initial joint velocities."""
    out = []
    for inputs in world_inputs:
        t = inputs.top_q.shape[0]
        wiggle = 0.01 * np.sin(np.linspace(0.0, rng.uniform(2.0, 6.0), t))[:, None, None] * rng.normal(size=(1, 1, 3))
        out.append(dataclasses.replace(inputs, top_q=inputs.top_q + wiggle, bar_q=inputs.bar_q + wiggle[:, :1],
                                       joint_qd0=0.05 * rng.normal(size=inputs.joint_qd0.shape)))
    return out


@pytest.fixture(scope="module", params=[False, True], ids=["limits_off", "limits_and_contact_on"])
def engines(request):
    scenes = _world_scenes(request.param)
    batched = MarionetteGradient(MarionetteModel.from_scenes(scenes, optimization_level=0, requires_grad=True),
                                 STEPS, checkpoint_steps=3)
    single = [MarionetteGradient(MarionetteModel(s, optimization_level=0, requires_grad=True), STEPS,
                                 checkpoint_steps=3) for s in scenes]
    return batched, single


def test_the_batched_forward_and_gradient_equal_the_per_world_ones(engines):
    batched, single = engines
    rng = np.random.default_rng(16)
    scene_inputs = batched.scene_inputs()
    assert isinstance(scene_inputs, list) and len(scene_inputs) == WORLDS
    for w, (inputs, engine) in enumerate(zip(scene_inputs, single)):
        own = engine.scene_inputs()
        for name in INPUT_FIELDS:  # each world's scene inputs are its own scene's
            assert np.array_equal(getattr(inputs, name), getattr(own, name)), (w, name)
    inputs = _inputs(batched, scene_inputs, rng)
    cotangents = [{name: rng.normal(size=shape) for name, shape in batched.output_shapes.items()}
                  for _ in range(WORLDS)]
    outputs = batched.forward(inputs)
    grads = batched.backward(cotangents)
    joint_q = []
    for w, engine in enumerate(single):
        want = engine.forward(inputs[w])
        for name in OUTPUT_FIELDS:
            assert np.array_equal(getattr(outputs[w], name), getattr(want, name)), (w, name)
        want_grad = engine.backward(cotangents[w])
        for name in INPUT_FIELDS:
            got, expected = getattr(grads[w], name), getattr(want_grad, name)
            assert got.shape == expected.shape, (w, name)
            assert np.any(expected != 0.0), (w, name)  # every input reaches the loss
            assert np.array_equal(got, expected), (w, name, np.max(np.abs(got - expected)))
        joint_q.append(outputs[w].joint_q)
    # The worlds really differ (different constants and inputs give different motions).
    assert min(np.max(np.abs(joint_q[a] - joint_q[b])) for a in range(WORLDS) for b in range(a)) > 1e-4


def test_a_batched_engine_wants_one_input_per_world(engines):
    batched, _ = engines
    inputs = batched.scene_inputs()
    with pytest.raises(ValueError, match="expected a list of 3"):
        batched.forward(inputs[:2])
    with pytest.raises(ValueError, match="expected a list of 3"):
        batched.forward(inputs[0])
    bad = dataclasses.replace(inputs[1], tie_damping=-np.ones_like(inputs[1].tie_damping))
    with pytest.raises(ValueError, match="world 1: RolloutInputs.tie_damping"):
        batched.forward([inputs[0], bad, inputs[2]])
