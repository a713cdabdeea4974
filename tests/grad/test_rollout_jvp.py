"""Forward-mode sensitivities of whole rollouts (``MarionetteGradient.jvp``, ``grad/rollout_tangent``)
and the JAX wrapper with a custom JVP (``fitting.marionette_rollout_jvp``), issue 13 item 4.

Setup as ``test_gradients_shipped_scenes.py``: the ``hanging`` scene as shipped (limits on, its
bars, strings, constants and ground contact, 30 Hz puppet, 1 kHz strings), 1 s (30 puppet steps,
990 string steps), 10 particles per string and ``[contact] smooth = true``.

- The dot-product identity ``<u, J v> = <J^T u, v>`` against the reverse engine (checkpointed tape),
  one direction per input group (all ten at once: P = 10), ``u`` random over every output; to 1e-10
  of the sum of the terms' magnitudes, as the step's test (``test_marionette_tangent.py``): both modes
  differentiate the same branch of the same floating-point rollout, so they differ by rounding only.
- Central differences (Richardson ``(4 D(e/2) - D(e)) / 3``) of every output along one direction, with a
  step-size study printed, for ``bar_q`` and ``tie_damping`` (the groups whose differences converge over
  the widest window, ``test_gradients_shipped_scenes.py``'s table); checked at two steps a decade apart.
- JAX: ``jax.jvp`` and ``jax.jacfwd`` (under ``jax.jit``) of the forward-mode wrapper equal the engine's
  JVP, and agree with ``jax.vjp`` of the reverse wrapper by the dot-product identity.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from dmarionette.grad.engine import INPUT_FIELDS, OUTPUT_FIELDS, MarionetteGradient
from dmarionette.marionette.solver import MarionetteModel
from tests.support.marionette_gradients import smooth_scene

wp.config.log_level = wp.LOG_WARNING

PARTICLES = 10
CONSTANTS = ("tie_stiffness", "tie_damping", "string_stiffness")
# Scales of the directions (as test_marionette_tangent: each input at a scale where the rollout's
# linearisation means something; the constants relative to their values).
SCALE = {"top_q": 1e-3, "bar_q": 1e-3, "bar_qd": 1e-3, "joint_q0": 1e-2, "joint_qd0": 1e-1,
         "particle_q0": 1e-3, "particle_qd0": 1e-3, **{name: 1e-3 for name in CONSTANTS}}
# Central differences: the steps ``e`` (multiples of the direction above: e = 1 moves the bars 1e-3 m, k_d by
# 1e-3 of its value), the two checked, and the tolerance on |FD - J v| / |J v| over all outputs, 10x the worst
# measured at those steps (printed; measured: bar_q 2.2e-13, 2.1e-12 at 1, 0.1, rounding only, the error times
# e constant: the outputs are linear in the bars' proxies to rounding over this range; tie_damping 8.2e-8,
# 9.1e-8, rounding-limited below 0.1 (9e-7 at 1e-2, 9e-5 at 1e-4), curvature-limited at 10 (0.61)).
FD_STEPS = {"bar_q": (1.0, 1e-1), "tie_damping": (1.0, 1e-1)}
FD_STUDY = (1e1, 1.0, 1e-1, 1e-2, 1e-3, 1e-4)
FD_TOLERANCE = {"bar_q": 3e-11, "tie_damping": 1e-6}


class Hanging:
    def __init__(self):
        scene = smooth_scene("hanging", PARTICLES)
        assert scene.body_effects["joint_limits"]
        self.model = MarionetteModel(scene, optimization_level=0, requires_grad=True)
        self.engine = MarionetteGradient(self.model, int(round(1.0 / self.model.puppet_dt)))
        self.inputs = self.engine.scene_inputs()
        rng = np.random.default_rng(11)
        self.directions = {}
        for name in INPUT_FIELDS:
            v = rng.normal(size=self.engine.input_shapes[name]) * SCALE[name]
            self.directions[name] = v * getattr(self.inputs, name) if name in CONSTANTS else v
        self.u = {name: rng.normal(size=shape) for name, shape in self.engine.output_shapes.items()}

    def group_tangents(self) -> dict[str, np.ndarray]:
        """Direction ``i`` moves input group ``INPUT_FIELDS[i]`` only: ``(P = 10, *shape)`` per field."""
        P = len(INPUT_FIELDS)
        tangents = {name: np.zeros((P, *self.engine.input_shapes[name])) for name in INPUT_FIELDS}
        for i, name in enumerate(INPUT_FIELDS):
            tangents[name][i] = self.directions[name]
        return tangents

    def outputs(self, inputs) -> dict[str, np.ndarray]:
        out = self.engine.forward(inputs)
        return {name: getattr(out, name) for name in OUTPUT_FIELDS}

    def moved(self, name, e):
        return dataclasses.replace(self.inputs, **{name: getattr(self.inputs, name) + e * self.directions[name]})

    def central(self, name, e) -> np.ndarray:
        def d(e):
            plus, minus = self.outputs(self.moved(name, e)), self.outputs(self.moved(name, -e))
            return np.concatenate([((plus[k] - minus[k]) / (2.0 * e)).ravel() for k in OUTPUT_FIELDS])

        return (4.0 * d(e / 2.0) - d(e)) / 3.0


_CACHE = {}


def _hanging() -> Hanging:
    if "hanging" not in _CACHE:
        _CACHE["hanging"] = Hanging()
    return _CACHE["hanging"]


def _flat(d: dict, p=None) -> np.ndarray:
    return np.concatenate([(d[k] if p is None else d[k][p]).ravel() for k in OUTPUT_FIELDS])


def test_rollout_jvp_matches_reverse_mode_every_input_group():
    h = _hanging()
    e = h.engine
    forward = h.outputs(h.inputs)
    out, dot = e.jvp(h.inputs, h.group_tangents())
    for name in OUTPUT_FIELDS:  # the JVP's primal is the plain rollout
        np.testing.assert_array_equal(getattr(out, name), forward[name], err_msg=name)
    grads = e.backward(h.u)
    for i, name in enumerate(INPUT_FIELDS):
        terms_f = np.concatenate([(h.u[k] * dot[k][i]).ravel() for k in OUTPUT_FIELDS])
        terms_r = (getattr(grads, name) * h.directions[name]).ravel()
        scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
        err = abs(terms_f.sum() - terms_r.sum()) / scale
        print(f"{name}: <u, Jv> = {terms_f.sum():.15e}, <J^T u, v> = {terms_r.sum():.15e}, |diff| / scale = {err:.1e}")
        assert np.any(terms_f), name  # every group moves the outputs (nothing checked trivially)
        assert err <= 1e-10, name


@pytest.mark.parametrize("name", list(FD_STEPS))
def test_rollout_jvp_matches_central_differences(name):
    h = _hanging()
    P = 1
    _, dot = h.engine.jvp(h.inputs, {name: h.directions[name][None]})
    assert dot["joint_q"].shape[0] == P
    jv = _flat(dot, 0)
    errors = {step: np.linalg.norm(h.central(name, step) - jv) / np.linalg.norm(jv)
              for step in sorted(set(FD_STUDY) | set(FD_STEPS[name]), reverse=True)}
    print(f"\n{name}: |FD - Jv| / |Jv| by step: " + ", ".join(f"{s:.0e} {err:.1e}" for s, err in errors.items()))
    bad = {s: errors[s] for s in FD_STEPS[name] if errors[s] > FD_TOLERANCE[name]}
    assert not bad, bad


def test_rollout_jvp_refuses_bad_tangents():
    h = _hanging()
    e = h.engine
    shape = e.input_shapes["bar_q"]
    with pytest.raises(ValueError, match=r"tangents\['bar_q'\]: got shape"):
        e.jvp(h.inputs, {"bar_q": np.zeros((2, shape[0] + 1, *shape[1:]))})
    with pytest.raises(ValueError, match="unknown input 'bar'"):
        e.jvp(h.inputs, {"bar": np.zeros((1, *shape))})
    with pytest.raises(ValueError, match="leading"):
        e.jvp(h.inputs, {"bar_q": np.zeros((2, *shape)),
                         "tie_stiffness": np.zeros((3, *e.input_shapes["tie_stiffness"]))})
    with pytest.raises(ValueError, match=r"tangents\['tie_damping'\]: non-finite"):
        e.jvp(h.inputs, {"tie_damping": np.full((1, *e.input_shapes["tie_damping"]), np.nan)})
    with pytest.raises(ValueError, match="RolloutInputs.bar_qd: got shape"):
        e.jvp(dataclasses.replace(h.inputs, bar_qd=np.zeros((1, 3))), {"bar_q": np.zeros((1, *shape))})


def test_rollout_jvp_results_are_the_callers():
    """What ``jvp`` returns is the caller's: a later call (other inputs, other directions) leaves it as it
    was (they were views of the arrays the next call writes, before)."""
    h = _hanging()
    e = h.engine
    first = e.jvp(h.inputs, {"joint_qd0": h.directions["joint_qd0"][None]})
    kept = ({name: np.array(getattr(first[0], name)) for name in OUTPUT_FIELDS},
            {name: np.array(first[1][name]) for name in OUTPUT_FIELDS})
    later = e.jvp(h.moved("top_q", 10.0), {"joint_qd0": 2.0 * h.directions["joint_qd0"][None]})
    for name in OUTPUT_FIELDS:
        assert not np.array_equal(getattr(later[0], name), kept[0][name]), name  # the later call wrote others
        assert not np.array_equal(later[1][name], kept[1][name]), name
        np.testing.assert_array_equal(getattr(first[0], name), kept[0][name], err_msg=name)
        np.testing.assert_array_equal(first[1][name], kept[1][name], err_msg=name)


def test_jax_forward_mode_matches_engine_and_reverse_mode():
    jax = pytest.importorskip("jax")
    from fitting.rollout import marionette_rollout, marionette_rollout_jvp

    h = _hanging()
    e = h.engine
    x = {name: getattr(h.inputs, name) for name in INPUT_FIELDS}
    names = ("bar_q", "tie_damping", "joint_qd0")
    f_fwd, f_rev = marionette_rollout_jvp(e), marionette_rollout(e)
    v = {name: np.zeros(e.input_shapes[name]) for name in INPUT_FIELDS}
    for name in names:
        v[name] = h.directions[name]
    # JAX dispatches asynchronously and the callback runs on another thread: wait for it before using the
    # engine directly (one engine is one set of Warp arrays)
    out, jv = jax.block_until_ready(jax.jit(lambda x, v: jax.jvp(f_fwd, (x,), (v,)))(x, v))
    _, want = e.jvp(h.inputs, {name: v[name][None] for name in names})
    for name in OUTPUT_FIELDS:
        np.testing.assert_allclose(np.asarray(jv[name]), want[name][0], rtol=0, atol=0, err_msg=name)
    # jax.jacfwd along every string's tie damping: one host call with P = S directions (vmap_method="expand_dims")
    def along_damping(k_d):
        return f_fwd({**x, "tie_damping": k_d})

    strings = e.input_shapes["tie_damping"][0]
    calls = []
    jvp = e.jvp

    def counted(inputs, tangents):
        calls.append({name: np.shape(t)[0] for name, t in tangents.items()})
        return jvp(inputs, tangents)

    e.jvp = counted  # the wrapper calls the engine's attribute
    try:
        jac = jax.block_until_ready(jax.jit(jax.jacfwd(along_damping))(x["tie_damping"]))
    finally:
        del e.jvp
    assert len(calls) == 1 and set(calls[0].values()) == {strings}, calls  # one host call, all directions
    _, basis = e.jvp(h.inputs, {"tie_damping": np.eye(strings)})
    for name in OUTPUT_FIELDS:
        np.testing.assert_allclose(np.moveaxis(np.asarray(jac[name]), -1, 0), basis[name], rtol=0, atol=0,
                                   err_msg=name)
    # jax.linearize: the linear map at x, evaluated along v
    _, f_lin = jax.linearize(f_fwd, x)
    lin = jax.block_until_ready(f_lin(v))
    for name in OUTPUT_FIELDS:
        np.testing.assert_allclose(np.asarray(lin[name]), want[name][0], rtol=0, atol=0, err_msg=name)
    # against jax.vjp of the reverse wrapper: <u, J v> = <J^T u, v>
    _, pullback = jax.vjp(f_rev, x)
    (g,) = pullback({name: h.u[name] for name in OUTPUT_FIELDS})
    terms_f = np.concatenate([(h.u[k] * np.asarray(jv[k])).ravel() for k in OUTPUT_FIELDS])
    terms_r = np.concatenate([(np.asarray(g[k]) * v[k]).ravel() for k in names])
    scale = max(np.abs(terms_f).sum(), np.abs(terms_r).sum())
    print(f"\njax: <u, Jv> = {terms_f.sum():.15e}, <J^T u, v> = {terms_r.sum():.15e}")
    assert abs(terms_f.sum() - terms_r.sum()) <= 1e-10 * scale


def test_rollout_jvp_refuses_several_worlds():
    h = _hanging()
    scene = h.model.scene
    model = MarionetteModel.from_scenes([scene, scene], optimization_level=0, requires_grad=True)
    engine = MarionetteGradient(model, 1)
    inputs = engine.scene_inputs()
    with pytest.raises(ValueError, match="2 worlds"):
        engine.jvp(inputs, {"bar_q": np.zeros((1, *engine.input_shapes["bar_q"]))})
    from fitting.rollout import marionette_rollout_jvp

    with pytest.raises(ValueError, match="2 worlds"):
        marionette_rollout_jvp(engine)
