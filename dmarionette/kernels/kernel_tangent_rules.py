"""The derivative rules of the interleaved tangent transformation (:mod:`kernel_tangent`): for each
operator and Warp builtin, the source of the tangent of its result from the sources of its operands
(atoms: names, constants, array reads) and of their tangents (``None`` for a constant).

Each rule is the derivative of the formula the primal evaluates, ties broken as Warp 1.19's adjoints
break them, so that the tangent agrees with the tape's reverse mode of the same kernel to rounding,
also at a switch:

- ``+``, ``-``, indexing, casts (``wp.float64(x)``, ``vec3(x)``), constructors, ``wp.skew``,
  ``wp.transpose``, ``wp.diag``: linear; ``*`` (scalars, vectors, matrices): product
  rule; ``a / b`` (scalar ``b``): ``(a_t - (a / b) b_t) / b``; ``wp.cross``, ``wp.dot``,
  ``wp.outer``: product rule;
- ``wp.sqrt``: ``x_t / (2 y)``; ``wp.exp``: ``y x_t``; ``wp.log``: ``x_t / x``;
  ``wp.sin``/``wp.cos``; ``wp.length(v)``: ``v . v_t / |v|``, and 0 at ``|v| = 0`` (Warp's
  ``adj_length``); ``wp.quat_rotate``/``wp.quat_rotate_inv``:
  :func:`~dmarionette.kernels.articulation_math_tangent.quat_rotate_tangent` (of the
  conjugate for the inverse: Warp's ``quat_rotate_inv`` is ``quat_rotate`` of the conjugate);
- switches, the branch taken: ``wp.max(a, b)``: ``a`` if ``a > b`` else ``b``; ``wp.min``:
  ``a`` if ``a < b`` else ``b``; ``wp.clamp(x, lo, hi)`` as Warp's ``min(max(lo, x), hi)``;
  ``wp.abs``: ``-x_t`` if ``x < 0``; ``wp.where(c, a, b)``: ``c`` chooses (an ``if`` runs
  the branch the primal runs, :mod:`kernel_tangent_transform`).

A zero of a value's type is written ``x - x`` (finite ``x``). A construct with no rule raises
:class:`RuleMissing` with the reason; the transformation turns it into a
:class:`~dmarionette.kernels.articulation_tangent.TangentError` naming the construct.
"""

from __future__ import annotations

import ast

import warp as wp

from dmarionette.kernels.articulation_math_tangent import quat_rotate_tangent

__all__ = ["RuleMissing", "binary_tangent", "call_tangent", "plus", "unary_tangent"]

_LINEAR1 = ("wp.skew", "wp.transpose", "wp.diag", "wp.float64", "wp.float32")
_BILINEAR = ("wp.cross", "wp.dot", "wp.outer")
# Functions of one argument: the tangent of ``y = f(x)`` from ``x``, its tangent ``t`` and ``y``.
_ONE_ARGUMENT = {
    "wp.sqrt": "{t} / ({y} + {y})",
    "wp.exp": "{y} * {t}",
    "wp.log": "{t} / {x}",
    "wp.sin": "wp.cos({x}) * {t}",
    "wp.cos": "-wp.sin({x}) * {t}",
    "wp.length": "wp.where({y} > ({y} - {y}), wp.dot({x}, {t}) / {y}, ({y} - {y}))",  # 0 at |x| = 0
    "wp.abs": "wp.where({x} < ({x} - {x}), -({t}), {t})",
}
# Switches of two arguments: the first argument's tangent where ``a <op> b``, else the second's.
_CHOOSE_FIRST = {"wp.max": ">", "wp.min": "<"}


class RuleMissing(Exception):
    """No rule for a construct; the message says why."""


def plus(a: str | None, b: str | None) -> str | None:
    """The sum of two tangents (``None``: zero)."""
    if a is None:
        return b
    if b is None:
        return a
    return f"({a}) + ({b})"


