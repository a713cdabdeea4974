"""The plain string step in SIMD lanes (``kernels/string_step_lanes``: four strings of equal
particle count per thread) computes the scalar one-launch step's numbers, bit for bit.

``SolverStringImplicit`` runs it for a plain float64 step on the CPU with printed springs
(``lanes``, on by default there); otherwise, or with ``lanes = False``, the scalar kernel
(``kernels/string_step``). Checked on the hard
case of ``test_string_step_schedules`` (tops swung fast and lowered onto the ground, ties moving,
chains of 2 to 50 particles), with several strings per particle count and constants varied
string by string, so that groups are full, partly padded (19 strings: not a multiple of 4) or
one string and three padding lanes; under several effect sets (each builds its own kernel); and
in a marionette scene, where a taped step (the scalar kernel with ``keep``) must still end where
the plain, laned, step does.
"""

import dataclasses

import numpy as np
import pytest
import warp as wp
from tests.support.strings import make_model, repeated_specs, spec, step_in_lockstep

import dmarionette as dm
from dmarionette.kernels.string_step_lanes import LANES, lane_groups
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.strings.model import StringEffects
from dmarionette.strings.solver import SolverStringImplicit

wp.config.log_level = wp.LOG_WARNING

# The hard case's five strings (test_string_step_schedules._model), each repeated this many times.
BASE = [
    (5, dict(particle_count=30, top=(0.0, 0.5, 0.0), bottom=(0.0, 0.05, 0.0), length=0.5, load_mass=0.02,
             internal_friction=0.3, air_drag=0.05, ground_stiffness=2000.0, ground_absorption=5.0,
             ground_friction=2.0)),
    (3, dict(particle_count=7, top=(0.3, 0.4, 0.0), bottom=(0.6, 0.4, 0.2), length=0.45)),
    (4, dict(particle_count=50, top=(-0.3, 0.6, 0.1), bottom=(-0.3, 0.1, 0.1), length=0.55, load_mass=0.05,
             tied=True, tie_point=(-0.3, 0.1, 0.1), tie_stiffness=800.0, tie_damping=2.0)),
    (6, dict(particle_count=2, top=(0.5, 0.4, 0.0), bottom=(0.5, 0.1, 0.0), length=0.3, load_mass=0.01,
             tied=True, tie_point=(0.5, 0.1, 0.0), tie_stiffness=500.0, tie_damping=1.0)),
    (1, dict(particle_count=3, top=(0.7, 0.4, 0.0), bottom=(0.9, 0.4, 0.0), length=0.25, internal_friction=0.2)),
]

EFFECT_SETS = {
    "every effect": StringEffects(),
    "no ground friction": StringEffects(ground_friction=False),
    "gravity and ground only": StringEffects(internal_friction=False, air_drag=False, ground_friction=False),
    "no gravity, no ground": StringEffects(gravity=False, ground_contact=False, ground_friction=False),
}


def _model(effects: StringEffects):
    """19 strings: the hard case's five, repeated, each copy moved and its constants varied
    (stiffness, friction, drag, ground, tie; every other copy of a tied string cut)."""
    specs = repeated_specs(BASE, (0.02, 0.01, -0.015))
    return make_model(specs, effects=effects, precision="float64")


def test_the_group_table():
    start = np.array([0, 30, 37, 67, 69, 71, 101, 103])  # counts 30, 7, 30, 2, 2, 30, 2
    group_string, group_real, group_base, rows = lane_groups(start, 4)
    np.testing.assert_array_equal(group_string, [[3, 4, 6, 3], [1, 1, 1, 1], [0, 2, 5, 0]])
    np.testing.assert_array_equal(group_real, [3, 1, 3])
    np.testing.assert_array_equal(group_base, [0, 2, 9])
    assert rows == 39


