"""Forward-mode sensitivities of a whole string rollout (``grad.string_tangent.StringRolloutTangent``).

1 s at 1 kHz of the built-in ``strings`` scene's six strings (50 particles each, every effect on),
from the state 0.2 s after the scene's start (whose segments are exactly at rest length, on the
kink of the spring's clamp),
tops swaying as the scene's motion (0.05 m at 0.5 Hz) plus a small circle, and, so that the tie
forces are outputs with a gradient, the two hand strings tied (eq. 2, the scene's default tie
constants) to points just below their bottoms that circle (the scene's strings are not tied: a
deviation for the test). One direction per input group (the initial positions and velocities,
the masses, each constant, the tops, tie targets and their velocities over every step).

- Against reverse mode (the taped steps, ``SolverStringImplicit.step(tape=)``, the hand adjoint,
  then ``tape.backward``): the dot-product identity ``<u, J v> = <J^T u, v>`` for random output
  cotangents (tie forces after every step, the final state), 1e-10 of the sum of the absolute
  products. The ground constants have no effect (no particle reaches the ground): both sides
  exactly zero.
- Against central differences of whole rollouts (``StringRollout``, the plain laned step), steps
  ``t`` from 1e-3 to 1e-7 of each group's scale: the error falls like ``t^2`` where it shows above
  rounding (slope 2 between such steps), the best step within 1e-6 relative. The rollout stays
  away from the step's kinks (asserted: every segment stays taut, by a margin, and no particle
  nears the ground), so it is smooth in a neighbourhood of the inputs.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.grad.string_tangent import CONSTANTS, StringRolloutTangent, StringTangentInputs
from dmarionette.strings.model import StringControl, StringModel
from dmarionette.strings.rollout import StringRollout
from dmarionette.strings.solver import SolverStringImplicit
from tests.support.strings import weighted_sum

DT = 1e-3
STEPS_T = 1000
WARM_UP = 200  # steps from the scene's initial state (every segment exactly at rest: the clamp's kink) to the start
CHUNK = 100
TOLERANCE = 1e-10
GROUPS = ("particle_q", "particle_qd", "particle_mass") + CONSTANTS + ("top_q", "tie_q", "tie_qd")
GROUND = ("string_ground_stiffness", "string_ground_absorption", "string_ground_friction")
FD_STEPS = 10.0 ** -np.arange(3, 8)


def scene_model(requires_grad: bool = False) -> StringModel:
    """The ``strings`` scene's strings, the two hand strings tied to points 2 cm below their bottoms."""
    scene = dm.load_scene("strings")
    specs = [dataclasses.replace(s, tied=True, tie_point=(s.bottom[0], s.bottom[1] - 0.02, s.bottom[2]))
             if s.name.startswith("hand") else s for s in scene.strings]
    return StringModel(specs, effects=scene.effects, gravity=scene.gravity, ground_height=scene.ground_height,
                       requires_grad=requires_grad)


def scene_controls(model: StringModel, steps: int = WARM_UP + STEPS_T):
    """Tops swaying (0.05 m at 0.5 Hz in x, as the scene) on a 5 mm circle; tie points circling (1 cm, 2 Hz)."""
    t = DT * np.arange(1, steps + 1)[:, None]
    tops = np.array([s.top for s in model.specs])[None] + np.stack(
        [0.05 * np.sin(np.pi * t) + 0.005 * np.cos(6 * t), 0.005 * np.sin(6 * t), 0.0 * t], axis=-1)
    w = 4 * np.pi
    tie = model.tie_points()[None] + np.stack([0.01 * np.sin(w * t), 0.0 * t, 0.01 * np.cos(w * t)], axis=-1)
    tie_v = np.stack([0.01 * w * np.cos(w * t), 0.0 * t, -0.01 * w * np.sin(w * t)], axis=-1) * np.ones_like(tie)
    return tops, tie, tie_v


def _scales(model):
    rest = model.string_rest_length.numpy()
    scale = {"particle_q": 0.1 * np.min(rest), "particle_qd": 0.05, "particle_mass": model.particle_mass.numpy(),
             "top_q": 0.1 * np.min(rest), "tie_q": 0.1 * np.min(rest), "tie_qd": 0.05}
    for name in CONSTANTS:
        scale[name] = np.maximum(getattr(model, name).numpy(), 1e-3 if name != "string_tied" else 1.0)
    return scale


def _shape(model, name):
    n, s = model.particle_count, model.string_count
    return {"particle_q": (n, 3), "particle_qd": (n, 3), "particle_mass": (n,), "top_q": (STEPS_T, s, 3),
            "tie_q": (STEPS_T, s, 3), "tie_qd": (STEPS_T, s, 3)}.get(name, (s,))


def _directions(model, rng):
    """One direction per group (a dict of every group's tangent, zero but in its own group)."""
    scale = _scales(model)
    out = []
    for group in GROUPS:
        v = {name: np.zeros(_shape(model, name)) for name in GROUPS}
        sc = scale[group]
        w = rng.normal(size=_shape(model, group))
        v[group] = w * (sc[:, None] if np.ndim(sc) and w.ndim == 2 else sc)
        out.append(v)
    return out


