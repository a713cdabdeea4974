"""Float64 operations on ``K`` lanes (one value per string), each one packed instruction, each
rounding as the scalar operation it stands for (issue 19, ``docs/simd_probe.md``).

A lane vector is Warp's ``vector(K, float64)``; each operation is a ``wp.func_native`` snippet on
a Clang ``ext_vector_type`` (so the kernel gets packed instructions whatever LLVM's SLP vectorizer
makes of it: with Warp's default CPU flags the SLP vectorizer computed one lane of a step written
with Warp's own ``+``, ``wp.cw_mul`` wrongly, ``docs/simd_probe.md``). CPU only: the snippets are
Clang C++, not CUDA. Used by ``string_step_lanes``; moved here from the probes
(``benchmarks/probe_simd_lanes.py`` imports them; the whole-step probe, since removed, did too).
"""

import functools

from types import SimpleNamespace

import warp as wp

_HEAD = """
    typedef double lanes_t __attribute__((ext_vector_type({lanes})));
    typedef long mask_t __attribute__((ext_vector_type({lanes})));
    lanes_t x, y, z;
    __builtin_memcpy(&x, a.c, sizeof(x));
    """
_LOAD_B = "__builtin_memcpy(&y, b.c, sizeof(y));\n"
_TAIL = """
    decltype(a) r;
    __builtin_memcpy(r.c, &z, sizeof(z));
    return r;
    """


@functools.cache
def lane_fma(lanes: int):
    """``fma(a, b, c)`` lane by lane (one rounding): Warp has no fused multiply-add builtin, and its
    generated code puts each operation in its own statement, so Clang never contracts
    ``cw_mul(a, b) + c``; Warp's ``mat33 * mat33`` is a chain of ``fma`` (``muladd<double>``)."""
    lane = wp.types.vector(lanes, wp.float64)

    @wp.func_native(_HEAD.format(lanes=lanes) + _LOAD_B + """
    lanes_t w;
    __builtin_memcpy(&w, c.c, sizeof(w));
    z = __builtin_elementwise_fma(x, y, w);
    """ + _TAIL)
    def lane_fma(a: lane, b: lane, c: lane) -> lane:
        ...

    return lane_fma


@functools.cache
def native_lane_ops(lanes: int) -> SimpleNamespace:
    """``add, sub, mul, div`` (``a op b``), ``sqrt``, ``max`` (``a > b ? a : b``, Warp's ``wp.max``
    for doubles), ``where_less(x, y, a, b)`` (``a`` where ``x < y``, else ``b``: a blend by the
    comparison's mask), ``fma`` (:func:`lane_fma`)."""
    lane = wp.types.vector(lanes, wp.float64)
    head = _HEAD.format(lanes=lanes)

    def binary(expression):
        @wp.func_native(head + _LOAD_B + f"z = {expression};" + _TAIL)
        def op(a: lane, b: lane) -> lane:
            ...
        return op

    @wp.func_native(head + "z = __builtin_elementwise_sqrt(x);" + _TAIL)
    def sqrt(a: lane) -> lane:
        ...

    @wp.func_native(head + _LOAD_B + """
    lanes_t p, q;
    __builtin_memcpy(&p, c.c, sizeof(p));
    __builtin_memcpy(&q, d.c, sizeof(q));
    mask_t m = x < y;
    z = __builtin_bit_cast(lanes_t, (__builtin_bit_cast(mask_t, p) & m) | (__builtin_bit_cast(mask_t, q) & ~m));
    """ + _TAIL)
    def where_less(a: lane, b: lane, c: lane, d: lane) -> lane:
        ...

    return SimpleNamespace(add=binary("x + y"), sub=binary("x - y"), mul=binary("x * y"), div=binary("x / y"),
                           max=binary("__builtin_bit_cast(lanes_t, (__builtin_bit_cast(mask_t, x) & (x > y))"
                                      " | (__builtin_bit_cast(mask_t, y) & ~(x > y)))"),
                           sqrt=sqrt, where_less=where_less, fma=lane_fma(lanes))
