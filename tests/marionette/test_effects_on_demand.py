"""Effects on demand for the whole marionette: an effect a scene turns off leaves no code behind.

Each effect is either a kernel that is not launched when off (contacts with ground, chair
and ball; feedback) or code removed from a kernel at generation time (the string terms,
through ``wp.static``; joint limits, in the generated puppet kernels). One marionette step
is run with every effect on, then with one effect off, recording the kernels launched.
"""

import dataclasses

import pytest
import warp as wp

import dmarionette as dm
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.scene.scene import BallSpec

wp.config.log_level = wp.LOG_WARNING


def _scene(**body_effects):
    """``hanging`` with every effect on; chair and ball placed out of the puppet's reach."""
    scene = dm.load_scene("hanging")
    effects = dict(scene.body_effects, chair=True, ball=True)
    effects.update(body_effects)
    return dataclasses.replace(scene, body_effects=effects,
                               chair=((1.0, 0.1, 0.0), (0.1, 0.1, 0.1)) if effects["chair"] else None,
                               ball=BallSpec((-1.0, 0.05, 0.0), 0.05, 0.05) if effects["ball"] else None)


def _launched(scene, monkeypatch) -> tuple[set[str], MarionetteModel]:
    model = MarionetteModel(scene, optimization_level=0)
    solver = SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    solver.step(a, b, control)  # compile and load first
    keys = set()
    real_launch = wp.launch

    def recording_launch(kernel, *args, **kwargs):
        keys.add(f"{kernel.module.name}:{kernel.key}")  # closures share a key; their modules differ
        return real_launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", recording_launch)
    solver.step(a, b, control)
    monkeypatch.setattr(wp, "launch", real_launch)
    return keys, model


@pytest.fixture(scope="module")
def all_on():
    with pytest.MonkeyPatch.context() as mp:
        return _launched(_scene(), mp)


def _by_name_for_generated(keys: set[str]) -> set[str]:
    """The puppet's generated kernels change module with the model's bodies (the ball is a
    body): compare those by kernel name only."""
    return {k.split(":")[1] if k.startswith("dmarionette_articulation_") else k for k in keys}


@pytest.mark.parametrize("effect", ["body_ground", "chair", "ball", "feedback"])
def test_an_effect_turned_off_launches_no_kernel_for_it(all_on, monkeypatch, effect):
    on_keys, _ = all_on
    off_keys, _ = _launched(_scene(**{effect: False}), monkeypatch)
    on_keys, off_keys = _by_name_for_generated(on_keys), _by_name_for_generated(off_keys)
    assert off_keys < on_keys, (effect, on_keys - off_keys, off_keys - on_keys)


def test_joint_limits_turned_off_are_not_in_the_generated_kernel(all_on, monkeypatch):
    _, on_model = all_on
    _, off_model = _launched(_scene(joint_limits=False), monkeypatch)
    source = {m: m.puppet_solver.kernels.solve_body_dynamics.adj.source for m in (on_model, off_model)}
    assert "dof_limit_lower" in source[on_model]
    assert "dof_limit_lower" not in source[off_model]


@pytest.mark.parametrize("effect", ["air_drag", "internal_friction", "ground_contact"])
def test_string_effects_turned_off_change_the_compiled_string_kernel(all_on, monkeypatch, effect):
    """The string terms live in one kernel built per effect set (``eval_string_system``, or in a
    plain step the one-launch ``integrate_string_implicit`` that assembles the same rows, or with
    ``SolverStringImplicit.lanes`` its laned form ``integrate_string_lanes``): off, it is a different kernel."""
    on_keys, _ = all_on
    scene = _scene()
    scene = dataclasses.replace(scene, effects=dataclasses.replace(scene.effects, **{effect: False}))
    off_keys, _ = _launched(scene, monkeypatch)
    assembles = ("eval_string_system", "integrate_string_implicit", "integrate_string_lanes")
    on_system = {k for k in on_keys if any(name in k for name in assembles)}
    off_system = {k for k in off_keys if any(name in k for name in assembles)}
    assert on_system and off_system and on_system != off_system