def _tangent_inputs(directions) -> StringTangentInputs:
    def stack(name):
        return np.stack([d[name] for d in directions])

    return StringTangentInputs(particle_q=stack("particle_q"), particle_qd=stack("particle_qd"),
                               particle_mass=stack("particle_mass"),
                               constants=np.stack([np.stack([d[c] for c in CONSTANTS], axis=-1) for d in directions]),
                               top_q=stack("top_q"), tie_q=stack("tie_q"), tie_qd=stack("tie_qd"))


@pytest.fixture(scope="module")
def problem():
    """The model, the directions, the start (after the warm-up), the controls and the tangent rollout."""
    model = scene_model()
    rng = np.random.default_rng(29)
    directions = _directions(model, rng)
    tops, tie, tie_v = scene_controls(model)
    state = model.state()
    StringRollout(SolverStringImplicit(model), DT, chunk_steps=CHUNK).run(
        state, tops[:WARM_UP], tie[:WARM_UP], tie_v[:WARM_UP])
    start = (state.particle_q.numpy().copy(), state.particle_qd.numpy().copy())
    controls = (tops[WARM_UP:], tie[WARM_UP:], tie_v[WARM_UP:])
    rollout = StringRolloutTangent(SolverStringImplicit(model), DT, len(directions), chunk_steps=CHUNK)
    result = rollout.run(model.state(*start), *controls, tangents=_tangent_inputs(directions))
    return model, directions, start, controls, result


def _reverse(start, controls, cotangents):
    """<u, outputs>'s gradient by the taped steps and tape.backward, per input group."""
    model = scene_model(requires_grad=True)
    solver = SolverStringImplicit(model)
    tops, tie, tie_v = controls
    u_force, u_q, u_qd = cotangents
    steps = [StringControl.from_numpy(model, tops[k], tie[k], tie_v[k]) for k in range(STEPS_T)]
    states = [model.state(*start)] + [model.state() for _ in range(STEPS_T)]
    weights = [wp.array(u_force[k], dtype=wp.vec3d) for k in range(STEPS_T)]
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for k in range(STEPS_T):
            solver.step(states[k], states[k + 1], steps[k], DT, tape=tape)
            wp.launch(weighted_sum, dim=model.string_count, inputs=[states[k + 1].tie_force, weights[k]],
                      outputs=[loss])
        wp.launch(weighted_sum, dim=model.particle_count, inputs=[states[-1].particle_q, wp.array(u_q, dtype=wp.vec3d)],
                  outputs=[loss])
        wp.launch(weighted_sum, dim=model.particle_count,
                  inputs=[states[-1].particle_qd, wp.array(u_qd, dtype=wp.vec3d)], outputs=[loss])
    tape.backward(loss)
    grads = {"particle_q": states[0].particle_q.grad.numpy(), "particle_qd": states[0].particle_qd.grad.numpy()}
    for name in ("particle_mass",) + CONSTANTS:
        grads[name] = getattr(model, name).grad.numpy()
    for name in ("top_q", "tie_q", "tie_qd"):
        grads[name] = np.array([getattr(c, name).grad.numpy() for c in steps])
    return {k: np.array(v, dtype=float) for k, v in grads.items()}


def test_rollout_stays_away_from_the_kinks(problem):
    model, _directions_, start, controls, _result = problem
    rollout = StringRollout(SolverStringImplicit(model), DT, chunk_steps=1)
    state = model.state(*start)
    result = rollout.run(state, *controls)
    q = result.frames  # every step
    start = model.string_start_np
    rest = model.string_rest_length.numpy()
    ratios = [1.0 - rest[s] / np.linalg.norm(np.diff(q[:, start[s]:start[s + 1]], axis=1), axis=-1)
              for s in range(model.string_count)]
    low = min(np.min(r) for r in ratios)
    print(f"smallest 1 - d/l over the rollout: {low:.2e}; lowest particle: {np.min(q[..., 1]):.3f} m")
    assert low > 1e-3  # every segment taut by a margin: the clamp of the geometric stiffness never switches
    assert np.min(q[..., 1]) > 0.1  # no particle near the ground: the ground term never switches


def test_rollout_tangent_and_reverse_mode_satisfy_the_dot_product_identity(problem):
    model, directions, start, controls, result = problem
    rng = np.random.default_rng(31)
    scale = [max(np.max(np.abs(a)), 1e-12) for a in (result.tie_force, result.particle_q, result.particle_qd)]
    u = [rng.normal(size=a.shape) / s for a, s in zip((result.tie_force, result.particle_q, result.particle_qd),
                                                        scale, strict=True)]
    grads = _reverse(start, controls, u)
    for k, (group, v) in enumerate(zip(GROUPS, directions, strict=True)):
        jv = (result.tie_force_dot[k], result.particle_q_dot[k], result.particle_qd_dot[k])
        left_terms = np.concatenate([(ui * jvi).ravel() for ui, jvi in zip(u, jv, strict=True)])
        right_terms = np.concatenate([(grads[name] * v[name]).ravel() for name in GROUPS])
        left, right = left_terms.sum(), right_terms.sum()
        size = max(np.abs(left_terms).sum(), np.abs(right_terms).sum())
        gap = abs(left - right) / max(size, 1e-300)
        print(f"{group}: <u, Jv> = {left:.9e}, <J^T u, v> = {right:.9e}, gap {gap:.1e} of {size:.2e}")
        if group in GROUND:
            assert left == 0.0 and right == 0.0, group
            continue
        assert size > 0.0, group
        assert abs(left - right) / size < TOLERANCE, group


