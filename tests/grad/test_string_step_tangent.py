"""The string step's tangent-linear model (``kernels/string_step_tangent``) against its hand adjoint and FD.

One step from a state chosen to reach every branch (every effect on; particles of one string
below the ground, a compressed string, a tie whose target moves; three strings of 9, 7 and 6
particles), kept away from the kinks (each segment's ``1 - d/l`` and each particle's depth at
least a margin from zero, asserted), so that the step is smooth in a neighbourhood of the state.

- The dot-product identity ``<u, J v> = <J^T u, v>`` against the hand-written adjoint
  (``string_step_adjoint``, recorded by ``SolverStringImplicit.step(tape=)``), for random output
  cotangents ``u`` and P random directions ``v`` in every input group at once (P = 1, 4, 7), and for
  one direction per input group (so that no group hides behind a larger one). Tolerance 1e-10 of
  the sum of the absolute products (the two sum the same products in another order: rounding).
- Central differences of the plain step along each group's direction, with steps ``t`` from 1e-3
  to 1e-7 of the group's scale: the error falls like ``t^2`` (slope 2 between steps where it shows
  above 100x rounding, ``eps |f| / (t |J v|)``) until rounding, the best step within 1e-7
  relative; where the step is linear in the group (velocities, tops, tie targets: ``A`` does not
  depend on them) every step is at rounding.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from tests.support.strings import ALL_ON, make_model, repeated_specs, spec, three_strings

from dmarionette.grad.string_tangent import CONSTANTS, StringStepTangent
from dmarionette.kernels.tangent_directions import direction_minor
from dmarionette.strings.model import StringControl
from dmarionette.strings.rollout import upload_values
from dmarionette.strings.solver import SolverStringImplicit

DT = 1e-3
TOLERANCE = 1e-10
# Away from the kinks: each segment's 1 - d/l and each particle's depth over a rest length at least
# MARGIN from zero; the largest FD step (1e-3 of the scales below: positions 0.1 of a rest length,
# rest lengths their own value) changes 1 - d/l by at most ~3e-3.
MARGIN = 0.008
STATE_GROUPS = ("particle_q", "particle_qd")
CONTROL_GROUPS = ("top_q", "tie_q", "tie_qd")
GROUPS = STATE_GROUPS + CONTROL_GROUPS + ("particle_mass",) + CONSTANTS
LINEAR_GROUPS = ("particle_qd", "top_q", "tie_q", "tie_qd")  # b is linear in them, A independent of them
GUARD_ROWS = 3  # rows after the P directions' outputs, checked unwritten (the padding lanes of the last group)


def _model():
    return make_model(
        three_strings(),
        effects=ALL_ON, requires_grad=True)


def _problem(model):
    """The step's start state and control (NumPy), and each input group's scale."""
    rng = np.random.default_rng(5)
    q = model.initial_positions() + rng.normal(scale=2e-3, size=(model.particle_count, 3))
    q[5:9, 1] = -np.array([0.004, 0.006, 0.008, 0.01])  # the ground string's last four below the ground
    qd = rng.normal(scale=0.2, size=q.shape)
    start = model.string_start_np
    rest = model.string_rest_length.numpy()
    for s in range(model.string_count):
        ratio = 1.0 - rest[s] / np.linalg.norm(np.diff(q[start[s]:start[s + 1]], axis=0), axis=1)
        assert np.min(np.abs(ratio)) > MARGIN, s  # every segment clearly taut or clearly compressed
    assert np.min(ratio) < -0.2  # the slack string is compressed
    depth = q[:, 1] - float(model.ground_height.value)
    assert np.min(np.abs(depth)) > MARGIN * np.min(rest)
    return _with_controls(model, q, qd)


def _with_controls(model, q, qd):
    """The problem of the start state ``q``, ``qd``: the tops and tie targets moved, the ties' velocities,
    and each input group's scale."""
    rest = model.string_rest_length.numpy()
    top = np.array([s.top for s in model.specs]) + np.array([0.002, -0.001, 0.0015])
    tie = model.tie_points() + np.array([0.003, 0.002, -0.001])
    tie_v = np.array([[0.2, -0.1, 0.3]] * model.string_count)
    scale = {"particle_q": 0.1 * np.min(rest), "particle_qd": 0.2, "top_q": np.min(rest), "tie_q": np.min(rest),
             "tie_qd": 0.2, "particle_mass": model.particle_mass.numpy()}
    for name in CONSTANTS:
        scale[name] = np.maximum(getattr(model, name).numpy(), 1e-3 if name != "string_tied" else 1.0)
    return dict(q=q, qd=qd, top=top, tie=tie, tie_v=tie_v), scale