def unary_tangent(op: ast.unaryop, a: str, ta: str | None) -> tuple[str, str | None]:
    """(primal, tangent) of ``op a``."""
    if isinstance(op, ast.USub):
        return f"-{a}", f"-({ta})"
    if isinstance(op, ast.UAdd):
        return a, ta
    raise RuleMissing("unary operator")


def binary_tangent(op: ast.operator, a: str, ta: str | None, b: str, tb: str | None) -> tuple[str, str | None]:
    """(primal, tangent) of ``a op b``."""
    if isinstance(op, ast.Add):
        return f"{a} + {b}", plus(ta, tb)
    if isinstance(op, ast.Sub):
        return f"{a} - {b}", (f"-({tb})" if ta is None else ta if tb is None else f"{ta} - {tb}")
    if isinstance(op, ast.Mult):
        return f"{a} * {b}", plus(None if ta is None else f"{ta} * {b}", None if tb is None else f"{a} * {tb}")
    if isinstance(op, ast.Div):
        if tb is None:
            return f"{a} / {b}", f"{ta} / {b}"
        num = f"-({a} / {b}) * {tb}" if ta is None else f"{ta} - ({a} / {b}) * {tb}"
        return f"{a} / {b}", f"({num}) / {b}"
    raise RuleMissing(f"binary operator {type(op).__name__}")


def call_tangent(f: str, obj, args: list[str], tans: list[str | None], res: str, alias) -> str:
    """The tangent of ``res = f(*args)``, a Warp builtin, constructor or cast (``obj``: the object
    ``f`` names, or None); ``alias(obj)`` gives the name under which the generated module holds an
    object (a function or type the tangent calls)."""

    def zero_like(i):  # a zero of the type of the active argument ``i``'s neighbour
        t = next(t for t in tans if t is not None)
        return tans[i] if tans[i] is not None else f"({t} - {t})"

    if f in _LINEAR1 and len(args) == 1:
        return f"{f}({tans[0]})"
    if f in _BILINEAR and len(args) == 2:
        return plus(None if tans[0] is None else f"{f}({tans[0]}, {args[1]})",
                    None if tans[1] is None else f"{f}({args[0]}, {tans[1]})")
    if f in _ONE_ARGUMENT and len(args) == 1:
        return _ONE_ARGUMENT[f].format(x=args[0], t=tans[0], y=res)
    if f in ("wp.quat_rotate", "wp.quat_rotate_inv") and len(args) == 2:
        q, v = args
        tq = tans[0] if tans[0] is not None else "wp.quatd()"
        tv = tans[1] if tans[1] is not None else "wp.vec3d()"
        if f == "wp.quat_rotate_inv":
            q, tq = f"wp.quat_inverse({q})", f"wp.quat_inverse({tq})"
        return f"{alias(quat_rotate_tangent)}({q}, {v}, {tq}, {tv})"
    if f in _CHOOSE_FIRST and len(args) == 2:
        return f"wp.where({args[0]} {_CHOOSE_FIRST[f]} {args[1]}, {zero_like(0)}, {zero_like(1)})"
    if f == "wp.clamp" and len(args) == 3:
        x, lo, hi = args
        return (f"wp.where(wp.max({lo}, {x}) < {hi}, wp.where({lo} > {x}, {zero_like(1)}, {zero_like(0)}), "
                f"{zero_like(2)})")
    if f == "wp.where" and len(args) == 3:
        if tans[0] is not None:
            raise RuleMissing("an active condition")
        t1 = tans[1] if tans[1] is not None else f"({tans[2]} - {tans[2]})"
        t2 = tans[2] if tans[2] is not None else f"({tans[1]} - {tans[1]})"
        return f"wp.where({args[0]}, {t1}, {t2})"
    scalar = getattr(obj, "_wp_scalar_type_", None)
    if scalar is not None or obj in (wp.float64, wp.float32):  # a constructor or cast: linear
        if len(args) == 1:
            return f"{f}({tans[0]})"
        zero = f"{alias(scalar)}(0.0)"
        return f"{f}({', '.join(t if t is not None else zero for t in tans)})"
    raise RuleMissing(f"no rule for the function {f}")