@pytest.mark.parametrize("effects", EFFECT_SETS.values(), ids=EFFECT_SETS.keys())
def test_lanes_equal_the_scalar_step(effects):
    model = _model(effects)
    assert model.string_count % LANES != 0
    lanes, scalar = SolverStringImplicit(model), SolverStringImplicit(model)
    assert lanes.lanes  # on by default (float64, CPU, printed springs)
    scalar.lanes = False
    reached_ground, a = step_in_lockstep(model, (lanes.step, lanes.workspace), (scalar.step, scalar.workspace))
    # Each ran its own kernel: the scalar one writes the workspace's d', the laned one its own scratch.
    assert np.any(scalar.workspace.scratch_d.numpy()) and not np.any(lanes.workspace.scratch_d.numpy())
    assert reached_ground == effects.ground_contact or not effects.gravity
    taut = a.string_taut.numpy()
    assert np.all(np.isfinite(a.particle_q.numpy()))
    if effects.gravity:
        assert 0 < taut.sum() < taut.size  # the taut flag differs between lanes of a group


def test_lanes_are_refused_where_they_do_not_apply():
    solver = SolverStringImplicit(_model(StringEffects()))
    assert solver.lanes  # float64, CPU, printed springs: on by default
    solver.lanes = False
    assert not solver.lanes
    solver.lanes = True
    assert solver.lanes
    for model in (make_model([spec()], precision="float32"),
                  make_model([spec()], effects=StringEffects(tension_only=True), precision="float64")):
        solver = SolverStringImplicit(model)
        with pytest.raises(ValueError, match="printed springs, float64 and a CPU device"):
            solver.lanes = True
        assert not solver.lanes


def test_marionette_taped_step_ends_where_the_laned_plain_step_does():
    """``hanging`` (its strings at their 50 particles), 0.3 s: the plain marionette step (laned
    strings), the same with ``lanes = False``, and the taped step (the scalar keep kernel) agree."""
    scene = dm.load_scene("hanging")
    model = MarionetteModel(scene, optimization_level=0, requires_grad=True)
    laned_model = MarionetteModel(scene, optimization_level=0)
    scalar_model = MarionetteModel(scene, optimization_level=0)
    assert model.string_solver.lanes and laned_model.string_solver.lanes  # on by default
    scalar_model.string_solver.lanes = False
    solvers = [SolverMarionette(m) for m in (laned_model, scalar_model)]
    taped_solver = SolverMarionette(model)
    steps = round(0.3 / model.puppet_dt)
    plain = [[m.state(), m.state()] for m in (laned_model, scalar_model)]
    taped = [model.state(requires_grad=True) for _ in range(steps + 1)]
    control = model.control()
    tape = wp.Tape()
    for p in range(steps):
        control.set_bars(model, p * model.puppet_dt)
        for solver, states in zip(solvers, plain):
            solver.step(states[p % 2], states[(p + 1) % 2], control)
        with tape:
            taped_solver.step(taped[p], taped[p + 1], control, tape=tape)
        for other in (plain[1][(p + 1) % 2], taped[p + 1]):
            x = plain[0][(p + 1) % 2]
            for name in ("particle_q", "particle_qd"):
                np.testing.assert_array_equal(getattr(x.strings, name).numpy(), getattr(other.strings, name).numpy(),
                                              err_msg=f"puppet step {p}: {name}")
            for name in ("tie_force", "string_taut", "bar_feedback"):
                np.testing.assert_array_equal(getattr(x, name).numpy(), getattr(other, name).numpy(),
                                              err_msg=f"puppet step {p}: {name}")
            np.testing.assert_array_equal(x.puppet.joint_q.numpy(), other.puppet.joint_q.numpy())
    # The scalar kernel writes the string workspace's d', the laned one its own scratch.
    string_ws = [s.workspace.string_workspaces[0] for s in solvers]
    assert not np.any(string_ws[0].scratch_d.numpy()) and np.any(string_ws[1].scratch_d.numpy())
    assert np.all(np.isfinite(taped[-1].puppet.joint_q.numpy()))
