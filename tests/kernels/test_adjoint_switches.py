"""Warp's adjoints of the differentiated ``wp.func``s at their switching points (issue 13).

Each function is launched in a small kernel on a ``wp.Tape`` at its switch and on both
sides of it (1e-9 and 1e-3 away), and the taped derivative is compared with the analytic
one. Warp's adjoints of the primitives at a tie (measured, Warp 1.19): ``max(x, 0)`` sends
nothing to ``x`` at ``x = 0``, ``min(x, 0)`` sends nothing either, ``abs'(0) = +1``,
``clamp(x, 0, 1)`` passes the derivative at ``x = 0`` but not at ``x = 1``. Built from these,
``max(x, 0) + log(1 + exp(-|x|))`` had the derivative -0.5 at 0 (true: 0.5), which every
smooth contact at rest hit (``body_contact.compute_softplus``, now exact branches; a first
fix with ``log(1 + exp(+-x))`` in two ``where`` branches overflowed in the branch not taken
and gave NaN gradients in the ``chair`` scene, hence the far points here).

Smooth functions must match the analytic derivative at the switch too. Genuine kinks
(the function is continuous but its derivative jumps) are checked on both sides, and at
the kink the tape is checked to give one of the two one-sided derivatives (the side named
in the test); ``docs/gradients.md`` lists them.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.articulation_math import compute_smooth_norm
from dmarionette.kernels.body_contact import (compute_normal_hard, compute_normal_smooth, compute_sigmoid,
                                              compute_softplus)
from dmarionette.kernels.string_spring import string_spring_functions

wp.config.log_level = wp.LOG_WARNING

SPRING = string_spring_functions(wp.float64)
K, C, DELTA, V_EPS = 2000.0, 5.0, 0.5e-3, 0.01


def _normal_force(normal, variable: str):
    """The normal force of ``normal`` (``compute_normal_smooth`` or ``compute_normal_hard``) as a
    function of the gap ``d`` at rest (``variable="d"``) or of the normal velocity ``v_n`` at zero
    gap (``"vn"``)."""
    along_gap = variable == "d"

    @wp.func
    def normal_force(x: wp.float64) -> wp.float64:
        d = wp.float64(0.0)
        vn = wp.float64(0.0)
        if wp.static(along_gap):
            d = x
        else:
            vn = x
        fn, kn, cn = normal(d, vn, wp.float64(K), wp.float64(C), wp.float64(DELTA), wp.float64(V_EPS))
        return fn

    return normal_force


@wp.func
def _smooth_norm(x: wp.float64) -> wp.float64:
    return compute_smooth_norm(wp.vec3d(x, wp.float64(0.5) * x, wp.float64(0.0)))


@wp.func
def _tension(x: wp.float64) -> wp.float64:
    return SPRING.compute_string_tension(wp.float64(1.0) + x, wp.float64(3.0), wp.float64(1.0))


@wp.func
def _geometric_stiffness(x: wp.float64) -> wp.float64:
    """The transverse entry of the printed spring's Jacobian (clamped while compressed)."""
    f, jac, taut = SPRING.compute_string_spring_printed(wp.vec3d(wp.float64(1.0) + x, wp.float64(0.0), wp.float64(0.0)),
                                                        wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0)),
                                                        wp.float64(3.0), wp.float64(1.0))
    return jac[1, 1]


@wp.func
def _ramp_lower(x: wp.float64) -> wp.float64:
    """The ramps of the joint limits and the tie's axial stiffness: ``clamp(x, 0, 1)`` at 0."""
    return wp.clamp(x, wp.float64(0.0), wp.float64(1.0))


@wp.func
def _ramp_upper(x: wp.float64) -> wp.float64:
    return wp.clamp(wp.float64(1.0) + x, wp.float64(0.0), wp.float64(1.0))


