"""The interleaved forward-mode transformer (``kernels/kernel_tangent``) refuses what it has no rule
for, naming the construct, instead of dropping a term (its rules are checked against the tape in
the tests of the kernels it transforms: tests/articulation/test_*_tangent.py,
tests/marionette/test_*_tangent.py)."""

from __future__ import annotations

import re

import numpy as np
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


@wp.kernel
def eval_scaled(
    # Model:
    scale: wp.array(dtype=wp.float64),
    # State in:
    body_pos: wp.array(dtype=wp.vec3d),
    # State out:
    out: wp.array(dtype=wp.vec3d),
):
    i = wp.tid()
    out[i] = scale[i] * body_pos[i]


def _scaled_launch_arrays(P: int = 2, n: int = 3):
    scale = wp.array(np.arange(1.0, n + 1.0), dtype=wp.float64, device="cpu")
    pos = wp.array(np.ones((n, 3)), dtype=wp.vec3d, device="cpu")
    out = wp.zeros(n, dtype=wp.vec3d, device="cpu")
    tangents = {"body_pos": wp.array(np.ones((P, n, 3)), dtype=wp.vec3d, device="cpu"),
                "out": wp.zeros((P, n), dtype=wp.vec3d, device="cpu")}
    return {"scale": scale, "body_pos": pos, "out": out}, tangents


def test_launch_takes_arguments_by_name():
    """The primal's arguments by name give what they give in signature order; the tangent of ``out`` is
    ``scale * tan_body_pos`` in every direction."""
    tk = tangent_kernel(eval_scaled)
    assert tk.tangent_inputs == ["body_pos"] and tk.tangent_outputs == ["out"]
    args, tangents = _scaled_launch_arrays()
    tk.launch(3, 2, dict(reversed(args.items())), tangents, "cpu")
    expected = np.repeat(np.arange(1.0, 4.0)[:, None], 3, axis=1)
    np.testing.assert_array_equal(args["out"].numpy(), expected)
    np.testing.assert_array_equal(tangents["out"].numpy(), np.stack([expected, expected]))


@pytest.mark.parametrize("where, change, received", [
    ("tangents", lambda a, t: t.update(body_qd=t["body_pos"]), "'body_qd'"),  # no parameter of the kernel
    ("tangents", lambda a, t: t.pop("body_pos"), "'body_pos'"),  # missing
    ("tangents", lambda a, t: t.update(tan_out=t.pop("out")), "'tan_out'"),  # the generated kernel's name
    ("args", lambda a, t: a.update(scales=a.pop("scale")), "'scales'"),
    ("args", lambda a, t: a.pop("out"), "'out'"),
])
def test_launch_checks_names(where, change, received):
    """An unknown or missing name raises ValueError naming the kernel, the name received and the names
    expected; nothing is launched."""
    tk = tangent_kernel(eval_scaled)
    args, tangents = _scaled_launch_arrays()
    change(args, tangents)
    expected = "['body_pos', 'out']" if where == "tangents" else "['scale', 'body_pos', 'out']"
    with pytest.raises(ValueError, match=re.escape(received)) as info:
        tk.launch(3, 2, args, tangents, "cpu")
    assert "eval_scaled" in str(info.value) and expected in str(info.value)
    assert not args.get("out", tangents.get("out")).numpy().any()


def test_launch_accepts_tangents_of_other_array_parameters():
    """A tangent of an array parameter the tangent kernel does not take (here the constant ``scale``)
    is accepted and unused: one mapping may serve kernels reading different parts of a state."""
    tk = tangent_kernel(eval_scaled)
    args, tangents = _scaled_launch_arrays()
    tangents["scale"] = wp.array(np.full((2, 3), np.nan), dtype=wp.float64, device="cpu")
    tk.launch(3, 2, [args[n] for n in tk.params], tangents, "cpu")
    assert np.isfinite(tangents["out"].numpy()).all()
