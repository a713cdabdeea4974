"""The values of the tangent-linear kernels: one direction per value, or ``K`` directions in SIMD lanes.

A tangent kernel loops over its P directions; written against this namespace, one kernel body
serves both layouts (``string_step_tangent``, issue 13 item 4):

- ``lanes = 1`` (any float type, CPU or CUDA): a tangent scalar is a ``scalar``, a tangent vector a
  ``vec3``; the loop steps by one direction.
- ``lanes = K`` (float64, CPU: the gathers are Clang C++ snippets, ``lane_ops.native_direction_memory``):
  a tangent scalar is a ``vector(K, float64)`` (lane ``l``: direction ``k + l``), a tangent vector a
  ``3 x K`` matrix (column ``l``: direction ``k + l``; row ``i``, ``v[i]``, component ``i`` of the K
  directions); the loop steps by K directions, the last group padded (its padding lanes read the
  last direction, are computed and never written). The primal values stay scalars and ``vec3``:
  a primal matrix times a tangent vector is Warp's ``mat33 * mat(3, K)``, a primal vector along a
  tangent scalar an outer product. The packing of these ``K``-wide operations is left to Clang's
  vectorizer (``-march=native``; the laned step's snippets, ``lane_ops.native_lane_ops``, exist
  because a *bit-exact* laned step needed them; the tangent only has to agree to rounding,
  ``tests/grad/test_string_tangent_lanes.py``).

Both give the same names (the scalar ones are the expressions the scalar tangent always used, so its
numbers are unchanged): ``TS``, ``TV`` (the types, also the zero constructors ``TS(zero)``,
``TV(zero)``), ``step`` (directions per value), ``load(a, k, directions, i)`` (``a[k, i]`` of a
``(P, n)`` scalar array), ``load_constant(a, k, directions, i, c)`` (``a[k, i, c]``), ``load3`` and
``store3(a, k, directions, i, v)`` (of a ``(P, n)`` vec3 array; the store writes the real
directions only), ``outer(v, a)`` (the primal vector ``v`` times the tangent scalar ``a``),
``dot(u, r)`` (the primal ``u`` dotted with the tangent vector ``r``), ``tvec(a, b, c)`` (the
tangent vector of three tangent scalars, component-wise).
"""

import functools

from types import SimpleNamespace

import warp as wp

from .lane_ops import native_direction_memory

__all__ = ["tangent_directions"]


@functools.cache
def tangent_directions(scalar, lanes: int = 1) -> SimpleNamespace:
    """The namespace of the module doc for a float type and ``lanes`` directions per value."""
    if lanes == 1:
        return _scalar_directions(scalar)
    if scalar is not wp.float64:
        raise TypeError(f"tangent directions in lanes: float64 only (the lane snippets), got {scalar}")
    return _lane_directions(lanes)


def _scalar_directions(scalar) -> SimpleNamespace:
    vec3 = wp.types.vector(3, scalar)

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
    def tvec(a: scalar, b: scalar, c: scalar):
        return vec3(a, b, c)

    return SimpleNamespace(TS=scalar, TV=vec3, step=1, load=load, load_constant=load_constant, load3=load3,
                           store3=store3, outer=outer, dot=dot, tvec=tvec)


def _lane_directions(lanes: int) -> SimpleNamespace:
    f64 = wp.float64
    lane = wp.types.vector(lanes, f64)
    lvec = wp.types.matrix((3, lanes), f64)
    vec3 = wp.vec3d
    mem = native_direction_memory(lanes)

    @wp.func
    def load(a: wp.array2d(dtype=f64), k: int, directions: int, i: int):
        return mem.gather(a, k, directions, i)

    @wp.func
    def load_constant(a: wp.array3d(dtype=f64), k: int, directions: int, i: int, c: int):
        return mem.gather_constant(a, k, directions, i, c)

    @wp.func
    def load3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int):
        return mem.gather3(a, k, directions, i)

    @wp.func
    def store3(a: wp.array2d(dtype=vec3), k: int, directions: int, i: int, v: lvec):
        mem.scatter3(a, k, directions, i, v)

    @wp.func
    def outer(v: vec3, a: lane):
        return wp.outer(v, a)

    @wp.func
    def dot(u: vec3, r: lvec):
        return u * r  # the row vector u^T times the 3 x K matrix

    @wp.func
    def tvec(a: lane, b: lane, c: lane):
        return wp.matrix_from_rows(a, b, c)

    return SimpleNamespace(TS=lane, TV=lvec, step=lanes, load=load, load_constant=load_constant, load3=load3,
                           store3=store3, outer=outer, dot=dot, tvec=tvec)