def _shape(model, name):
    if name in STATE_GROUPS:
        return (model.particle_count, 3)
    if name in CONTROL_GROUPS:
        return (model.string_count, 3)
    return (model.particle_count,) if name == "particle_mass" else (model.string_count,)


def _directions(model, scale, groups_per_direction, rng):
    """One dict of input tangents per direction, nonzero in the groups given, scaled per group."""
    out = []
    for groups in groups_per_direction:
        v = {}
        for name in GROUPS:
            shape = _shape(model, name)
            on = name in groups
            w = rng.normal(size=shape) if on else np.zeros(shape)
            v[name] = w * (scale[name][:, None] if np.ndim(scale[name]) and len(shape) == 2 else scale[name])
        out.append(v)
    return out


def _tangent(model, problem, directions, lanes=True, tangent_lanes=None, minor=False):
    """The tangent kernel: (x1', v1', F') per direction, and the step's outputs (the forward: the
    laned step, its factorisation read in the laned layout, or the scalar one; the tangent:
    ``tangent_lanes``, by default the directions in SIMD lanes where supported; ``minor``: the
    particles' tangent arrays, in and out, stored direction-minor, ``tangent_directions.direction_minor``)."""
    solver = SolverStringImplicit(model)
    solver.lanes = lanes
    p = len(directions)
    stepper = StringStepTangent(solver, p, tangent_lanes)
    s0 = model.state(problem["q"], problem["qd"])
    s1 = model.state()
    control = StringControl.from_numpy(model, problem["top"], problem["tie"], problem["tie_v"])

    def stack(name, dtype, minor_layout=False):
        values = np.stack([d[name] for d in directions])
        if not minor_layout:
            return wp.array(values, dtype=dtype, device=model.device)
        a = direction_minor(p, values.shape[1], dtype, model.device)
        upload_values(a, values)
        return a

    vec3 = model.vec3
    consts = wp.array(np.stack([np.stack([d[c] for c in CONSTANTS], axis=-1) for d in directions]),
                      dtype=model.scalar)
    # The outputs: the first P rows of arrays with GUARD_ROWS more (which no direction may write).
    counts = (model.particle_count, model.particle_count, model.string_count)
    # (Direction-minor: the particles' outputs in their own storage, whose padding the last group may write.)
    guarded = [direction_minor(p, n, model.vec3, model.device) if minor and n == model.particle_count
               else wp.zeros((p + GUARD_ROWS, n), dtype=model.vec3, device=model.device) for n in counts]
    out = [a[:p] for a in guarded]
    stepper.step(s0, s1, control, DT, stack("particle_q", vec3, minor), stack("particle_qd", vec3, minor), *out,
                 stack("top_q", vec3), stack("tie_q", vec3), stack("tie_qd", vec3),
                 stack("particle_mass", model.scalar, minor), consts)
    assert all(not np.any(a.numpy()[p:]) for a in guarded), "a tangent written past direction P"  # (major rows)
    return [a.numpy() for a in out], [s1.particle_q.numpy(), s1.particle_qd.numpy(), s1.tie_force.numpy()]


def _adjoint(model, problem, cotangents):
    """The hand adjoint (the step on a tape): every input group's gradient of <u, outputs>."""
    solver = SolverStringImplicit(model)
    s0 = model.state(problem["q"], problem["qd"])
    s1 = model.state()
    control = StringControl.from_numpy(model, problem["top"], problem["tie"], problem["tie_v"])
    for name in ("particle_mass",) + CONSTANTS:
        getattr(model, name).grad.zero_()
    tape = wp.Tape()
    with tape:
        solver.step(s0, s1, control, DT, tape=tape)
    for a, u in zip((s1.particle_q, s1.particle_qd, s1.tie_force), cotangents, strict=True):
        upload_values(a.grad, u)
    tape.backward()
    grads = {"particle_q": s0.particle_q.grad, "particle_qd": s0.particle_qd.grad, "top_q": control.top_q.grad,
             "tie_q": control.tie_q.grad, "tie_qd": control.tie_qd.grad}
    grads.update({name: getattr(model, name).grad for name in ("particle_mass",) + CONSTANTS})
    return {k: v.numpy().copy() for k, v in grads.items()}


