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
from tests.support.tangents import assert_dot_product, launch_tangent


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


# ---------------------------------------------------------------- the unrolled layout (``unroll``)


def _run_layout(tk, dim, args, tangents_in, P):
    """Primal outputs and output tangents (numpy) of one launch of ``tk`` on copies of ``args``."""
    values = {n: (wp.clone(v) if isinstance(v, wp.array) else v) for n, v in args.items()}
    tan = {n: wp.array(tangents_in[n], dtype=args[n].dtype, device="cpu") for n in tk.tangent_inputs}
    tan.update({n: wp.zeros((P, *args[n].shape), dtype=args[n].dtype, device="cpu") for n in tk.tangent_outputs})
    tk.launch(dim, P, values, tan, "cpu")
    return ({n: values[n].numpy() for n in tk.tangent_outputs}, {n: tan[n].numpy() for n in tk.tangent_outputs})


@wp.func
def compute_pair(x: wp.vec3d, k: wp.float64):
    """Two results, a branch on the primal and an element write of a local vector."""
    y = x
    if x[0] > wp.float64(0.0):
        y[1] = k * x[0] * x[2]
    return wp.length(y), wp.cross(x, y)


@wp.kernel
def eval_mixed(
    # Model:
    point_body: wp.array(dtype=wp.int32),
    # State in:
    body_pos: wp.array(dtype=wp.vec3d),
    body_v: wp.array(dtype=wp.vec3d),
    # State out:
    out: wp.array(dtype=wp.vec3d),
    total: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    acc = wp.vec3d()
    s = wp.float64(0.0)
    for j in range(point_body[i]):  # a loop of data-dependent trip count, carrying active values
        r, c = compute_pair(body_pos[i] + wp.float64(j) * body_v[i], wp.float64(0.5))
        acc += c
        s = s + wp.max(r, wp.float64(0.5))
    if s > wp.float64(2.5):
        return
    out[i] = acc
    wp.atomic_add(total, 0, s * s)


@pytest.mark.parametrize("P, unroll", [(6, 3), (4, 2), (5, 8), (1, 8)])
def test_unrolled_layout_matches_the_one_direction_layout(P, unroll):
    """The unrolled layout (primal once per block of ``width`` directions, each tangent statement once
    per direction) against the one-direction layout, on a kernel with each construct the
    transformation keeps (a loop whose trip count is data, carrying active values; a function of two
    results with a branch and an element write; an early return; a switch; an atomic add of an output
    both accumulate): the primal outputs bit for bit (the same statements on the same values, written
    by the first block only) and the tangents bit for bit too (each direction's tangent statements are
    the same expressions on the same primal values, only placed in one thread). The kernels the rollout
    JVP runs are compared likewise in their dot-product tests (``tests/support/tangents``). P = 6 with
    unroll 3 and P = 4 with unroll 2: two blocks each."""
    n = 7
    rng = np.random.default_rng(P)
    args = {"point_body": wp.array(np.array([0, 1, 2, 3, 1, 2, 3], dtype=np.int32), dtype=wp.int32, device="cpu"),
            "body_pos": wp.array(rng.standard_normal((n, 3)) * 0.4, dtype=wp.vec3d, device="cpu"),
            "body_v": wp.array(rng.standard_normal((n, 3)) * 0.2, dtype=wp.vec3d, device="cpu"),
            "out": wp.zeros(n, dtype=wp.vec3d, device="cpu"), "total": wp.zeros(1, dtype=wp.float64, device="cpu")}
    old, new = tangent_kernel(eval_mixed), tangent_kernel(eval_mixed, unroll=unroll)
    assert old.arguments == new.arguments and new.width(P) == min(unroll, P)
    v = {name: rng.standard_normal((P, n, 3)) for name in old.tangent_inputs}
    prim_old, tan_old = _run_layout(old, n, args, v, P)
    prim_new, tan_new = _run_layout(new, n, args, v, P)
    for name in old.tangent_outputs:
        np.testing.assert_array_equal(prim_new[name], prim_old[name], err_msg=f"primal {name}")
        assert np.abs(tan_old[name]).max() > 0.0, f"tangent {name} is zero (nothing compared)"
        np.testing.assert_array_equal(tan_new[name], tan_old[name], err_msg=f"tangent {name}")


def test_unrolled_width():
    """The directions per thread: the largest divisor of P up to ``unroll`` (0: the one-direction layout)."""
    tk = tangent_kernel(eval_scaled, unroll=8)
    assert [tk.width(p) for p in (1, 4, 5, 12, 16, 13, 24)] == [1, 4, 5, 6, 8, 1, 8]
    assert tangent_kernel(eval_scaled).width(16) is None
    assert "_blk, i = wp.tid()" in tk.source and "tan_out[_dir_d7, i] = " in tk.source


# ---------------------------------------------------------------- struct arguments


@wp.struct
class PullModel:
    """Constants of ``eval_pull``: an array field with a tangent name (``string_stiffness``), one
    without (``string_taut_distance``), an integer array and a scalar."""

    string_start: wp.array(dtype=wp.int32)
    string_stiffness: wp.array(dtype=wp.float64)
    string_taut_distance: wp.array(dtype=wp.float64)
    scale: wp.float64


@wp.struct
class PullState:
    """The state ``eval_pull`` reads: ``particle_q`` (read, a tangent name) and ``particle_qd`` (a
    tangent name, but not read: no tangent)."""

    particle_q: wp.array(dtype=wp.vec3d)
    particle_qd: wp.array(dtype=wp.vec3d)


@wp.kernel
def eval_pull(
    # Model:
    model: PullModel,
    # State in:
    state_in: PullState,
    # State out:
    out: wp.array(dtype=wp.vec3d),
    total: wp.array(dtype=wp.vec3d),
):
    s = wp.tid()
    first = model.string_start[s]
    last = model.string_start[s + 1] - 1
    d = state_in.particle_q[last] - state_in.particle_q[first]
    f = model.scale * model.string_stiffness[s] * (wp.length(d) - model.string_taut_distance[s]) * d
    out[s] = f
    wp.atomic_add(total, 0, wp.float64(0.5) * f)


@wp.kernel
def eval_pull_arrays(
    # Model:
    string_start: wp.array(dtype=wp.int32),
    string_stiffness: wp.array(dtype=wp.float64),
    string_taut_distance: wp.array(dtype=wp.float64),
    scale: wp.float64,
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    # State out:
    out: wp.array(dtype=wp.vec3d),
    total: wp.array(dtype=wp.vec3d),
):
    s = wp.tid()
    first = string_start[s]
    last = string_start[s + 1] - 1
    d = particle_q[last] - particle_q[first]
    f = scale * string_stiffness[s] * (wp.length(d) - string_taut_distance[s]) * d
    out[s] = f
    wp.atomic_add(total, 0, wp.float64(0.5) * f)


def _pull_args(rng) -> tuple[dict, dict]:
    """(struct arguments of ``eval_pull``, the same arrays one by one for ``eval_pull_arrays``)."""
    arr = lambda a, d: wp.array(np.asarray(a), dtype=d, device="cpu")  # noqa: E731
    flat = {"string_start": arr([0, 3, 7, 9], wp.int32), "string_stiffness": arr(rng.uniform(1.0, 2.0, 3), wp.float64),
            "string_taut_distance": arr(rng.uniform(0.1, 0.5, 3), wp.float64), "scale": wp.float64(0.75),
            "particle_q": arr(rng.standard_normal((9, 3)), wp.vec3d),
            "particle_qd": arr(rng.standard_normal((9, 3)), wp.vec3d),
            "out": wp.zeros(3, dtype=wp.vec3d, device="cpu"), "total": wp.zeros(1, dtype=wp.vec3d, device="cpu")}
    model, state = PullModel(), PullState()
    for name in ("string_start", "string_stiffness", "string_taut_distance", "scale"):
        setattr(model, name, flat[name])
    for name in ("particle_q", "particle_qd"):
        setattr(state, name, flat[name])
    flat.pop("particle_qd")  # eval_pull_arrays takes only what it reads
    return {"model": model, "state_in": state, "out": flat["out"], "total": flat["total"]}, flat


@pytest.mark.parametrize("P, unroll", [(3, 0), (6, 3), (5, 8)])
def test_struct_arguments_match_the_arrays_one_by_one(P, unroll):
    """A kernel taking its arrays in structs: the array fields it reads whose names are tangent names get
    tangents, named by their fields (``string_stiffness``, ``particle_q``), in the order of the kernel
    taking the same arrays one by one; the rest are constants (``string_taut_distance``, the integer
    layout, the scalar; ``particle_qd``, not read, has none). Primal outputs and tangents equal that
    kernel's bit for bit in both layouts (the same statements on the same values)."""
    rng = np.random.default_rng(7 + P)
    args, flat = _pull_args(rng)
    structs, arrays = tangent_kernel(eval_pull, unroll=unroll), tangent_kernel(eval_pull_arrays, unroll=unroll)
    assert structs.tangent_inputs == arrays.tangent_inputs == ["string_stiffness", "particle_q"]
    assert structs.tangent_outputs == arrays.tangent_outputs == ["out", "total"]
    v = {"string_stiffness": rng.standard_normal((P, 3, 1)), "particle_q": rng.standard_normal((P, 9, 3))}
    prim_s, tan_s = launch_tangent(eval_pull, 3, args, v, P, unroll)
    prim_a, tan_a = launch_tangent(eval_pull_arrays, 3, flat, v, P, unroll)
    for name in ("out", "total"):
        assert np.abs(tan_a[name]).max() > 0.0, f"tangent {name} is zero (nothing compared)"
        np.testing.assert_array_equal(prim_s[name], prim_a[name], err_msg=f"primal {name}")
        np.testing.assert_array_equal(tan_s[name], tan_a[name], err_msg=f"tangent {name}")


@pytest.mark.parametrize("P", [1, 4])
def test_struct_arguments_dot_product(P):
    """The dot-product identity against Warp's tape on the struct kernel (the tape reaches the struct's
    array fields' gradients)."""
    rng = np.random.default_rng(11 + P)
    args, _flat = _pull_args(rng)
    assert_dot_product(eval_pull, 3, args, P, rng)


def test_struct_fields_as_constants():
    """With no tangent names, a struct's array fields are constants: no tangent inputs, a zero tangent."""
    tk = tangent_kernel(eval_pull, frozenset())
    assert tk.tangent_inputs == [] and tk.tangent_outputs == ["out", "total"]
    assert "tan_out[_dir, s] = " in tk.source and "tan_particle_q" not in tk.source


@wp.kernel
def eval_struct_write(
    # State in:
    model: PullModel,
    # State out:
    state_out: PullState,
):
    i = wp.tid()
    state_out.particle_q[i] = model.string_stiffness[i] * state_out.particle_qd[i]


@wp.kernel
def eval_field_clash(
    # State in:
    model: PullModel,
    string_stiffness: wp.array(dtype=wp.float64),
    # State out:
    out: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    out[i] = model.string_stiffness[i] * string_stiffness[i]


@pytest.mark.parametrize("kernel, construct", [(eval_struct_write, "assignment target"),
                                               (eval_field_clash, "the name of another parameter")])
def test_struct_constructs_raise(kernel, construct):
    """A write into a struct's array field (its tangent would be lost) and a field named like another
    parameter (tangents are named by field) raise, naming the construct."""
    with pytest.raises(TangentError, match=construct):
        tangent_kernel(kernel)