def _sig(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # no overflow at |x| = 1e3


def _sp(x):
    return np.logaddexp(0.0, x)


# name -> (function, switch point, analytic derivative, at the kink: None if smooth there, else
# "left"/"right": the side whose derivative the tape gives at the switch)
CASES = {
    "softplus": (compute_softplus, 0.0, lambda x: _sig(x), None),
    "softplus_far": (compute_softplus, 0.0, lambda x: _sig(x), None),  # +-1e3: finite, no overflow
    "sigmoid": (compute_sigmoid, 0.0, lambda x: _sig(x) * (1.0 - _sig(x)), None),
    # smooth contact at zero gap and at rest (the default start): d and v_n
    "normal_smooth_d": (_normal_force(compute_normal_smooth, "d"), 0.0,
                        lambda x: K * _sig(x / DELTA) + C * _sig(x / DELTA) * (1 - _sig(x / DELTA)) / DELTA * V_EPS * np.log(2.0),
                        None),
    "normal_smooth_vn": (_normal_force(compute_normal_smooth, "vn"), 0.0, lambda x: -C * 0.5 * _sig(-x / V_EPS), None),
    # sqrt(|v|^2 + 1e-24) at v = 0: a finite (zero) gradient where a plain norm has none
    "smooth_norm": (_smooth_norm, 0.0, lambda x: 1.25 * x / np.sqrt(1.25 * x * x + 1e-24), None),
    # genuine kinks: hard contact onset, a tension-only segment going slack, the printed
    # spring's clamped geometric stiffness at the rest length
    "normal_hard_d": (_normal_force(compute_normal_hard, "d"), 0.0, lambda x: K * (x > 0), "left"),
    "tension": (_tension, 0.0, lambda x: 3.0 * (x > 0), "left"),
    "ramp_lower": (_ramp_lower, 0.0, lambda x: 1.0 * (x >= 0), "right"),
    "ramp_upper": (_ramp_upper, 0.0, lambda x: 1.0 * (x <= 0), "right"),
    "geometric_stiffness": (_geometric_stiffness, 0.0, lambda x: -3.0 * (1.0 / (1.0 + x) ** 2) * (x > 0), "left"),
}


def _taped(func, xs: np.ndarray) -> np.ndarray:
    @wp.kernel(module="unique")
    def eval_func(x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64)):
        i = wp.tid()
        y[i] = func(x[i])

    x = wp.array(xs, dtype=wp.float64, requires_grad=True)
    y = wp.zeros(len(xs), dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(eval_func, len(xs), inputs=[x], outputs=[y])
    tape.backward(grads={y: wp.ones(len(xs), dtype=wp.float64)})
    return x.grad.numpy()


@pytest.mark.parametrize("name", list(CASES))
def test_adjoint_at_and_around_the_switch(name):
    func, x0, deriv, kink = CASES[name]
    offsets = np.array([-1e-3, -1e-9, 0.0, 1e-9, 1e-3])
    if name.endswith("_far"):
        offsets = np.array([-1e3, -40.0, 40.0, 1e3])
    got = _taped(func, x0 + offsets)
    scale = max(abs(deriv(x0 - 1e-3)), abs(deriv(x0 + 1e-3)), 1.0)
    for off, g in zip(offsets, got):
        if off == 0.0 and kink is not None:
            want = deriv(x0 - 1e-300) if kink == "left" else deriv(x0 + 1e-300)
        elif off == 0.0:
            want = deriv(x0)
        else:
            want = deriv(x0 + off)
        assert abs(g - want) <= 1e-9 * scale, (name, off, g, want)


def test_the_old_softplus_adjoint_was_wrong_at_zero():
    """The formula the contact used before: its taped derivative at exactly 0 is -0.5
    (the test that shows what the fix is for; the value itself is unchanged, bit for bit)."""

    @wp.func
    def old_softplus(x: wp.float64) -> wp.float64:
        return wp.max(x, wp.float64(0.0)) + wp.log(wp.float64(1.0) + wp.exp(-wp.abs(x)))

    assert _taped(old_softplus, np.array([0.0]))[0] == pytest.approx(-0.5)
    xs = np.array([-1e3, -30.0, -1.0, -1e-9, -0.0, 0.0, 1e-9, 1.0, 30.0, 1e3])

    @wp.kernel(module="unique")
    def both(x: wp.array(dtype=wp.float64), a: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64)):
        i = wp.tid()
        a[i] = old_softplus(x[i])
        b[i] = compute_softplus(x[i])

    x = wp.array(xs, dtype=wp.float64)
    a, b = wp.zeros(len(xs), dtype=wp.float64), wp.zeros(len(xs), dtype=wp.float64)
    wp.launch(both, len(xs), inputs=[x], outputs=[a, b])
    assert np.array_equal(a.numpy(), b.numpy())
