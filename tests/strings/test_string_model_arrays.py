"""``StringModelArrays`` (``kernels/string_model_arrays``): the string model's constants as one kernel
argument hold the model's own arrays, their gradients reach those arrays' ``.grad`` through Warp's
tape, and the struct is rebuilt after an array's ``requires_grad`` changes (a captured launch checks
the gradient pointers it holds)."""

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.string_model_arrays import ARRAY_FIELDS, DIFFERENTIABLE_FIELDS
from dmarionette.strings.solver import SolverStringImplicit
from tests.support.strings import ALL_ON, make_model, taped_rollout, three_strings, wiggled_controls


def test_the_struct_holds_the_models_own_arrays():
    model = make_model(three_strings(), ALL_ON)
    for name in ARRAY_FIELDS:
        assert getattr(model.arrays, name) is getattr(model, name), name
    assert np.array_equal(np.asarray(model.arrays.gravity), np.asarray(model.gravity))
    assert model.arrays.ground_height == model.ground_height


@pytest.mark.parametrize("hand_adjoint", [False, True])
def test_taped_gradients_reach_every_differentiable_array(hand_adjoint):
    """Warp's tape (the five passes, ``hand_adjoint = False``) and the hand-written adjoint (its
    ``model_grad`` struct) both accumulate into each constant's ``.grad``: none stays zero."""
    model = make_model(three_strings(), ALL_ON, requires_grad=True)
    solver = SolverStringImplicit(model)
    solver.hand_adjoint = hand_adjoint
    steps, dt = 6, 1e-3
    states = [model.state() for _ in range(steps + 1)]
    tape, loss = taped_rollout(solver, states, wiggled_controls(model, steps, dt), dt, np.random.default_rng(3))
    tape.backward(loss)
    for name in DIFFERENTIABLE_FIELDS:
        assert np.any(getattr(model, name).grad.numpy() != 0.0), name


def test_a_captured_step_needs_the_struct_rebuilt_after_requires_grad_changes():
    model = make_model(three_strings(), ALL_ON, requires_grad=True)
    solver = SolverStringImplicit(model)
    a, b, control = model.state(), model.state(), model.control()

    def capture():
        solver.step(a, b, control, 1e-3)
        with wp.ScopedCapture(device=model.device):
            solver.step(a, b, control, 1e-3)

    model.string_stiffness.requires_grad = False  # its gradient freed: the struct still points at it
    with pytest.raises(RuntimeError, match="gradient"):
        capture()
    model.refresh_arrays()
    capture()
