"""The values of the tangent-linear kernels: one direction per value, or ``K`` directions in SIMD lanes.

A tangent kernel loops over its P directions; written against this namespace, one kernel body
serves both layouts (``string_step_tangent``, issue 13 item 4):

- ``lanes = 1`` (any float type, CPU or CUDA): a tangent scalar is a ``scalar``, a tangent vector a
  ``vec3``; the loop steps by one direction; every function is the Warp operation it names.
- ``lanes = K`` (float64, CPU only: Clang C++ snippets, ``lane_ops``' style): a tangent scalar is a
  ``vector(K, float64)`` (lane ``l``: direction ``k + l``), a tangent vector a ``3 x K`` matrix
  (column ``l``: direction ``k + l``; row ``i``, ``v[i]``, component ``i`` of the K directions); the
  loop steps by K directions, the last group padded (its padding lanes read the last direction,
  are computed and never written, ``lane_ops.native_direction_memory``). Each arithmetic function
  is a snippet on Clang ``ext_vector_type`` values, so that the kernel gets packed instructions:
  written with Warp's own operators on ``vector(4)``/``mat(3, 4)``, the string tangent compiled to
  ~1,250 scalar and ~30 packed AVX2 operations and ran no faster than one direction at a time
  (measured, ``bench_string_tangent``); with these, ~490 packed and ~70 scalar. The primal values
  stay scalars, ``vec3`` and ``mat33``.

Both give the same names, each the scalar operation it stands for (one rounding per operation, in
the order written): ``TS``, ``TV`` (the types, also the zero constructors ``TS(zero)``,
``TV(zero)``), ``step`` (directions per value), ``load(a, k, directions, i)`` (``a[k, i]`` of a
``(P, n)`` scalar array), ``load_constant(a, k, directions, i, c)`` (``a[k, i, c]``), ``load3`` and
``store3(a, k, directions, i, v)`` (of a ``(P, n)`` vec3 array; the store writes the real directions
only; with ``minor``, of a direction-minor one, :func:`direction_minor`, whose storage's padding
the padding lanes write), ``sload3`` and ``sstore3`` (the same, always of an array with a leading
direction axis); on tangent vectors ``vadd(a, b)``,
``vsub(a, b)``, ``vneg(a)``, ``vscl(c, a)`` (``c`` a primal scalar), on tangent scalars ``sadd``,
``ssub``, ``sneg``, ``sscl``; ``outer(v, a)`` (the primal vector ``v`` times the tangent scalar
``a``), ``dot(u, r)`` (the primal ``u`` dotted with the tangent vector ``r``), ``mat(m, r)`` (the
primal ``mat33`` times ``r``), ``tvec(a, b, c)`` (the tangent vector of three tangent scalars,
component-wise).
"""

import functools

from types import SimpleNamespace
from typing import Any

import warp as wp

from .lane_ops import native_direction_memory

__all__ = ["MINOR_PADDING", "direction_minor", "is_direction_minor", "tangent_directions"]


# The direction-minor arrays' storage holds a multiple of this many directions (the widest lane vector),
# so that a last lane group with padding lanes also loads and stores contiguously (into the padding).
MINOR_PADDING = 8


