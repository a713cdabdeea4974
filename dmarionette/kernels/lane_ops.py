"""Float64 operations on ``K`` lanes (one value per string), each one packed instruction, each
rounding as the scalar operation it stands for (issue 19, ``docs/simd_probe.md``).

A lane vector is Warp's ``vector(K, float64)``; each operation is a ``wp.func_native`` snippet on
a Clang ``ext_vector_type`` (so the kernel gets packed instructions whatever LLVM's SLP vectorizer
makes of it: with Warp's default CPU flags the SLP vectorizer computed one lane of a step written
with Warp's own ``+``, ``wp.cw_mul`` wrongly, ``docs/simd_probe.md``). CPU only: the snippets are
Clang C++, not CUDA. Used by ``string_step_lanes``; moved here from the probes
(``benchmarks/probe_simd_lanes.py`` imports them; the whole-step probe, since removed, did too).

``native_lane_memory``: the laned kernels' gathers from and scatters to the simulator's per-particle
and per-string arrays, as snippets too (Warp's own indexing wraps negative indices, integer work on
every lane of every access; measured in ``docs/lanes_status.md``, "Fewer instructions").
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


# Rows of a lane matrix from (or to) ``K`` array entries: ``a[index[k] + j]``, lane ``k``. Warp's own
# ``a[i]`` also wraps a negative index (``i < 0: i += shape``), integer work (a sign, a mask, an add)
# for every lane of every access that the row loops of the laned kernels pay and spill; these never
# wrap (the kernels' indices are particle and string indices, never negative) and otherwise address
# as Warp does (``data + i * strides[0]``).
_ENTRY = "(({type}*)((char*)a.data + (long)(index.c[k] + j) * (long)a.strides[0]))"


@functools.cache
def native_lane_memory(lanes: int) -> SimpleNamespace:
    """``gather3(a, index, j)``: the ``3 x K`` lane matrix of the ``vec3d`` entries
    ``a[index[k] + j]``; ``gather(a, index, j)``: the lane vector of the ``float64`` entries;
    ``scatter3(a, index, j, real, v)``: ``a[index[k] + j] = v[:, k]`` for the lanes ``k < real``;
    ``scatter_add3``/``scatter_sub3``/``scatter_add``: ``a[...] = a[...] + v[:, k]`` (``-``,
    the ``float64`` one), each rounded once, for the lanes ``k < real``."""
    lane = wp.types.vector(lanes, wp.float64)
    ivec = wp.types.vector(lanes, wp.int32)
    lvec = wp.types.matrix((3, lanes), wp.float64)
    vec3 = wp.vec3d
    entry3 = entry = _ENTRY.format(type="double")

    @wp.func_native(f"""
    wp::mat_t<3, {lanes}, wp::float64> r;
    for (int k = 0; k < {lanes}; ++k) {{
        const double* p = {entry3};
        r.data[0][k] = p[0];
        r.data[1][k] = p[1];
        r.data[2][k] = p[2];
    }}
    return r;
    """)
    def gather3(a: wp.array(dtype=vec3), index: ivec, j: int) -> lvec:
        ...

    @wp.func_native(f"""
    wp::vec_t<{lanes}, wp::float64> r;
    for (int k = 0; k < {lanes}; ++k)
        r.c[k] = *{entry};
    return r;
    """)
    def gather(a: wp.array(dtype=wp.float64), index: ivec, j: int) -> lane:
        ...

    def scatter3_op(op):
        @wp.func_native(f"""
        for (int k = 0; k < {lanes}; ++k) {{
            if (k < real) {{
                double* p = {entry3};
                p[0] = {op.format(i=0)};
                p[1] = {op.format(i=1)};
                p[2] = {op.format(i=2)};
            }}
        }}
        """)
        def scatter3(a: wp.array(dtype=vec3), index: ivec, j: int, real: int, v: lvec):
            ...
        return scatter3

    @wp.func_native(f"""
    for (int k = 0; k < {lanes}; ++k) {{
        if (k < real) {{
            double* p = {entry};
            *p = *p + v.c[k];
        }}
    }}
    """)
    def scatter_add(a: wp.array(dtype=wp.float64), index: ivec, j: int, real: int, v: lane):
        ...

    return SimpleNamespace(gather3=gather3, gather=gather, scatter3=scatter3_op("v.data[{i}][k]"),
                           scatter_add3=scatter3_op("p[{i}] + v.data[{i}][k]"),
                           scatter_sub3=scatter3_op("p[{i}] - v.data[{i}][k]"), scatter_add=scatter_add)


# An entry of a tangent array with a leading direction axis, ``a[d, i]`` (``a[d, s, c]``), direction
# ``d = min(k + l, directions - 1)`` in lane ``l``: the padding lanes past the last direction read the
# last one (finite values, computed, never written).
_DIRECTION = "(k + l < directions ? k + l : directions - 1)"
_ENTRY2 = f"((char*)a.data + (long)({_DIRECTION}) * (long)a.strides[0] + (long)i * (long)a.strides[1])"


@functools.cache
def native_direction_memory(lanes: int) -> SimpleNamespace:
    """Gathers and scatters of ``K`` tangent directions, one per lane, from the tangent arrays with a
    leading direction axis (``string_step_tangent`` with ``lanes``): ``gather3(a, k, directions, i)``,
    the ``3 x K`` lane matrix of ``a[k + l, i]`` (``vec3d``); ``gather(a, k, directions, i)``, the lane
    vector of ``a[k + l, i]`` (``float64``); ``gather_constant(a, k, directions, s, c)``, of
    ``a[k + l, s, c]``; ``scatter3(a, k, directions, i, v)``: ``a[k + l, i] = v[:, l]`` for the lanes
    ``k + l < directions``. A lane past the last direction reads the last one."""
    lane = wp.types.vector(lanes, wp.float64)
    lvec = wp.types.matrix((3, lanes), wp.float64)
    vec3 = wp.vec3d

    @wp.func_native(f"""
    wp::mat_t<3, {lanes}, wp::float64> r;
    for (int l = 0; l < {lanes}; ++l) {{
        const double* p = (const double*){_ENTRY2};
        r.data[0][l] = p[0];
        r.data[1][l] = p[1];
        r.data[2][l] = p[2];
    }}
    return r;
    """)
    def gather3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int) -> lvec:
        ...

    @wp.func_native(f"""
    wp::vec_t<{lanes}, wp::float64> r;
    for (int l = 0; l < {lanes}; ++l)
        r.c[l] = *(const double*){_ENTRY2};
    return r;
    """)
    def gather(a: wp.array2d(dtype=wp.float64), k: int, directions: int, i: int) -> lane:
        ...

    @wp.func_native(f"""
    wp::vec_t<{lanes}, wp::float64> r;
    for (int l = 0; l < {lanes}; ++l)
        r.c[l] = *(const double*)({_ENTRY2} + (long)c * (long)a.strides[2]);
    return r;
    """)
    def gather_constant(a: wp.array3d(dtype=wp.float64), k: int, directions: int, i: int, c: int) -> lane:
        ...

    @wp.func_native(f"""
    for (int l = 0; l < {lanes}; ++l) {{
        if (k + l < directions) {{
            double* p = (double*){_ENTRY2};
            p[0] = v.data[0][l];
            p[1] = v.data[1][l];
            p[2] = v.data[2][l];
        }}
    }}
    """)
    def scatter3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int, v: lvec):
        ...

    return SimpleNamespace(gather3=gather3, gather=gather, gather_constant=gather_constant, scatter3=scatter3)