def _check_identity(model, problem, scale, groups_per_direction, seed, lanes=True):
    rng = np.random.default_rng(seed)
    directions = _directions(model, scale, groups_per_direction, rng)
    jv, outputs = _tangent(model, problem, directions, lanes)
    u = [rng.normal(size=o.shape) / max(np.max(np.abs(o)), 1e-12) for o in outputs]
    jtu = _adjoint(model, problem, u)
    for k, v in enumerate(directions):
        left_terms = np.concatenate([(ui * jvi[k]).ravel() for ui, jvi in zip(u, jv, strict=True)])
        right_terms = np.concatenate([(jtu[name] * v[name]).ravel() for name in GROUPS])
        left, right = left_terms.sum(), right_terms.sum()
        size = max(np.abs(left_terms).sum(), np.abs(right_terms).sum())
        assert size > 0.0
        gap = abs(left - right) / size
        print(f"direction {k} ({'+'.join(groups_per_direction[k]) if len(groups_per_direction[k]) < 3 else 'all'}): "
              f"<u, Jv> = {left:.6e}, <J^T u, v> = {right:.6e}, gap {gap:.1e} of {size:.2e}")
        assert gap < TOLERANCE


@pytest.mark.parametrize("directions", [1, 4, 7, 9])
def test_tangent_and_adjoint_satisfy_the_dot_product_identity(directions):
    model = _model()
    problem, scale = _problem(model)
    _check_identity(model, problem, scale, [GROUPS] * directions, seed=directions)


@pytest.mark.parametrize("lanes", [True, False], ids=["laned-forward", "scalar-forward"])
def test_tangent_and_adjoint_agree_in_each_input_group(lanes):
    model = _model()
    problem, scale = _problem(model)
    _check_identity(model, problem, scale, [(name,) for name in GROUPS], seed=17, lanes=lanes)


@pytest.mark.parametrize("directions", [1, 3, 4, 7, 9, 12, 16])
def test_laned_and_scalar_tangents_agree(directions):
    """The directions in SIMD lanes (launches of 8, then 4 per lane vector, the last direction
    alone, ``direction_chunks``, each chunk padded up to its lanes; P = 12: 8 + 4, P = 9: 8 + 1)
    against one at a time, every input group in every direction: the same operations in the same
    order (``tangent_directions``; with more than one group of directions per string both take
    the segments' linear maps; where the lanes have one group, P = 3, 4, 7, they take the spring
    tangents instead: another order), so equal up to rounding; asserted to 1e-13 of each output's largest entry per direction
    (rounding through the substitution, a few hundred eps at most). P = 1, 3, 7, 9 have padding
    lanes, which write nothing (``_tangent`` checks the rows after the P outputs stay zero)."""
    model = _model()
    problem, scale = _problem(model)
    rng = np.random.default_rng(23)
    v = _directions(model, scale, [GROUPS] * directions, rng)
    laned, _ = _tangent(model, problem, v, tangent_lanes=True)
    scalar, _ = _tangent(model, problem, v, tangent_lanes=False)
    for name, a, b in zip(("x1'", "v1'", "F'"), laned, scalar):
        assert a.shape == b.shape == (directions, b.shape[1], 3)
        for k in range(directions):
            size = np.max(np.abs(b[k]))
            assert size > 0.0, (name, k)
            assert np.max(np.abs(a[k] - b[k])) <= 1e-13 * size, (name, k, np.max(np.abs(a[k] - b[k])) / size)


@pytest.mark.parametrize("directions", [3, 4, 9, 10, 12, 16])
def test_direction_minor_layout_gives_the_same_tangents(directions):
    """The particles' tangent arrays stored direction-minor (``tangent_directions.direction_minor``:
    each lane group one contiguous load and store, shuffled into lanes) against the leading direction
    axis (per-lane gathers): the same arithmetic on the same values, so equal to the last bit, where
    every lane of a group is a real direction (P = 4, 12, 16) and where the last group has padding
    lanes (P = 3, 10: they read and write the storage's padding; P = 9's last direction runs alone)."""
    model = _model()
    problem, scale = _problem(model)
    v = _directions(model, scale, [GROUPS] * directions, np.random.default_rng(29))
    minor, _ = _tangent(model, problem, v, tangent_lanes=True, minor=True)
    major, _ = _tangent(model, problem, v, tangent_lanes=True)
    for name, a, b in zip(("x1'", "v1'", "F'"), minor, major, strict=True):
        assert np.any(b), name
        assert np.array_equal(a, b), (name, np.max(np.abs(a - b)))


