"""Effects on demand: an effect switched off is compiled out and equals that effect at zero."""

import dataclasses

import numpy as np
import pytest
import warp as wp
from tests.support.strings import make_model, roll, spec

from dmarionette.kernels.string_system import eval_string_system_kernel
from dmarionette.strings.model import StringControl, StringEffects, StringModel
from dmarionette.strings.solver import SolverStringImplicit

ALL_ON = StringEffects()

# effect switched off -> the scene constants that make the same effect vanish when it is on
ZEROED = {
    "air_drag": {"air_drag": 0.0},
    "internal_friction": {"internal_friction": 0.0},
    "ground_friction": {"ground_friction": 0.0},
    "ground_contact": {"ground_stiffness": 0.0, "ground_absorption": 0.0, "ground_friction": 0.0},
}


def _swinging_string(**constants):
    """A string that swings down from horizontal and brushes the ground."""
    base = dict(particle_count=25, top=(0.0, 0.4, 0.0), bottom=(0.5, 0.4, 0.0), length=0.5, load_mass=0.02,
                internal_friction=0.3, air_drag=0.05, ground_stiffness=2000.0, ground_absorption=5.0,
                ground_friction=2.0)
    base.update(constants)
    return spec(**base)


@pytest.mark.parametrize("effect", sorted(ZEROED))
def test_disabled_effect_equals_zero_constant(effect):
    off = make_model([_swinging_string()], effects=dataclasses.replace(ALL_ON, **{effect: False}))
    zero = make_model([_swinging_string(**ZEROED[effect])], effects=ALL_ON)
    state_off, run_off = roll(off, 1e-3, 1000, chunk=50)
    state_zero, run_zero = roll(zero, 1e-3, 1000, chunk=50)
    assert np.min(run_off.frames[:, :, 1]) < 0.0  # the string does reach the ground
    np.testing.assert_allclose(run_off.frames, run_zero.frames, rtol=0, atol=1e-14)
    np.testing.assert_allclose(state_off.particle_qd.numpy(), state_zero.particle_qd.numpy(), rtol=0, atol=1e-12)


def test_disabled_gravity_equals_zero_gravity():
    off = make_model([_swinging_string()], effects=dataclasses.replace(ALL_ON, gravity=False))
    zero = StringModel([_swinging_string()], effects=ALL_ON, gravity=(0.0, 0.0, 0.0), ground_height=0.0)
    top = np.zeros((300, 1, 3))
    top[:, 0] = [0.0, 0.4, 0.0]
    top[:, 0, 0] = 0.1 * np.sin(np.linspace(0, 6, 300))
    _, run_off = roll(off, 1e-3, 300, top_q=top, chunk=30)
    _, run_zero = roll(zero, 1e-3, 300, top_q=top, chunk=30)
    np.testing.assert_allclose(run_off.frames, run_zero.frames, rtol=0, atol=1e-14)


def _generated_source(effects: StringEffects) -> str:
    # Warp's module builder (internal API) gives the C++ that the CPU compiler receives.
    from warp._src.context import ModuleBuilder

    kernel = eval_string_system_kernel(wp.float64, effects.as_tuple())
    return ModuleBuilder(kernel.module, kernel.module.options, target="cpu").codegen("cpu")


@pytest.mark.parametrize(
    "effect,function",
    [("air_drag", "compute_air_drag"), ("internal_friction", "compute_internal_friction"),
     ("ground_contact", "compute_ground_contact"), ("ground_friction", "compute_ground_friction")],
)
def test_disabled_effect_is_not_in_the_compiled_kernel(effect, function):
    with_effect = _generated_source(ALL_ON)
    without = _generated_source(dataclasses.replace(ALL_ON, **{effect: False}))
    assert function in with_effect
    assert function not in without


def test_rollout_equals_step_by_step():
    """The captured-graph rollout (odd chunk: ends with a state copy) equals eager stepping."""
    model = make_model([_swinging_string(), _swinging_string(particle_count=7, top=(0.2, 0.6, 0.0),
                                                              bottom=(0.2, 0.2, 0.3), length=0.6)],
                       effects=ALL_ON)
    steps, dt = 147, 1e-3
    top = np.broadcast_to(np.array([s.top for s in model.specs]), (steps, 2, 3)).copy()
    top[:, :, 2] += 0.05 * np.sin(np.arange(steps) * 0.05)[:, None]
    state, result = roll(model, dt, steps, top_q=top, chunk=7)
    solver = SolverStringImplicit(model)
    a, b = model.state(), model.state()
    for k in range(steps):
        control = StringControl.from_numpy(model, top[k], model.tie_points(), np.zeros((2, 3)))
        solver.step(a, b, control, dt)
        a, b = b, a
    np.testing.assert_array_equal(state.particle_q.numpy(), a.particle_q.numpy())
    np.testing.assert_array_equal(result.string_taut[-1], a.string_taut.numpy())


def test_float32_runs_the_hanging_strings_close_to_float64():
    """float32 is available; at the default stiffness it stays within 1 mm of float64 over 1 s."""
    from dmarionette.scene.scene import load_scene
    from dmarionette.strings.simulate import simulate_strings

    scene = load_scene("strings")
    runs = {p: simulate_strings(scene, 1.0, progress=False, model=StringModel.from_scene(scene, precision=p))
            for p in ("float64", "float32")}
    assert np.all(np.isfinite(runs["float32"].particle_q))
    gap = np.max(np.abs(runs["float32"].particle_q - runs["float64"].particle_q))
    assert gap < 1e-3, gap
