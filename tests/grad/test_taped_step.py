"""The taped step is the plain step: ``SolverMarionette.step(..., tape=tape)`` (a workspace of
its own per step, recorded on a ``wp.Tape``, as the gradient engine runs it) ends bit for bit
where the plain step (the solver's reused workspace) does, over a 1 s rollout of each built-in
scene: joint limits, contacts (ground, chair, ball) and feedback on, the paper's rates
(strings 1 kHz, puppet 30 Hz); the strings have 10 particles instead of 50 to keep the test
short. The ``strings`` scene has no puppet: its strings are stepped alone
(``SolverStringImplicit.step(..., tape=tape)``). One more case runs tension-only strings
(the puppet at the string rate, which they need) for 0.1 s, through the unrecorded
active-set pass.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.strings.model import StringControl, StringModel
from dmarionette.strings.solver import SolverStringImplicit

wp.config.log_level = wp.LOG_WARNING

PARTICLES = 10
DURATION = 1.0  # s


def _short_strings(scene):
    strings = tuple(dataclasses.replace(s, particle_count=PARTICLES) for s in scene.strings)
    return dataclasses.replace(scene, strings=strings)


def _assert_same_marionette_state(a, b, step: int) -> None:
    for name, x, y in (("particle_q", a.strings.particle_q, b.strings.particle_q),
                       ("particle_qd", a.strings.particle_qd, b.strings.particle_qd),
                       ("joint_q", a.puppet.joint_q, b.puppet.joint_q),
                       ("joint_qd", a.puppet.joint_qd, b.puppet.joint_qd),
                       ("tie_force", a.tie_force, b.tie_force),
                       ("string_taut", a.string_taut, b.string_taut),
                       ("bar_feedback", a.bar_feedback, b.bar_feedback),
                       ("bar_reaction", a.bar_reaction, b.bar_reaction),
                       ("tie_target", a.tie_target, b.tie_target)):
        assert np.array_equal(x.numpy(), y.numpy()), f"puppet step {step}: {name} differs"


def _compare_marionette(scene, duration: float) -> int:
    model = MarionetteModel(scene, optimization_level=0, requires_grad=True)
    solver = SolverMarionette(model)
    steps = round(duration / model.puppet_dt)
    plain = [model.state(), model.state()]
    taped = [model.state(requires_grad=True) for _ in range(steps + 1)]
    control = model.control()
    tape = wp.Tape()
    for p in range(steps):
        control.set_bars(model, p * model.puppet_dt)
        solver.step(plain[p % 2], plain[(p + 1) % 2], control)
        with tape:
            solver.step(taped[p], taped[p + 1], control, tape=tape)
        _assert_same_marionette_state(plain[(p + 1) % 2], taped[p + 1], p)
    assert np.all(np.isfinite(taped[-1].puppet.joint_q.numpy()))
    return steps


MARIONETTE_SCENES = [name for name in dm.builtin_scenes() if dm.load_scene(name).puppet is not None]


def test_every_builtin_scene_is_covered():
    assert set(MARIONETTE_SCENES) | {"strings"} == set(dm.builtin_scenes())


@pytest.mark.parametrize("name", MARIONETTE_SCENES)
def test_taped_marionette_step_equals_the_plain_step(name):
    scene = _short_strings(dm.load_scene(name))
    assert scene.body_effects["joint_limits"] and scene.body_effects["body_ground"]
    assert _compare_marionette(scene, DURATION) == 30


def test_taped_tension_only_step_equals_the_plain_step():
    scene = _short_strings(dm.load_scene("hanging"))
    scene = dataclasses.replace(scene, puppet_hz=scene.string_hz,
                                effects=dataclasses.replace(scene.effects, tension_only=True))
    assert _compare_marionette(scene, 0.1) == 100


def test_taped_string_step_equals_the_plain_step():
    """The ``strings`` scene (no puppet): its strings under their bars for 1 s."""
    scene = _short_strings(dm.load_scene("strings"))
    model = StringModel.from_scene(scene, requires_grad=True)
    solver = SolverStringImplicit(model)
    steps = round(DURATION / scene.string_dt)
    times = scene.string_dt * np.arange(1, steps + 1)
    tops = scene.top_positions(np.array([s.top for s in model.specs]), times)
    ties = model.tie_points()
    plain = [model.state(), model.state()]
    taped = [model.state() for _ in range(steps + 1)]
    tape = wp.Tape()
    for k in range(steps):
        control = StringControl.from_numpy(model, tops[k], ties, np.zeros_like(ties))
        solver.step(plain[k % 2], plain[(k + 1) % 2], control, scene.string_dt)
        with tape:
            solver.step(taped[k], taped[k + 1], control, scene.string_dt, tape=tape)
        for name in ("particle_q", "particle_qd", "tie_force", "string_taut"):
            want, got = getattr(plain[(k + 1) % 2], name).numpy(), getattr(taped[k + 1], name).numpy()
            assert np.array_equal(want, got), f"string step {k}: {name} differs"
