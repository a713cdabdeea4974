"""Checks of the interleaved tangent kernels (``kernels/kernel_tangent``) against Warp's reverse
mode of the same kernel and against central finite differences.

The dot-product identity ``<u, J v> = <J^T u, v>``: ``J v`` from the tangent kernel (P
directions ``v`` at once), ``J^T u`` from ``wp.Tape`` on the primal kernel. Both sides are
sums of float64 products, each rounded to ~1e-16 of its size; the tolerance, 1e-10 of the
sum of the absolute values of the terms, leaves room for ~1e5 terms' rounding, far more
than a test kernel has, and is far below any missing or wrong term.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.kernels.kernel_tangent import UNROLL, tangent_kernel

RTOL = 1e-10


def _components(dtype) -> int:
    return int(np.prod(getattr(dtype, "_shape_", ()))) or 1


def _random_like(a: wp.array, rng, lead=()) -> np.ndarray:
    return rng.standard_normal((*lead, *a.shape, _components(a.dtype)))


def _as_array(values: np.ndarray, dtype) -> wp.array:
    """A Warp array from ``(*shape, components)`` values."""
    inner = getattr(dtype, "_shape_", ())
    return wp.array(values.reshape(*values.shape[:-1], *inner), dtype=dtype, device="cpu")


def _numpy(a: wp.array) -> np.ndarray:
    n = a.numpy()
    return n.reshape(*a.shape, _components(a.dtype))


def _is_struct(value) -> bool:
    """A ``wp.struct`` value."""
    return hasattr(value, "_cls") and hasattr(value._cls, "vars")


def array_of(args: dict, name: str) -> wp.array:
    """The array ``name`` of ``args``: an argument, or an array field of a struct argument (a tangent is
    named by its field, ``kernels/kernel_tangent``)."""
    if name in args:
        return args[name]
    for value in args.values():
        if _is_struct(value) and name in value._cls.vars:
            return getattr(value, name)
    raise KeyError(name)


def struct_value(struct_type, **fields):
    """A ``struct_type`` value holding ``fields``, its other array fields empty arrays (Warp's tape
    mirrors every array field of a struct argument with its gradient, so none may be unset)."""
    value = struct_type()
    for name, var in struct_type.vars.items():
        if name in fields:
            setattr(value, name, fields[name])
        elif isinstance(var.type, wp.array):
            setattr(value, name, wp.zeros(0, dtype=var.type.dtype, device="cpu"))
    return value


def copy_args(args: dict, make) -> dict:
    """``args`` with each array, also a struct argument's array field (a new struct), replaced by
    ``make(name, array)`` (``name``: the argument's or the field's)."""
    out = {}
    for n, v in args.items():
        if isinstance(v, wp.array):
            out[n] = make(n, v)
        elif _is_struct(v):
            out[n] = v._cls()
            for f in v._cls.vars:
                x = getattr(v, f)
                setattr(out[n], f, make(f, x) if isinstance(x, wp.array) else x)
        else:
            out[n] = v
    return out


def launch_tangent(kernel, dim, args: dict, tangents: dict, P: int, unroll: int = 0) -> tuple[dict, dict]:
    """Runs the tangent kernel of ``kernel`` on copies of ``args`` (name -> value; outputs hold their
    initial values) with the input tangents ``tangents`` (name -> numpy ``(P, *shape, comps)``; the
    output tangents start at zero; ``unroll``: the layout, :func:`tangent_kernel`'s). Returns (primal
    outputs, output tangents) as numpy arrays."""
    tk = tangent_kernel(kernel, unroll=unroll)
    values = copy_args(args, lambda _n, a: wp.clone(a))
    tan = {n: _as_array(tangents[n], array_of(args, n).dtype) for n in tk.tangent_inputs}
    for n in tk.tangent_outputs:
        a = args[n]
        tan[n] = _as_array(np.zeros((P, *a.shape, _components(a.dtype))), a.dtype)
    tk.launch(dim, P, [values[n] for n in tk.params], tan)
    return ({n: _numpy(values[n]) for n in tk.tangent_outputs},
            {n: tan[n].numpy().reshape(P, *args[n].shape, -1) for n in tk.tangent_outputs})


def dot_product_check(kernel, dim, args: dict, P: int, rng) -> list[tuple[float, float, float]]:
    """The dot-product identity per direction: ``[(<u, J v_p>, <J^T u, v_p>, scale)]``; also asserts
    that the tangent kernel's primal outputs equal the primal kernel's bit for bit, and that the
    unrolled layout (``UNROLL``: the P directions in one block) gives the same primal and tangents bit
    for bit (the same statements on the same values; ``tests/kernels/test_kernel_tangent``)."""
    tk = tangent_kernel(kernel)
    v = {n: _random_like(array_of(args, n), rng, (P,)) for n in tk.tangent_inputs}
    prim, jv = launch_tangent(kernel, dim, args, v, P)
    prim_u, jv_u = launch_tangent(kernel, dim, args, v, P, UNROLL)
    for n in tk.tangent_outputs:
        np.testing.assert_array_equal(prim_u[n], prim[n], err_msg=f"{kernel.key}: unrolled primal output {n}")
        np.testing.assert_array_equal(jv_u[n], jv[n], err_msg=f"{kernel.key}: unrolled tangent of {n}")
    taped = copy_args(args, lambda _n, a: wp.clone(a, requires_grad=a.dtype not in (wp.int32, wp.int64)))
    tape = wp.Tape()
    with tape:
        wp.launch(kernel, dim=dim, inputs=[taped[n] for n in tk.params], device="cpu")
    for n in tk.tangent_outputs:
        np.testing.assert_array_equal(prim[n], _numpy(taped[n]), err_msg=f"{kernel.key}: primal output {n}")
    u = {n: _random_like(args[n], rng) for n in tk.tangent_outputs}
    tape.backward(grads={taped[n]: _as_array(u[n], args[n].dtype) for n in tk.tangent_outputs})
    jtu = {n: _numpy(array_of(taped, n).grad) for n in tk.tangent_inputs}
    out = []
    for p in range(P):
        terms = np.concatenate([(u[n] * jv[n][p]).ravel() for n in tk.tangent_outputs])
        rhs = sum(float(np.sum(jtu[n] * v[n][p])) for n in tk.tangent_inputs)
        out.append((float(terms.sum()), rhs, float(np.abs(terms).sum())))
    return out


def assert_dot_product(kernel, dim, args: dict, P: int, rng) -> None:
    for lhs, rhs, scale in dot_product_check(kernel, dim, args, P, rng):
        assert scale > 0.0, f"{kernel.key}: the tangent is zero (nothing checked)"
        assert abs(lhs - rhs) <= RTOL * scale, f"{kernel.key}: <u, Jv> = {lhs!r}, <J^T u, v> = {rhs!r}"


def central_difference_study(kernel, dim, args: dict, rng, steps=(1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7)):
    """Tangent (one random direction, scaled per input by ``scale``) against central differences of the
    primal kernel at each step: returns ``[(step, max abs error, max abs tangent)]``."""
    tk = tangent_kernel(kernel)
    v = {n: _random_like(array_of(args, n), rng, (1,)) for n in tk.tangent_inputs}
    _, jv = launch_tangent(kernel, dim, args, v, 1)

    def run(eps):
        vals = copy_args(args, lambda n, a: (_as_array(_numpy(a) + eps * v[n][0], a.dtype) if n in tk.tangent_inputs
                                             else wp.clone(a)))
        wp.launch(kernel, dim=dim, inputs=[vals[n] for n in tk.params], device="cpu")
        return {n: _numpy(vals[n]) for n in tk.tangent_outputs}

    study = []
    for eps in steps:
        plus, minus = run(eps), run(-eps)
        err = max(float(np.max(np.abs((plus[n] - minus[n]) / (2 * eps) - jv[n][0]))) for n in tk.tangent_outputs)
        study.append((eps, err, max(float(np.max(np.abs(jv[n][0]))) for n in tk.tangent_outputs)))
    return study


# The best central-difference step balances truncation (C eps^2) and rounding (~u |f| / eps): its error
# is ~u^(2/3) of the scale (u the float64 unit roundoff); 100 times that leaves room for the constants.
FD_RTOL = 100 * np.finfo(np.float64).eps ** (2.0 / 3.0)


def assert_central_differences(study, what: str) -> None:
    """The study of :func:`central_difference_study` (steps a decade apart from 1e-2 down): where the
    truncation error is visible at eps 1e-3 (above 100 :data:`FD_RTOL` of the scale; a kernel nearly
    linear in its inputs has none), it falls like eps^2 to 1e-4 (100x; 50x to 200x allowed); the best
    step's error is within :data:`FD_RTOL` of the tangent's scale."""
    errors = {eps: err for eps, err, _ in study}
    scale = max(s for _, _, s in study)
    if errors[1e-3] > 100 * FD_RTOL * scale:
        ratio = errors[1e-3] / errors[1e-4]
        assert 50.0 <= ratio <= 200.0, f"{what}: the error fell {ratio:.1f}x from eps 1e-3 to 1e-4 (eps^2: 100x)"
    best = min(errors.values())
    assert best <= FD_RTOL * scale, f"{what}: best central difference error {best:.3e} (|Jv| {scale:.3e})"