def direction_minor(directions: int, count: int, dtype, device) -> wp.array:
    """A zero ``(P, count)`` tangent array (``P = directions``) stored direction-minor: a view of the
    first P rows of the ``(count, P')`` array's transpose (``P'``: P rounded up to a multiple of
    :data:`MINOR_PADDING`), so that the directions of one entry are contiguous (strides ``(size, P'
    size)``). Any kernel indexes it as ``a[k, i]``; the lane loads of :func:`tangent_directions` with
    ``minor`` read a group of ``K`` directions of one entry as contiguous lane vectors (no gather),
    and a last group's padding lanes read and write the storage past P (scratch, never read as a
    direction)."""
    padded = -(-directions // MINOR_PADDING) * MINOR_PADDING
    return wp.zeros((count, padded), dtype=dtype, device=device).transpose()[:directions]


@functools.cache
def tangent_directions(scalar, lanes: int = 1, minor: bool = False) -> SimpleNamespace:
    """The namespace of the module doc for a float type and ``lanes`` directions per value.
    ``minor`` (lanes only): ``load``, ``load3`` and ``store3`` take direction-minor arrays
    (:func:`direction_minor`) with room for every lane group (``k + lanes`` directions: real or
    padding): one contiguous transfer per group, no gather, the padding lanes' values written into
    the padding; the caller checks both (:func:`is_direction_minor`)."""
    if lanes == 1:
        return _scalar_directions(scalar)
    if scalar is not wp.float64:
        raise TypeError(f"tangent directions in lanes: float64 only (the lane snippets), got {scalar}")
    return _lane_directions(lanes, minor)


def is_direction_minor(a: wp.array, first: int = 0, lanes: int = 1) -> bool:
    """Whether the ``(P, n)`` array ``a``'s directions are contiguous (:func:`direction_minor`'s layout)
    with room for lane groups of ``lanes`` directions from direction ``first`` on: the directions
    ``first ... first + lanes - 1`` real (``< P``) or in its storage's padding."""
    size = wp.types.type_size_in_bytes(a.dtype)
    if a.strides[0] != size:
        return False
    return first + lanes <= max(a.shape[0], a.strides[1] // size if a.ndim > 1 and a.shape[1] > 1 else 0)


def _scalar_directions(scalar) -> SimpleNamespace:
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def load(a: wp.array2d(dtype=scalar), k: int, directions: int, i: int):
        return a[k, i]

    @wp.func
    def load_constant(a: wp.array3d(dtype=scalar), k: int, directions: int, i: int, c: int):
        return a[k, i, c]

    @wp.func
    def load3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int):
        return a[k, i]

    @wp.func
    def store3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int, v: vec3):
        a[k, i] = v

    @wp.func
    def outer(v: vec3, a: scalar):
        return a * v

    @wp.func
    def dot(u: vec3, r: vec3):
        return wp.dot(u, r)

    @wp.func
    def mat(m: mat33, r: vec3):
        return m * r

    @wp.func
    def tvec(a: scalar, b: scalar, c: scalar):
        return vec3(a, b, c)

    return SimpleNamespace(TS=scalar, TV=vec3, step=1, load=load, load_constant=load_constant, load3=load3,
                           store3=store3, sload3=load3, sstore3=store3, vadd=_add, vsub=_sub, vneg=_neg,
                           vscl=_scale, sadd=_add, ssub=_sub, sneg=_neg, sscl=_scale, outer=outer, dot=dot, mat=mat,
                           tvec=tvec)


# One direction per value: a tangent scalar's and a tangent vector's sum, difference, negation and
# product with a primal scalar are Warp's own operators, one function each for both (generic).


@wp.func
def _add(a: Any, b: Any):
    return a + b


@wp.func
def _sub(a: Any, b: Any):
    return a - b


@wp.func
def _neg(a: Any):
    return -a


@wp.func
def _scale(c: Any, a: Any):
    return c * a


# Clang vector snippets (``lane_ops``' style): a tangent scalar's K lanes, a tangent vector's three rows.
_TYPES = """
    typedef double lanes_t __attribute__((ext_vector_type({lanes})));
    """
_S_IN = "lanes_t {name}; __builtin_memcpy(&{name}, {arg}.c, sizeof({name}));\n"
_S_OUT = """
    wp::vec_t<{lanes}, wp::float64> ret;
    __builtin_memcpy(ret.c, &z, sizeof(z));
    return ret;
    """
_V_IN = "lanes_t {name}[3]; for (int i = 0; i < 3; ++i) __builtin_memcpy(&{name}[i], {arg}.data[i], sizeof(lanes_t));\n"
_V_OUT = """
    wp::mat_t<3, {lanes}, wp::float64> ret;
    for (int i = 0; i < 3; ++i) __builtin_memcpy(ret.data[i], &z[i], sizeof(lanes_t));
    return ret;
    """


