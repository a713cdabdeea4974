"""The interleaved forward-mode transformer (``kernels/kernel_tangent``) refuses what it has no rule
for, naming the construct, instead of dropping a term (its rules are checked against the tape in
the tests of the kernels it transforms: tests/articulation/test_*_tangent.py,
tests/marionette/test_*_tangent.py)."""

from __future__ import annotations

import pytest
import warp as wp

from dmarionette.kernels.articulation_tangent import TangentError
from dmarionette.kernels.kernel_tangent import tangent_kernel


@wp.kernel
def eval_normalized(
    # State in:
    body_pos: wp.array(dtype=wp.vec3d),
    # State out:
    out: wp.array(dtype=wp.vec3d),
):
    i = wp.tid()
    out[i] = wp.normalize(body_pos[i])


@wp.kernel
def eval_power(
    # State in:
    body_pos: wp.array(dtype=wp.vec3d),
    # State out:
    out: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    out[i] = body_pos[i][0] ** wp.float64(2.0)


@pytest.mark.parametrize("kernel, construct", [(eval_normalized, "wp.normalize"), (eval_power, "Pow")])
def test_unknown_constructs_raise(kernel, construct):
    with pytest.raises(TangentError, match=construct):
        tangent_kernel(kernel)


def test_inactive_values_need_no_rule():
    """With ``body_pos`` constant (not a tangent name) the same kernel transforms: its tangent output
    is zero and no rule is asked for."""
    tk = tangent_kernel(eval_normalized, frozenset())
    assert tk.tangent_inputs == [] and tk.tangent_outputs == ["out"]
    assert "tan_out[_dir, i] = " in tk.source
