"""The string step's hand-written adjoint (``kernels/string_step_adjoint``) against the taped five passes.

Both differentiate the same function (the one-launch step and the five passes give the same
forward bits, ``tests/strings/test_string_step_schedules.py``): the taped passes with Warp's
automatic adjoints (and the solve's hand-written one), the new kernel by hand. So every
gradient must agree to rounding, in every input group the step has: the initial positions and
velocities, the tops, the tie targets and their velocities, and every constant (mass, ``k_s``,
rest length, ``k_f``, ``k_air``, ground repulsion, absorption and friction, tie ``k``, ``k_d`` and
the ``tied`` flag). The problems switch every effect on, with particles on the ground, a
string tied to a moving body point and a slack segment (the clamped geometric stiffness), with
the printed springs and with the tension-only ones.

Tolerance: 1e-10 of each group's largest gradient. The two adjoints sum the same products in
another order; measured differences are 1e-16 to 3e-14 of the group's scale over 400 steps
(printed by the tests).

The marionette engine (strings, puppet, coupling, feedback) is checked the same way on the
shipped ``chair_scripted`` scene (10 particles per string, smooth contact, 1/3 s).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tests.support.strings import (ALL_ON, make_model, rollout_gradients, taped_rollout, three_strings,
                                  wiggled_controls)
from tests.support.marionette_gradients import smooth_scene

from dmarionette.grad.engine import MarionetteGradient
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.strings.solver import SolverStringImplicit

STEPS = 400
DT = 1e-3
TOLERANCE = 1e-10


def _model(tension_only: bool):
    """Three strings: one swinging onto the ground, one tied to a circling point, one slack at the top."""
    return make_model(
        three_strings(),
        effects=dataclasses.replace(ALL_ON, tension_only=tension_only), requires_grad=True)


def _string_gradients(hand: bool, tension_only: bool) -> dict[str, np.ndarray]:
    model = _model(tension_only)
    solver = SolverStringImplicit(model)
    solver.hand_adjoint = hand
    controls = wiggled_controls(model, STEPS, DT)
    states = [model.state() for _ in range(STEPS + 1)]
    tape, loss = taped_rollout(solver, states, controls, DT, np.random.default_rng(11))
    # The problem reaches what it is meant to: particles below the ground, a compressed segment.
    q = np.array([s.particle_q.numpy() for s in states[::20]])
    assert np.min(q[:, :9, 1]) < 0.0
    seg = np.linalg.norm(np.diff(q[:, 16:22], axis=1), axis=-1)
    assert np.min(seg) < 0.35 / 5
    tape.backward(loss)
    return rollout_gradients(model, states, controls)


@pytest.mark.parametrize("tension_only", [False, True], ids=["printed", "tension-only"])
def test_hand_adjoint_equals_the_taped_passes_on_strings(tension_only):
    """Tension-only springs: both differentiate the step with its active set held fixed (the
    slack string's segments are inactive, or forced by the step's end; ``strings/solver.py``)."""
    hand, taped = _string_gradients(True, tension_only), _string_gradients(False, tension_only)
    for name in taped:
        scale = np.max(np.abs(taped[name]))
        assert scale > 0.0, name  # every group is exercised
        gap = np.max(np.abs(hand[name] - taped[name])) / scale
        print(f"{name}: {gap:.1e} of {scale:.2e}")
        assert gap < TOLERANCE, name


def _chair_gradients(hand: bool) -> dict[str, np.ndarray]:
    model = MarionetteModel(smooth_scene("chair_scripted", 10), optimization_level=0, requires_grad=True)
    model.string_solver.hand_adjoint = hand  # before the engine plans its taped segment
    engine = MarionetteGradient(model, 10)
    rng = np.random.default_rng(3)
    weights = {k: rng.normal(size=s) for k, s in engine.output_shapes.items()}
    engine.forward(engine.scene_inputs())
    grads = engine.backward(weights)
    return {f.name: np.asarray(getattr(grads, f.name)) for f in dataclasses.fields(grads)}


def test_hand_adjoint_equals_the_taped_passes_in_the_marionette():
    hand, taped = _chair_gradients(True), _chair_gradients(False)
    for name in taped:
        scale = np.max(np.abs(taped[name]))
        if scale == 0.0:
            continue
        gap = np.max(np.abs(hand[name] - taped[name])) / scale
        print(f"{name}: {gap:.1e} of {scale:.2e}")
        assert gap < TOLERANCE, name
