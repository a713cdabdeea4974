"""The taped string step in SIMD lanes (the laned step with ``keep`` and the laned hand-written adjoint,
``kernels/string_step_adjoint_lanes``) against the scalar one (the one-launch step with ``keep`` and
``kernels/string_step_adjoint``): the same forward and the same gradients, bit for bit.

The laned kernels do the scalar kernels' operations in their order and rounding, lane by lane, and
each string's particles and constants are written by one lane of one thread, so nothing is summed
in another order: every state output, every kept pivot inverse and every gradient must be equal
(``np.testing.assert_array_equal``), not close. The problem is ``test_string_step_adjoint``'s (every
effect on, particles below the ground, a string tied to a circling point, compressed segments)
with its strings repeated and varied so that the groups of four strings of equal particle count are
full, padded (11 strings), or one string with three padding lanes, and one group of two-particle
chains (the last row is the first). Then the marionette engine (``MarionetteGradient``) on
``chair_scripted`` and ``hanging``: lanes on and off give the same gradients, bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from tests.support.strings import (ALL_ON, make_model, repeated_specs, rollout_gradients, taped_rollout,
                                  wiggled_controls)
from tests.support.marionette_gradients import smooth_scene

from dmarionette.grad.engine import MarionetteGradient
from dmarionette.kernels.string_step_lanes import LANES, lane_groups
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.strings.model import StringEffects
from dmarionette.strings.solver import SolverStringImplicit

STEPS = 200
DT = 1e-3

# test_string_step_adjoint's three strings and a two-particle chain, each repeated this many times.
BASE = [
    (5, dict(particle_count=9, top=(0.0, 0.15, 0.0), bottom=(0.5, 0.02, 0.0), length=0.6, internal_friction=0.3,
             air_drag=0.05, ground_stiffness=2000.0, ground_absorption=5.0, ground_friction=2.0)),
    (2, dict(particle_count=7, top=(0.5, 1.0, 0.0), bottom=(0.5, 0.6, 0.0), length=0.4, internal_friction=0.2,
             air_drag=0.02, tied=True, tie_point=(0.6, 0.55, 0.1), tie_stiffness=300.0, tie_damping=3.0)),
    (1, dict(particle_count=6, top=(1.0, 1.0, 0.0), bottom=(1.0, 0.75, 0.05), length=0.35, load_mass=0.02)),
    (3, dict(particle_count=2, top=(1.5, 0.3, 0.0), bottom=(1.5, 0.05, 0.0), length=0.3, load_mass=0.01,
             internal_friction=0.1, ground_stiffness=1500.0, ground_absorption=3.0, ground_friction=1.0,
             tied=True, tie_point=(1.5, 0.05, 0.0), tie_stiffness=500.0, tie_damping=1.0)),
]


def _model(effects: StringEffects):
    """11 strings: counts 9 x 5 (a full group and a group of one), 7 x 2, 6 x 1, 2 x 3; each copy
    moved and its constants varied (every other copy of a tied string cut)."""
    specs = repeated_specs(BASE, (0.03, 0.0, -0.02))
    return make_model(specs, effects=effects, requires_grad=True)


def _taped_run(lanes: bool, effects: StringEffects) -> dict[str, np.ndarray]:
    """A taped rollout of ``STEPS`` steps (tops swung, ties circling) and the gradient of a random
    weighting of the final positions, velocities and tie forces; returns every state output and
    kept value of every step and every gradient."""
    model = _model(effects)
    solver = SolverStringImplicit(model)
    solver.lanes = lanes
    controls = wiggled_controls(model, STEPS, DT)
    states = [model.state() for _ in range(STEPS + 1)]
    workspaces = [solver.new_workspace() for _ in range(STEPS)]
    tape, loss = taped_rollout(solver, states, controls, DT, np.random.default_rng(11), workspaces)
    out = {name: np.array([getattr(s, name).numpy() for s in states[1:]])
           for name in ("particle_q", "particle_qd", "tie_force", "string_taut")}
    out["particle_dv"] = np.array([w.particle_dv.numpy() for w in workspaces])
    out["pivot_inverse"] = np.array([_pivot_inverses(model, w, lanes) for w in workspaces])
    tape.backward(loss)
    out.update(rollout_gradients(model, states, controls))
    out["below_ground"] = np.min(out["particle_q"][..., 1])
    return out


def _pivot_inverses(model, ws, lanes: bool) -> np.ndarray:
    """The kept pivot inverses per particle (rows 1.. of each string; the top's row is never a pivot),
    from the scalar workspace or from the laned one (real lanes only)."""
    if not lanes:
        inv = ws.scratch_inverse.numpy().copy()
    else:
        start = model.string_start.numpy()
        group_string, group_real, group_base, _rows = lane_groups(start, LANES)
        laned = ws.lane_inverse.numpy()  # (rows, 9, K)
        inv = np.zeros((model.particle_count, 3, 3))
        for g in range(len(group_real)):
            for k in range(group_real[g]):
                s = group_string[g, k]
                n = start[s + 1] - start[s]
                inv[start[s] + 1:start[s + 1]] = laned[group_base[g] + 1:group_base[g] + n, :, k].reshape(-1, 3, 3)
    inv[model.string_start.numpy()[:-1]] = 0.0  # never written by either
    return inv


EFFECT_SETS = {
    "every effect": ALL_ON,
    "no ground friction": dataclasses.replace(ALL_ON, ground_friction=False),
    "no gravity, no ground": StringEffects(gravity=False, internal_friction=True, air_drag=True, ground_contact=False,
                                           ground_friction=False),
}


@pytest.mark.parametrize("effects", EFFECT_SETS.values(), ids=EFFECT_SETS.keys())
def test_laned_taped_step_equals_the_scalar_one(effects):
    laned, scalar = _taped_run(True, effects), _taped_run(False, effects)
    if effects.ground_contact:
        assert laned["below_ground"] < 0.0  # particles start steps below the ground
    off = set()  # the gradients of constants whose effect is off are zero
    if not effects.ground_contact:
        off |= {"string_ground_stiffness_grad", "string_ground_absorption_grad", "string_ground_friction_grad"}
    if not effects.ground_friction:
        off.add("string_ground_friction_grad")
    for name, value in scalar.items():
        if name.endswith("_grad") and name not in off:
            assert np.max(np.abs(value)) > 0.0, name  # every group is exercised
        np.testing.assert_array_equal(laned[name], value, err_msg=name)


def test_the_laned_taped_step_is_the_laned_kernel():
    """The comparison above compares two different kernels: lanes on writes the laned keep arrays into
    a lean workspace (``particle_dv`` and the lane arrays: no scalar arrays at all); lanes off the
    scalar keep arrays (and not the five passes' blocks). A lean workspace stepped after lanes were turned off gets the scalar arrays and
    ends where a scalar workspace does."""
    model = _model(ALL_ON)
    solver = SolverStringImplicit(model)
    assert solver.lanes
    ws = solver.new_workspace()
    assert ws.scratch_inverse is None and ws.system_diag is None and ws.segment_jacobian is None
    a, b, c = model.state(), model.state(), model.state()
    tape = wp.Tape()
    with tape:
        solver.step(a, b, model.control(), DT, tape=tape, workspace=ws)
    assert np.any(ws.lane_inverse.numpy() != 0.0) and ws.scratch_inverse is None
    solver.lanes = False
    scalar_ws = solver.new_workspace()
    with tape:
        solver.step(a, b, model.control(), DT, tape=tape, workspace=scalar_ws)
    assert scalar_ws.lane_inverse is None and np.any(scalar_ws.scratch_inverse.numpy() != 0.0)
    assert scalar_ws.system_diag is None and scalar_ws.segment_jacobian is None  # the scalar keep step's only
    with tape:
        solver.step(a, c, model.control(), DT, tape=tape, workspace=ws)  # the lean one, lanes now off
    np.testing.assert_array_equal(ws.scratch_inverse.numpy(), scalar_ws.scratch_inverse.numpy())
    np.testing.assert_array_equal(c.particle_q.numpy(), b.particle_q.numpy())


def _engine_gradients(scene_name: str, lanes: bool, seconds: float, particle_count: int | None):
    model = MarionetteModel(smooth_scene(scene_name, particle_count), optimization_level=0, requires_grad=True)
    model.string_solver.lanes = lanes  # before the engine plans its taped segment
    engine = MarionetteGradient(model, int(round(seconds / model.puppet_dt)))
    rng = np.random.default_rng(3)
    weights = {k: rng.normal(size=s) for k, s in engine.output_shapes.items()}
    outputs = engine.forward(engine.scene_inputs())
    grads = engine.backward(weights)
    out = {f.name: np.asarray(getattr(grads, f.name)) for f in dataclasses.fields(grads)}
    out.update({f"forward {k}": np.asarray(v) for k, v in dataclasses.asdict(outputs).items()}
               if dataclasses.is_dataclass(outputs) else {})
    return out


@pytest.mark.parametrize("scene_name, seconds, particle_count",
                         [("chair_scripted", 1.0 / 3.0, 10), ("hanging", 0.2, None)], ids=["chair_scripted", "hanging"])
def test_laned_gradients_equal_the_scalar_ones_in_the_marionette(scene_name, seconds, particle_count):
    laned = _engine_gradients(scene_name, True, seconds, particle_count)
    scalar = _engine_gradients(scene_name, False, seconds, particle_count)
    assert any(np.max(np.abs(v)) > 0.0 for v in scalar.values())
    for name, value in scalar.items():
        np.testing.assert_array_equal(laned[name], value, err_msg=name)
