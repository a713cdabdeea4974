"""Forward-mode (tangent) kernel of the bar feedback (``kernels/bar_feedback``: paper eq. 4 for taut
strings and the exact reaction on the bars), transformed by ``kernels/kernel_tangent``.

Dot-product identity against Warp's reverse mode of the same kernel on a ``wp.Tape``
(``tests/support/tangents``: 1e-10 of the sum of the terms' magnitudes), P = 1, 3, 5; float64
strings; internal friction on and off; the printed and the tension-only spring. Strings: one
taut (eq. 4 and the reaction), one slack (reaction only), one on no bar, and one whose first
segment is exactly at its rest length (the tension-only spring's ``max(l - d, 0)`` and its
``l > d`` branch at their kink). Also float32 strings under a float64 bar (the precision
boundary's widening), against the tape at float32 rounding.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.bar_feedback import eval_bar_feedback_kernel
from dmarionette.kernels.string_model_arrays import string_model_arrays_type
from dmarionette.kernels.string_state_arrays import string_state_arrays_type
from tests.support.tangents import assert_dot_product, dot_product_check, struct_value

REST = 0.25


def _case(rng, friction, tension_only, scalar=wp.float64, bar_scalar=None):
    vec = wp.types.vector(3, scalar)
    bar_vec = vec if bar_scalar is None else wp.types.vector(3, bar_scalar)
    bs = scalar if bar_scalar is None else bar_scalar
    counts = [4, 5, 3, 4]
    start = np.cumsum([0] + counts).astype(np.int32)
    q = rng.standard_normal((start[-1], 3)) * 0.3
    q[start[3]:start[4]] = [[0.5, 1.5 - REST * k, 0.0] for k in range(4)]  # segments exactly at rest length
    arr = lambda a, d: wp.array(np.asarray(a), dtype=d, device="cpu")  # noqa: E731
    kernel = eval_bar_feedback_kernel(scalar, friction, tension_only, bar_scalar)
    model = struct_value(string_model_arrays_type(scalar), string_start=arr(start, wp.int32),
                         string_stiffness=arr(rng.uniform(500, 2000, 4), scalar),
                         string_rest_length=arr([REST] * 4, scalar),
                         string_internal_friction=arr(rng.uniform(0.5, 2.0, 4), scalar))
    state = struct_value(string_state_arrays_type(scalar), particle_q=arr(q, vec),
                         particle_qd=arr(rng.standard_normal(q.shape), vec),
                         string_taut=arr([1, 0, 1, 1], wp.int32))
    args = {"model": model, "string_bar": arr([0, 1, -1, 1], wp.int32),
            "feedback_stiffness": bs(300.0), "feedback_damping": bs(2.0), "puppet_weight": bar_vec(0.0, -9.81, 0.0),
            "state_in": state,
            "bar_q": arr(rng.standard_normal((2, 3)), bar_vec), "bar_qd": arr(rng.standard_normal((2, 3)), bar_vec),
            "bar_feedback": wp.zeros(2, dtype=bar_vec, device="cpu"),
            "bar_reaction": wp.zeros(2, dtype=bar_vec, device="cpu")}
    return kernel, 4, args


@pytest.mark.parametrize("P", [1, 3, 5])
@pytest.mark.parametrize("friction", [False, True])
@pytest.mark.parametrize("tension_only", [False, True])
def test_bar_feedback_dot_product(tension_only, friction, P):
    rng = np.random.default_rng(41 + P)
    assert_dot_product(*_case(rng, friction, tension_only), P, rng)


def test_bar_feedback_float32_strings():
    """Float32 strings, float64 bar: the identity holds to float32 rounding (the reaction is evaluated in
    float32 by both the tangent and the tape; 1e-5 of the terms' magnitudes)."""
    rng = np.random.default_rng(43)
    for lhs, rhs, scale in dot_product_check(*_case(rng, True, False, wp.float32, wp.float64), 3, rng):
        assert scale > 0.0 and abs(lhs - rhs) <= 1e-5 * scale, (lhs, rhs, scale)