def _lane_directions(lanes: int, minor_layout: bool) -> SimpleNamespace:
    f64 = wp.float64
    lane = wp.types.vector(lanes, f64)
    lvec = wp.types.matrix((3, lanes), f64)
    vec3 = wp.vec3d
    mem = native_direction_memory(lanes)
    minor = _minor_memory(lanes)
    MINOR = minor_layout
    head = _TYPES.format(lanes=lanes)
    s_out = _S_OUT.format(lanes=lanes)
    v_out = _V_OUT.format(lanes=lanes)

    def s_in(*args):
        return "".join(_S_IN.format(name=n, arg=a) for n, a in args)

    def v_in(*args):
        return "".join(_V_IN.format(name=n, arg=a) for n, a in args)

    rows = "lanes_t z[3]; for (int i = 0; i < 3; ++i) z[i] = {};\n"

    @wp.func
    def load(a: wp.array2d(dtype=f64), k: int, directions: int, i: int):
        if wp.static(MINOR):
            return minor.load(a, k, i)
        else:
            return mem.gather(a, k, directions, i)

    @wp.func
    def load_constant(a: wp.array3d(dtype=f64), k: int, directions: int, i: int, c: int):
        return mem.gather_constant(a, k, directions, i, c)

    @wp.func
    def load3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int):
        if wp.static(MINOR):
            return minor.load3(a, k, i)
        else:
            return mem.gather3(a, k, directions, i)

    @wp.func
    def store3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int, v: lvec):
        if wp.static(MINOR):
            minor.store3(a, k, i, v)
        else:
            mem.scatter3(a, k, directions, i, v)

    @wp.func_native(head + v_in(("x", "a"), ("y", "b")) + rows.format("x[i] + y[i]") + v_out)
    def vadd(a: lvec, b: lvec) -> lvec:
        ...

    @wp.func_native(head + v_in(("x", "a"), ("y", "b")) + rows.format("x[i] - y[i]") + v_out)
    def vsub(a: lvec, b: lvec) -> lvec:
        ...

    @wp.func_native(head + v_in(("x", "a")) + rows.format("-x[i]") + v_out)
    def vneg(a: lvec) -> lvec:
        ...

    @wp.func_native(head + v_in(("x", "a")) + rows.format("c * x[i]") + v_out)
    def vscl(c: f64, a: lvec) -> lvec:
        ...

    @wp.func_native(head + s_in(("x", "a"), ("y", "b")) + "lanes_t z = x + y;" + s_out)
    def sadd(a: lane, b: lane) -> lane:
        ...

    @wp.func_native(head + s_in(("x", "a"), ("y", "b")) + "lanes_t z = x - y;" + s_out)
    def ssub(a: lane, b: lane) -> lane:
        ...

    @wp.func_native(head + s_in(("x", "a")) + "lanes_t z = -x;" + s_out)
    def sneg(a: lane) -> lane:
        ...

    @wp.func_native(head + s_in(("x", "a")) + "lanes_t z = c * x;" + s_out)
    def sscl(c: f64, a: lane) -> lane:
        ...

    @wp.func_native(head + s_in(("x", "a")) + rows.format("v.c[i] * x") + v_out)
    def outer(v: vec3, a: lane) -> lvec:
        ...

    @wp.func_native(head + v_in(("x", "r")) + "lanes_t z = u.c[0] * x[0] + u.c[1] * x[1] + u.c[2] * x[2];" + s_out)
    def dot(u: vec3, r: lvec) -> lane:
        ...

    @wp.func_native(head + v_in(("x", "r"))
                    + rows.format("m.data[i][0] * x[0] + m.data[i][1] * x[1] + m.data[i][2] * x[2]") + v_out)
    def mat(m: wp.mat33d, r: lvec) -> lvec:
        ...

    @wp.func
    def tvec(a: lane, b: lane, c: lane):
        return wp.matrix_from_rows(a, b, c)

    return SimpleNamespace(TS=lane, TV=lvec, step=lanes, load=load, load_constant=load_constant, load3=load3,
                           store3=store3, sload3=mem.gather3, sstore3=mem.scatter3, vadd=vadd, vsub=vsub,
                           vneg=vneg, vscl=vscl, sadd=sadd, ssub=ssub, sneg=sneg, sscl=sscl, outer=outer, dot=dot,
                           mat=mat, tvec=tvec)