def _outputs(model, start, controls, v, t):
    """A plain rollout's outputs (tie forces, final state; each scaled) with the inputs moved by ``t v``."""
    saved = {name: getattr(model, name).numpy().copy() for name in ("particle_mass",) + CONSTANTS}
    tops, tie, tie_v = controls
    try:
        for name in saved:
            getattr(model, name).assign(saved[name] + t * v[name])
        state = model.state(start[0] + t * v["particle_q"], start[1] + t * v["particle_qd"])
        result = StringRollout(SolverStringImplicit(model), DT, chunk_steps=CHUNK).run(
            state, tops + t * v["top_q"], tie + t * v["tie_q"], tie_v + t * v["tie_qd"])
        return [result.tie_force, state.particle_q.numpy().copy(), state.particle_qd.numpy().copy()]
    finally:
        for name in saved:
            getattr(model, name).assign(saved[name])


def test_rollout_tangent_against_central_differences_of_whole_rollouts(problem):
    model, directions, start, controls, result = problem
    base = [result.tie_force, result.particle_q, result.particle_qd]
    scale = [max(np.max(np.abs(a)), 1e-12) for a in base]
    for k, group in enumerate(GROUPS):
        if group in GROUND:
            continue  # no effect (the identity test checks it is exactly zero)
        exact = np.concatenate([(a[k] / s).ravel() for a, s in zip(
            (result.tie_force_dot, result.particle_q_dot, result.particle_qd_dot), scale, strict=True)])
        size = np.max(np.abs(exact))
        assert size > 0.0, group
        errors = []
        for t in FD_STEPS:
            plus = _outputs(model, start, controls, directions[k], t)
            minus = _outputs(model, start, controls, directions[k], -t)
            fd = np.concatenate([((a - b) / (2 * t) / s).ravel() for a, b, s in zip(plus, minus, scale, strict=True)])
            errors.append(np.max(np.abs(fd - exact)) / size)
        errors = np.array(errors)
        # Rounding, amplified by 1000 steps, fitted as c / t at the smallest step (where the O(t^2)
        # error is 1e-8 of the largest step's: negligible); truncation shows above 10x that.
        noise = errors[-1] * FD_STEPS[-1] / FD_STEPS
        truncated = errors > 10.0 * noise
        print(f"{group}: errors {' '.join(f'{e:.1e}' for e in errors)}; error / fitted rounding "
              f"{' '.join(f'{e:.1f}' for e in errors / noise)}")
        assert np.min(errors) < 1e-6, group
        assert np.all(errors < np.maximum(1.5 * errors[0] * (FD_STEPS / FD_STEPS[0]) ** 2, 3.0 * noise)), group
        for i in range(len(FD_STEPS) - 1):
            if truncated[i] and truncated[i + 1]:
                assert 1.6 < np.log10(errors[i] / errors[i + 1]) < 2.4, group


def test_string_lanes_rollout_tangent_follows_the_scalar_one(problem):
    """One direction (every input group at once) through the whole rollout with the strings in SIMD
    lanes (``kernels/string_step_tangent_lanes``, the default at P = 1 with the laned forward; the six
    strings in groups of 4 + 2) against the scalar tangent kernel (``lanes=False``): the same
    operations up to rounding (a step's outputs differ by ~1e-16 relative,
    ``tests/grad/test_string_step_tangent.py``), so the gap is rounding carried through the steps: at
    most T = 1,000 steps' worth of a few eps through the solve, ~1e-12 of each output's largest
    entry, asserted (measured 3e-15, the printout)."""
    model, directions, start, controls, _ = problem
    one = {name: sum(d[name] for d in directions) for name in GROUPS}
    results = []
    for lanes in (None, False):
        rollout = StringRolloutTangent(SolverStringImplicit(model), DT, 1, chunk_steps=CHUNK, lanes=lanes)
        assert rollout.stepper.string_lanes == (lanes is None)
        results.append(rollout.run(model.state(*start), *controls, tangents=_tangent_inputs([one])))
    laned, scalar = results
    for name in ("tie_force_dot", "particle_q_dot", "particle_qd_dot"):
        a, b = getattr(laned, name), getattr(scalar, name)
        size = np.max(np.abs(b))
        gap = np.max(np.abs(a - b)) / size
        print(f"{name}: string lanes against scalar {gap:.1e} of {size:.2e}")
        assert size > 0.0 and gap <= 1e-12, name
