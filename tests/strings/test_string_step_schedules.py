"""The two schedules of the implicit string step compute the same numbers, bit for bit.

A printed-spring step runs as one launch per string (``kernels/string_step``,
``integrate_string_implicit``), on a tape too (with its hand-written adjoint); every
tension-only step, and a taped step with ``hand_adjoint = False``, runs the five passes
(spring, system, solve, integrate, tie force). Both call the same ``@wp.func``\\ s in the
same order, so a taped re-run of a rollout (the gradient engine's backward pass) ends exactly
where the plain run did. Checked on a hard case: strings swung fast, lowered onto the ground,
their ties moving, every effect on, float64 and float32, chains of 2 to 50 particles.
"""

import functools

import numpy as np
import pytest
import warp as wp
from tests.support.strings import make_model, spec, step_in_lockstep, swung_controls

from dmarionette.strings.model import StringEffects
from dmarionette.strings.solver import SolverStringImplicit

wp.config.log_level = wp.LOG_WARNING


def _model(precision: str):
    strings = [
        spec(particle_count=30, top=(0.0, 0.5, 0.0), bottom=(0.0, 0.05, 0.0), length=0.5, load_mass=0.02,
             internal_friction=0.3, air_drag=0.05, ground_stiffness=2000.0, ground_absorption=5.0,
             ground_friction=2.0),
        spec(particle_count=7, top=(0.3, 0.4, 0.0), bottom=(0.6, 0.4, 0.2), length=0.45),
        spec(particle_count=50, top=(-0.3, 0.6, 0.1), bottom=(-0.3, 0.1, 0.1), length=0.55, load_mass=0.05,
             tie_point=(-0.3, 0.1, 0.1), tie_stiffness=800.0, tie_damping=2.0),
        # The shortest chains: one free particle (both the first and the last row), two (no middle row).
        spec(particle_count=2, top=(0.5, 0.4, 0.0), bottom=(0.5, 0.1, 0.0), length=0.3, load_mass=0.01,
             tie_point=(0.5, 0.1, 0.0), tie_stiffness=500.0, tie_damping=1.0),
        spec(particle_count=3, top=(0.7, 0.4, 0.0), bottom=(0.9, 0.4, 0.0), length=0.25, internal_friction=0.2),
    ]
    return make_model(strings, effects=StringEffects(), precision=precision)


def _five_passes(solver: SolverStringImplicit, state_in, state_out, control, dt: float) -> None:
    """The step as the five passes (what a taped step launches), without a tape."""
    ws = solver.workspace
    h = solver.model.scalar(dt)
    solver.eval_string_spring(state_in, solver.new_workspace(taped=False).segment_active, ws)
    solver.eval_string_system(state_in, control, h, ws)
    solver.solve_string_system(ws, None)
    solver.integrate_string(state_in, state_out, control, h, ws)
    solver.eval_string_tie_force(state_out, control)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_one_launch_step_equals_the_five_passes(precision):
    model = _model(precision)
    fused, passes = SolverStringImplicit(model), SolverStringImplicit(model)
    reached_ground, a = step_in_lockstep(model, (fused.step, fused.workspace),
                                         (functools.partial(_five_passes, passes), passes.workspace))
    assert reached_ground  # the ground contact terms acted
    assert np.all(np.isfinite(a.particle_q.numpy()))


@pytest.mark.parametrize("hand_adjoint", [True, False], ids=["one-launch", "five-passes"])
def test_a_taped_step_ends_where_the_plain_step_does(hand_adjoint):
    """A taped step runs the one-launch step (its adjoint hand-written) or, as the reference
    for that adjoint, the five passes; either ends where the plain step does, bit for bit."""
    model = _model("float64")
    solver = SolverStringImplicit(model)
    solver.hand_adjoint = hand_adjoint
    a, b, taped_out = model.state(), model.state(), model.state()
    dt = 1e-3
    for k, control in enumerate(swung_controls(model, 300, dt)):
        if k % 25 == 24:
            tape = wp.Tape()
            with tape:
                solver.step(a, taped_out, control, dt, tape=tape)
        solver.step(a, b, control, dt)
        if k % 25 == 24:
            np.testing.assert_array_equal(taped_out.particle_q.numpy(), b.particle_q.numpy())
            np.testing.assert_array_equal(taped_out.particle_qd.numpy(), b.particle_qd.numpy())
            np.testing.assert_array_equal(taped_out.tie_force.numpy(), b.tie_force.numpy())
        a, b = b, a