# Direction-minor arrays (:func:`direction_minor`): the ``K`` directions ``k ... k + K - 1`` of entry
# ``i`` are ``3 K`` contiguous doubles ``x_0 y_0 z_0 x_1 ...``, loaded as ``3 K / 4`` 4-wide vectors and
# transposed into the lane matrix's rows by shuffles (and back for the store); a last group's padding
# lanes are the storage's padding (``direction_minor``). The layout is a static choice of the kernel
# (a runtime test per transfer measured slower than the gathers it saved).
_MINOR_ENTRY = "((char*)a.data + (long)k * (long)a.strides[0] + (long)i * (long)a.strides[1])"
_QUAD = "typedef double quad_t __attribute__((ext_vector_type(4)));\n"


@functools.cache
def _minor_memory(lanes: int) -> SimpleNamespace:
    """``load3(a, k, i)``, ``store3(a, k, i, v)``, ``load(a, k, i)``: the direction-minor transfers
    (each real lane the value the gather would read; :func:`direction_minor`)."""
    lane = wp.types.vector(lanes, wp.float64)
    lvec = wp.types.matrix((3, lanes), wp.float64)
    quads = lanes // 4

    @wp.func_native(_QUAD + f"""
    const double* p = (const double*){_MINOR_ENTRY};
    wp::mat_t<3, {lanes}, wp::float64> r;
    for (int q = 0; q < {quads}; ++q) {{
        quad_t v0, v1, v2;  // x0 y0 z0 x1 | y1 z1 x2 y2 | z2 x3 y3 z3
        __builtin_memcpy(&v0, p + 12 * q, sizeof(quad_t));
        __builtin_memcpy(&v1, p + 12 * q + 4, sizeof(quad_t));
        __builtin_memcpy(&v2, p + 12 * q + 8, sizeof(quad_t));
        quad_t x = __builtin_shufflevector(__builtin_shufflevector(v0, v1, 0, 3, 6, 6), v2, 0, 1, 2, 5);
        quad_t y = __builtin_shufflevector(__builtin_shufflevector(v0, v1, 1, 4, 7, 7), v2, 0, 1, 2, 6);
        quad_t z = __builtin_shufflevector(__builtin_shufflevector(v0, v1, 2, 5, 5, 5), v2, 0, 1, 4, 7);
        __builtin_memcpy(&r.data[0][4 * q], &x, sizeof(quad_t));
        __builtin_memcpy(&r.data[1][4 * q], &y, sizeof(quad_t));
        __builtin_memcpy(&r.data[2][4 * q], &z, sizeof(quad_t));
    }}
    return r;
    """)
    def load3(a: wp.array2d(dtype=wp.vec3d), k: int, i: int) -> lvec:
        ...

    @wp.func_native(_QUAD + f"""
    double* p = (double*){_MINOR_ENTRY};
    for (int q = 0; q < {quads}; ++q) {{
        quad_t x, y, z;
        __builtin_memcpy(&x, &v.data[0][4 * q], sizeof(quad_t));
        __builtin_memcpy(&y, &v.data[1][4 * q], sizeof(quad_t));
        __builtin_memcpy(&z, &v.data[2][4 * q], sizeof(quad_t));
        quad_t v0 = __builtin_shufflevector(__builtin_shufflevector(x, y, 0, 4, 1, 1), z, 0, 1, 4, 2);
        quad_t v1 = __builtin_shufflevector(__builtin_shufflevector(y, z, 1, 5, 2, 2), x, 0, 1, 6, 2);
        quad_t v2 = __builtin_shufflevector(__builtin_shufflevector(z, x, 2, 7, 3, 3), y, 0, 1, 7, 2);
        __builtin_memcpy(p + 12 * q, &v0, sizeof(quad_t));
        __builtin_memcpy(p + 12 * q + 4, &v1, sizeof(quad_t));
        __builtin_memcpy(p + 12 * q + 8, &v2, sizeof(quad_t));
    }}
    """)
    def store3(a: wp.array2d(dtype=wp.vec3d), k: int, i: int, v: lvec):
        ...

    @wp.func_native(f"""
    wp::vec_t<{lanes}, wp::float64> r;
    __builtin_memcpy(r.c, {_MINOR_ENTRY}, sizeof(r.c));
    return r;
    """)
    def load(a: wp.array2d(dtype=wp.float64), k: int, i: int) -> lane:
        ...

    return SimpleNamespace(load3=load3, store3=store3, load=load)