def _laned_model_and_problem():
    """Strings for the string-lanes tangent (``kernels/string_step_tangent_lanes``): the three strings
    repeated 5, 3 and 6 times (groups of 4 + 1, 3, 4 + 2 strings: padding lanes in three groups),
    constants differing per copy, every other copy of the tied string cut; each copy ``i`` of the
    ground string with its last ``i % 4`` particles below the ground (lanes of one group in and out
    of contact), the slack copies compressed."""
    def keywords(s):
        return {k: v for k, v in vars(s).items() if k not in ("name", "stiffness")}

    ground, tied, slack = three_strings()
    model = make_model(repeated_specs([(5, keywords(ground)), (3, keywords(tied)), (6, keywords(slack))],
                                      (0.03, 0.0, -0.02)), effects=ALL_ON, requires_grad=True)
    rng = np.random.default_rng(41)
    q = model.initial_positions() + rng.normal(scale=2e-3, size=(model.particle_count, 3))
    start = model.string_start_np
    for i in range(5):  # the ground string's copies: strings 0 ... 4
        below = i % 4
        if below:
            q[start[i + 1] - below:start[i + 1], 1] = -0.004 * np.arange(1, below + 1)
    return model, _with_controls(model, q, rng.normal(scale=0.2, size=q.shape))


def test_string_lanes_tangent_agrees_with_the_scalar_one():
    """One direction with the strings in SIMD lanes (the laned forward's groups, its factorisation read
    in place; the branches as selects) against the scalar tangent kernel, one thread per string: the
    same operations per lane in the same order (rounding only: the kernel's doc), asserted to 1e-13
    of each output's largest entry, on the three strings (each its own group, three padding lanes)
    and on groups of 4 + 1, 3 and 4 + 2 strings with the ground and the tie on in some lanes only;
    the padding lanes write nothing (``_tangent`` checks the rows after the direction's; the real
    strings' outputs are all compared)."""
    cases = [(_model(), _problem(_model())), _laned_model_and_problem()]
    for model, (problem, scale) in cases:
        assert StringStepTangent(SolverStringImplicit(model), 1).string_lanes
        assert np.any(problem["q"][:, 1] < 0.0) and np.any(model.string_tied.numpy() == 1.0)
        for minor in (False, True):
            v = _directions(model, scale, [GROUPS], np.random.default_rng(31))
            laned, _ = _tangent(model, problem, v, minor=minor)
            scalar, _ = _tangent(model, problem, v, tangent_lanes=False, minor=minor)
            for name, a, b in zip(("x1'", "v1'", "F'"), laned, scalar, strict=True):
                size = np.max(np.abs(b))
                assert size > 0.0, name
                gap = np.max(np.abs(a - b)) / size
                print(f"{model.string_count} strings, minor {minor}, {name}: {gap:.1e}")
                assert gap <= 1e-13, (name, gap)


def test_string_lanes_tangent_and_adjoint_satisfy_the_dot_product_identity():
    """The string-lanes tangent (P = 1) against the hand adjoint on groups with padding lanes, ground
    contact and ties in some lanes: every input group at once, then each group alone."""
    model, (problem, scale) = _laned_model_and_problem()
    _check_identity(model, problem, scale, [GROUPS], seed=43)
    for k, name in enumerate(GROUPS):
        _check_identity(model, problem, scale, [(name,)], seed=47 + k)


def _plain_outputs(model, problem, v, t):
    """The plain step's outputs with every input moved by ``t v`` (constants in the model, restored)."""
    solver = SolverStringImplicit(model)
    saved = {name: getattr(model, name).numpy().copy() for name in ("particle_mass",) + CONSTANTS}
    try:
        for name in saved:
            upload_values(getattr(model, name), saved[name] + t * v[name])
        s0 = model.state(problem["q"] + t * v["particle_q"], problem["qd"] + t * v["particle_qd"])
        s1 = model.state()
        control = StringControl.from_numpy(model, problem["top"] + t * v["top_q"], problem["tie"] + t * v["tie_q"],
                                           problem["tie_v"] + t * v["tie_qd"])
        solver.step(s0, s1, control, DT)
        return [s1.particle_q.numpy().copy(), s1.particle_qd.numpy().copy(), s1.tie_force.numpy().copy()]
    finally:
        for name in saved:
            upload_values(getattr(model, name), saved[name])


