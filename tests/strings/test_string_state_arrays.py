"""``StringStateArrays``, ``StringControlArrays`` (``kernels/string_state_arrays``): a state's and a
control's arrays as one kernel argument each hold the objects' own arrays, are built once and rebuilt
when an array or its gradient is replaced (a captured launch checks the gradient pointers a struct
holds), and the step's gradients reach the state's and the control's ``.grad`` through them."""

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.string_state_arrays import CONTROL_FIELDS, STATE_FIELDS
from dmarionette.strings.solver import SolverStringImplicit
from tests.support.strings import ALL_ON, make_model, taped_rollout, three_strings, wiggled_controls


def test_the_structs_hold_the_objects_own_arrays_and_are_built_once():
    model = make_model(three_strings(), ALL_ON)
    state, control = model.state(), model.control()
    for owner, fields in ((state, STATE_FIELDS), (control, CONTROL_FIELDS)):
        arrays = owner.arrays
        for name in fields:
            assert getattr(arrays, name) is getattr(owner, name), name
        assert owner.arrays is arrays  # cached


def test_a_replaced_array_or_gradient_rebuilds_the_struct():
    model = make_model(three_strings(), ALL_ON)
    state, control = model.state(), model.control()
    before = state.arrays
    state.particle_qd = wp.zeros_like(state.particle_qd)
    assert state.arrays is not before and state.arrays.particle_qd is state.particle_qd
    before = control.arrays
    control.tie_q.requires_grad = True  # a new .grad: the struct's gradient pointer would be stale
    assert control.arrays is not before and control.arrays.tie_q is control.tie_q


def test_a_captured_step_after_requires_grad_changes():
    """A captured launch checks the gradient pointers of its struct arguments: the control's struct,
    rebuilt after ``requires_grad`` changed, passes (the taped five passes, which take it)."""
    model = make_model(three_strings(), ALL_ON, requires_grad=True)
    solver = SolverStringImplicit(model)
    solver.hand_adjoint = False
    a, b, control = model.state(), model.state(), model.control()
    solver.step(a, b, control, 1e-3, tape=wp.Tape())
    control.top_q.requires_grad = False  # its gradient freed
    with wp.ScopedCapture(device=model.device):
        solver.step(a, b, control, 1e-3, tape=wp.Tape())


@pytest.mark.parametrize("hand_adjoint", [False, True])
def test_taped_gradients_reach_the_state_and_the_control(hand_adjoint):
    """Warp's tape (the five passes, mirroring the structs) and the hand-written adjoint (its
    gradient structs) accumulate into the initial state's and every control's ``.grad``."""
    model = make_model(three_strings(), ALL_ON, requires_grad=True)
    solver = SolverStringImplicit(model)
    solver.hand_adjoint = hand_adjoint
    steps, dt = 6, 1e-3
    states = [model.state() for _ in range(steps + 1)]
    controls = wiggled_controls(model, steps, dt)
    tape, loss = taped_rollout(solver, states, controls, dt, np.random.default_rng(3))
    tape.backward(loss)
    for name in ("particle_q", "particle_qd"):
        assert np.any(getattr(states[0], name).grad.numpy() != 0.0), name
    for name in ("top_q", "tie_q", "tie_qd"):
        assert all(np.any(getattr(c, name).grad.numpy() != 0.0) for c in controls), name