STEPS = 10.0 ** -np.arange(3, 8)
# Where the step is linear in a group, the difference quotient's error is rounding alone: eps |f| / t
# relative to |J v|, amplified by the step's arithmetic (the solve's condition); measured 1-30 times.
ROUNDING_FACTOR = 1000.0


def test_tangent_against_central_differences_with_a_step_study():
    """Per input group: the error of central differences against J v over steps 1e-3 .. 1e-7."""
    model = _model()
    problem, scale = _problem(model)
    rng = np.random.default_rng(23)
    directions = _directions(model, scale, [(name,) for name in GROUPS], rng)
    jv, outputs = _tangent(model, problem, directions)
    out_scale = [max(np.max(np.abs(o)), 1e-12) for o in outputs]  # m, m/s, N: each output on its own scale
    flat_outputs = np.concatenate([(o / s).ravel() for o, s in zip(outputs, out_scale, strict=True)])
    for k, name in enumerate(GROUPS):
        exact = np.concatenate([(jvi[k] / s).ravel() for jvi, s in zip(jv, out_scale, strict=True)])
        size = np.max(np.abs(exact))
        assert size > 0.0, name
        errors = []
        for t in STEPS:
            plus = _plain_outputs(model, problem, directions[k], t)
            minus = _plain_outputs(model, problem, directions[k], -t)
            fd = np.concatenate([((a - b) / (2 * t) / s).ravel()
                                 for a, b, s in zip(plus, minus, out_scale, strict=True)])
            errors.append(np.max(np.abs(fd - exact)) / size)
        errors = np.array(errors)
        slope = np.log10(errors[0] / errors[1])  # 2 where the O(t^2) truncation error dominates
        rounding = np.finfo(float).eps * np.max(np.abs(flat_outputs)) / (STEPS * size)
        print(f"{name}: errors {' '.join(f'{e:.1e}' for e in errors)}; slope(1e-3 -> 1e-4) {slope:.2f}; "
              f"error / (eps |f| / (t |Jv|)) {' '.join(f'{e:.0f}' for e in errors / rounding)}")
        assert np.min(errors) < 1e-7, name
        # Every step: at most the t^2 line through the largest step's error, or rounding.
        assert np.all(errors < np.maximum(1.5 * errors[0] * (STEPS / STEPS[0]) ** 2, ROUNDING_FACTOR * rounding)), name
        if name in LINEAR_GROUPS:
            assert np.all(errors < ROUNDING_FACTOR * rounding), name  # linear: rounding at every step
        truncated = errors > 100.0 * rounding  # where the O(t^2) error shows above rounding
        for i in range(len(STEPS) - 1):
            if truncated[i] and truncated[i + 1]:
                assert 1.6 < np.log10(errors[i] / errors[i + 1]) < 2.4, name


def test_float32_tangent_follows_the_float64_one():
    """The kernel built for float32 (the scalar forward: lanes are float64 only) against float64:
    float32 rounding (eps 1.2e-7) amplified by the solve; measured 1.1e-5 of each output's scale."""
    model64 = _model()
    model32 = make_model(model64.specs, effects=model64.effects, precision="float32")
    problem, scale = _problem(model64)
    directions = _directions(model64, scale, [GROUPS] * 2, np.random.default_rng(3))
    jv32, _ = _tangent(model32, problem, directions, lanes=False)
    jv64, _ = _tangent(model64, problem, directions)
    for a, b in zip(jv32, jv64, strict=True):
        gap = np.max(np.abs(a - b)) / np.max(np.abs(b))
        print(f"float32 against float64: {gap:.1e}")
        assert gap < 1e-4


def test_tension_only_springs_are_refused():
    """The tension-only springs' step (an active-set solve) has no tangent: a clear error, not a wrong answer."""
    model = make_model([spec(name="a", particle_count=5)], effects=dataclasses.replace(ALL_ON, tension_only=True))
    with pytest.raises(NotImplementedError, match="tension-only"):
        StringStepTangent(SolverStringImplicit(model), 2)
