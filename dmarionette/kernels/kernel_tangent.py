"""Tangent-linear (forward-mode) kernels of hand-written Warp kernels, by an "interleaved"
source-to-source transformation: each statement's primal, then its tangent.

Warp's tape is reverse mode only. :func:`tangent_kernel` parses a kernel's Python source
with :mod:`ast` and writes a kernel ``<key>_tangent`` that runs one thread per (direction,
original thread): ``wp.tid()`` gains a leading direction index, so the launch is
``dim = (P, *dim)`` and loops need no per-direction storage. Control flow is kept as it
is (forward mode needs no tape): ``if``/``for`` (static or dynamic bounds), early
``return``, ``+=`` on locals, element writes of local vectors and matrices. Every active
value ``y`` gets its tangent ``tan_y`` right after it. Calls of project ``@wp.func``s
with an active argument are transformed recursively into ``<name>_jvp<n>`` functions
(one per function and pattern of active arguments) that return the primal results and
then the tangents of the active ones; a closure's free names (the hard or smooth normal
force of ``body_contact``, the strings' float type, ``wp.static`` constants) are resolved
to the objects the closure holds. The source written is kept in the cache folder
(``DMARIONETTE_CACHE``; ``articulation_codegen.import_generated``, as the generated articulation
kernels), the closures' objects handed to the module as its globals.

Tangent kernel signature: the primal kernel's parameters in their groups, with a ``Tangent
in`` group after the input groups holding ``tan_<name>`` for every array parameter named in
``tangent_names`` (default :data:`TANGENT_NAMES`) that the kernel reads, and a last group
``Tangent out`` holding ``tan_<name>`` for every array it writes (plain writes and
``wp.atomic_add``); :meth:`TangentKernel.launch` takes the arguments by name. Each tangent
array has a leading direction axis (``wp.array2d`` -> ``wp.array3d``, same
dtype). The tangent kernel also writes the primal outputs (the direction-0 threads
only), so one launch gives the pass and its P directional derivatives; an output that the
primal accumulates (``wp.atomic_add``) is accumulated in its tangent too, so the caller
initialises it as it initialises the primal. Everything else is constant (tangent 0):
scalar parameters, structs (contact constants, surfaces), integer arrays, and arrays not
named.

Rules (each the derivative of the formula the primal evaluates, ties broken as Warp
1.19's adjoints break them, so that the tangent agrees with the tape's reverse mode of the
same kernel to rounding, also at a switch):

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
  ``wp.abs``: ``-x_t`` if ``x < 0``; ``wp.where(c, a, b)``: ``c`` chooses; an ``if`` runs
  the branch the primal runs (its condition carries no tangent);
- ``wp.atomic_add(a, i.., x)``: also ``wp.atomic_add(tan_a, p, i.., x_t)``; ``a[i] = x``:
  also ``tan_a[p, i] = x_t``.

A value that is active somewhere (the analysis is flow-insensitive) but assigned a
constant elsewhere gets the tangent ``y - y``, zero of its type (finite ``y``).

Covered (each checked against the tape by the dot-product identity, at and away from its
switches, and against central differences): ``articulation_forces`` (``eval_body_external_forces``,
``eval_body_point_springs``, ``eval_body_points``, ``compute_point_state``), ``body_contact``
(ground, chair box and ball, hard and smooth), ``string_body_coupling``
(``eval_string_response``, ``eval_tie_path``, ``apply_string_forces_to_anchors``) and
``bar_feedback`` (eq. 4 and the exact reaction, printed and tension-only springs); their
users are :class:`~dmarionette.articulation.step_tangent.PuppetStepTangent` and
:class:`~dmarionette.grad.marionette_tangent.MarionetteTangent`.

Why interleaved and not hand-written tangents: no derivative to keep in sync by hand (a
change of a kernel changes its tangent), and the transformer is the one place where a rule
lives. Why one thread per (direction, thread), not a direction loop: loops and branches stay
as they are, with no per-direction storage of the loop's values; the price is the primal
recomputed per direction (these kernels are a small part of a step: the dynamics and the
string solve, which have their own tangents, dominate).

Anything else (another builtin, ``**``, keyword arguments on an active call, an active
``if`` condition or index, a tuple returned into an expression) raises
:class:`~dmarionette.kernels.articulation_tangent.TangentError` naming the construct: no
term is ever dropped silently.
"""

from __future__ import annotations

import ast
import builtins
import hashlib
import inspect
import textwrap
import typing

import warp as wp

from dmarionette.kernels.articulation_codegen import import_generated
from dmarionette.kernels.articulation_math import compute_spatial
from dmarionette.kernels.articulation_math_tangent import quat_rotate_tangent
from dmarionette.kernels.articulation_tangent import TangentError

__all__ = ["TANGENT_NAMES", "TangentKernel", "tangent_kernel"]

# Array parameters whose tangents the kernels take (by name; every other input is a constant).
TANGENT_NAMES = frozenset({
    # the body and joint state
    "body_pos", "body_rot", "body_w", "body_v", "joint_q", "joint_qd",
    # the puppet's applied loads and spring anchors (Control), its tie constants
    "body_force", "body_torque", "spring_anchor_pos", "spring_anchor_vel", "spring_stiffness", "spring_damping",
    # the strings: particle state, tie forces and path, their constants
    "particle_q", "particle_qd", "tie_force", "tie_q", "tie_qd", "tie_target", "point_end",
    "string_stiffness", "string_rest_length", "string_internal_friction", "string_tie_stiffness",
    "string_tie_damping",
    # the bars
    "bar_q", "bar_qd",
})

_FunctionType = type(compute_spatial)  # warp's @wp.func object
_PREFIX = "tan_"
_DIR = "_dir"
_TMP = "_tmp"
_GLB = "_glb"

_LINEAR1 = ("wp.skew", "wp.transpose", "wp.diag", "wp.float64", "wp.float32")
_BILINEAR = ("wp.cross", "wp.dot", "wp.outer")
_INACTIVE_CALLS = ("wp.tid", "wp.static", "wp.identity", "int", "float", "bool", "len", "range", "wp.int32")


def _src(node: ast.AST) -> str:
    return ast.unparse(node)


def _fail(where: str, node: ast.AST, why: str):
    raise TangentError(f"kernel_tangent ({where}): no tangent rule for `{_src(node)}`: {why}")


def _describe(obj, depth: int = 0) -> str:
    """A description of a global the generated source refers to, stable across processes (it is part
    of the hash that names the generated file)."""
    if isinstance(obj, (bool, int, float, str)):
        return repr(obj)
    if hasattr(obj, "_wp_scalar_type_"):
        shape = getattr(obj, "_shape_", getattr(obj, "_length_", None))
        return f"{getattr(obj, '__name__', type(obj).__name__)}{shape}[{obj._wp_scalar_type_.__name__}]"
    if isinstance(obj, _FunctionType):
        f = obj.func
        cells = [_describe(c.cell_contents, depth + 1) for c in (f.__closure__ or ())] if depth < 2 else []
        return f"{f.__module__}.{f.__qualname__}({', '.join(cells)})"
    if hasattr(obj, "key") and hasattr(obj, "cls"):  # a wp.struct
        return f"struct {obj.key}"
    return getattr(obj, "__qualname__", None) or repr(type(obj))


class _Builder:
    """One tangent module: the globals its source refers to and the functions it has generated."""

    def __init__(self):
        self.env: dict[str, object] = {}
        self.alias_of: dict[int, str] = {}
        self.funcs: list[str] = []
        self.analysed: dict[tuple, _Transform] = {}  # (id(function), active mask) -> its analysed transform
        self.jvp: dict[tuple, str] = {}  # (id(function), active mask) -> the name of its emitted jvp function
        self.count = 0

    def alias(self, obj) -> str:
        if id(obj) not in self.alias_of:
            name = f"{_GLB}{len(self.alias_of)}"
            self.alias_of[id(obj)] = name
            self.env[name] = obj
        return self.alias_of[id(obj)]

    def analysis(self, fn, mask: tuple) -> _Transform:
        """The transform of ``fn`` with the arguments of ``mask`` active, analysed (not emitted)."""
        key = (id(fn), mask)
        if key not in self.analysed:
            self.analysed[key] = _Transform(self, fn.func, {i for i, a in enumerate(mask) if a}, kernel=False)
        return self.analysed[key]

    def function_jvp(self, fn, mask: tuple) -> tuple[str, tuple]:
        """(name, output mask) of the jvp function of ``fn`` for ``mask``, emitted once (after its callees)."""
        key = (id(fn), mask)
        t = self.analysis(fn, mask)
        if key not in self.jvp:
            self.count += 1
            name = f"{fn.func.__name__}_jvp{self.count}"
            self.jvp[key] = name
            self.funcs.append(t.emit_function(name))
        return self.jvp[key], t.out_mask


class _Transform:
    """The transformation of one kernel or function (module doc)."""

    def __init__(self, builder: _Builder, pyfunc, active_params: set, kernel: bool, tangent_names=()):
        self.b = builder
        self.kernel = kernel
        self.where = pyfunc.__qualname__
        tree = ast.parse(textwrap.dedent(inspect.getsource(pyfunc)))
        fn = tree.body[0]
        if not isinstance(fn, ast.FunctionDef) or fn.args.vararg or fn.args.kwonlyargs or fn.args.defaults:
            raise TangentError(f"kernel_tangent: {self.where}: expected a plain function definition")
        self.fn = fn
        scope = dict(pyfunc.__globals__)
        scope.update({n: c.cell_contents for n, c in zip(pyfunc.__code__.co_freevars, pyfunc.__closure__ or ())})
        self.params = [a.arg for a in fn.args.args]
        self.locals = set(self.params) | {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)
                                          and isinstance(n.ctx, ast.Store)}
        clash = sorted(n for n in self.locals if n.startswith((_PREFIX, _TMP, _GLB)) or n == _DIR)
        if clash:
            raise TangentError(f"kernel_tangent: {self.where}: names {clash} clash with the tangent code's own")
        # Annotations are evaluated where the function is defined (a closure's are not cells): their objects.
        self.annotation = {}
        for a in fn.args.args:
            ann = pyfunc.__annotations__.get(a.arg)
            self.annotation[a.arg] = eval(ann, scope) if isinstance(ann, str) else ann  # noqa: S307 (the source's own)
        self._resolve(scope)
        self.arrays = {n for n, a in self.annotation.items() if isinstance(a, wp.array)}
        if kernel:
            self.active_arrays = {n for n in self.arrays if n in tangent_names}
            self.active = set()
        else:
            if self.arrays:
                raise TangentError(f"kernel_tangent: {self.where}: a function taking arrays")
            self.active_arrays = set()
            self.active = {self.params[i] for i in active_params}
        self.outputs = self._outputs() if kernel else []
        self.out_mask: tuple = ()
        self.lines: list[str] = []
        self.temps = 0
        self._analyse()

    # ------------------------------------------------------------ names
    def _resolve(self, scope: dict) -> None:
        """Free names (and attribute chains on non-module objects) -> aliases of the objects they name;
        Python scalar constants are written in as literals."""
        b = self.b
        locals_ = self.locals

        def value(obj):
            if isinstance(obj, (bool, int, float)):
                return ast.Constant(obj)
            return ast.Name(b.alias(obj))

        class Resolver(ast.NodeTransformer):
            def visit_Attribute(self, node):
                chain, base = [], node
                while isinstance(base, ast.Attribute):
                    chain.append(base.attr)
                    base = base.value
                if isinstance(base, ast.Name) and base.id not in locals_ and base.id in scope:
                    obj = scope[base.id]
                    if obj is wp or inspect.ismodule(obj):
                        return node
                    for a in reversed(chain):
                        obj = getattr(obj, a)
                    return value(obj)
                return self.generic_visit(node)

            def visit_Name(self, node):
                if node.id in locals_ or not isinstance(node.ctx, ast.Load):
                    return node
                if node.id in scope:
                    obj = scope[node.id]
                    if obj is wp:
                        return node
                    if obj is typing.Any:
                        return ast.Name(b.alias(typing.Any))
                    return value(obj)
                if hasattr(builtins, node.id):
                    return node
                raise TangentError(f"kernel_tangent: cannot resolve the name {node.id}")

        for a in self.fn.args.args:
            a.annotation = None  # written from the evaluated annotations (annotation_source)
        self.fn.decorator_list = []
        self.fn.returns = None
        self.fn = Resolver().visit(self.fn)

    def annotation_source(self, name: str, lead: int = 0) -> str:
        """The type of parameter ``name`` (an array type: with ``lead`` more leading dimensions)."""
        a = self.annotation[name]
        if isinstance(a, wp.array):
            return f"wp.array{a.ndim + lead}d(dtype={self._type_source(a.dtype)})"
        if lead:
            raise TangentError(f"kernel_tangent: {self.where}: a tangent of the non-array {name}")
        return self._type_source(a)

    def _type_source(self, t) -> str:
        for n in ("float64", "float32", "int32", "vec3d", "quatd", "mat33d"):
            if t is getattr(wp, n):
                return f"wp.{n}"
        if t is int:
            return "int"
        return self.b.alias(t)

    def _object(self, node: ast.AST):
        """The object a (resolved) name refers to, or None."""
        if isinstance(node, ast.Name) and node.id in self.b.env:
            return self.b.env[node.id]
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "wp":
            return getattr(wp, node.attr, None)
        return None

    def _outputs(self) -> list[str]:
        out = []
        for n in ast.walk(self.fn):
            name = None
            if isinstance(n, ast.Subscript) and isinstance(n.ctx, ast.Store) and isinstance(n.value, ast.Name):
                name = n.value.id
            elif isinstance(n, ast.Call) and _src(n.func) == "wp.atomic_add" and isinstance(n.args[0], ast.Name):
                name = n.args[0].id
            if name in self.arrays and name not in out:
                out.append(name)
        return out

    # ------------------------------------------------------------ activity
    def _analyse(self) -> None:
        """Flow-insensitive activity (a fixed point over all assignments), then the outputs' mask."""
        changed = True
        while changed:
            changed = False
            for st in ast.walk(self.fn):
                for name in self._activated(st):
                    if name not in self.active:
                        self.active.add(name)
                        changed = True
        if not self.kernel:
            rets = [st for st in ast.walk(self.fn) if isinstance(st, ast.Return) and st.value is not None]
            mask = None
            for r in rets:
                elts = r.value.elts if isinstance(r.value, ast.Tuple) else [r.value]
                m = tuple(self.is_active(e) for e in elts)
                if mask is not None and len(m) != len(mask):
                    _fail(self.where, r, "returns of different lengths")
                mask = m if mask is None else tuple(a or b for a, b in zip(mask, m))
            self.out_mask = mask or ()

    def _activated(self, st) -> list[str]:
        if isinstance(st, ast.Assign) and len(st.targets) == 1:
            t, v = st.targets[0], st.value
            if isinstance(t, ast.Name):
                return [t.id] if self.is_active(v) else []
            if isinstance(t, ast.Tuple):
                if isinstance(v, ast.Tuple):
                    return [e.id for e, x in zip(t.elts, v.elts) if isinstance(e, ast.Name) and self.is_active(x)]
                mask = self.call_mask(v)
                return [e.id for e, a in zip(t.elts, mask) if a and isinstance(e, ast.Name)]
            if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name) and t.value.id not in self.arrays:
                return [t.value.id] if self.is_active(v) else []
        if isinstance(st, ast.AugAssign) and isinstance(st.target, ast.Name):
            return [st.target.id] if self.is_active(st.value) else []
        return []

    def is_active(self, node: ast.AST) -> bool:
        if isinstance(node, ast.Name):
            return node.id in self.active
        if isinstance(node, (ast.Constant, ast.Compare, ast.BoolOp, ast.Attribute)):
            return False
        if isinstance(node, ast.Subscript):
            if isinstance(node.value, ast.Name) and node.value.id in self.arrays:
                return node.value.id in self.active_arrays
            return self.is_active(node.value)
        if isinstance(node, ast.BinOp):
            return self.is_active(node.left) or self.is_active(node.right)
        if isinstance(node, ast.UnaryOp):
            return not isinstance(node.op, ast.Not) and self.is_active(node.operand)
        if isinstance(node, ast.Tuple):
            return any(self.is_active(e) for e in node.elts)
        if isinstance(node, ast.Call):
            return any(self.call_mask(node))
        _fail(self.where, node, f"expression kind {type(node).__name__}")

    def call_mask(self, call: ast.AST) -> tuple:
        """Which results of a call are active (a single result: a 1-tuple)."""
        if not isinstance(call, ast.Call):
            _fail(self.where, call, "a tuple assignment from something other than a call")
        f = _src(call.func)
        if f in _INACTIVE_CALLS:
            return (False,)
        args = list(call.args) + [k.value for k in call.keywords]
        mask = tuple(self.is_active(a) for a in call.args)
        if not any(self.is_active(a) for a in args):
            obj = self._object(call.func)
            if isinstance(obj, _FunctionType):
                return (False,) * 8  # any number of (inactive) results
            return (False,)
        obj = self._object(call.func)
        if _is_project(obj):
            if call.keywords:
                _fail(self.where, call, "keyword arguments")
            return self.b.analysis(obj, mask).out_mask
        return (True,)

    # ------------------------------------------------------------ emission
    def emit(self, line: str, indent: int) -> None:
        self.lines.append("    " * indent + line)

    def temp(self) -> str:
        self.temps += 1
        return f"{_TMP}{self.temps}"

    def tan(self, name: str) -> str:
        return f"{_PREFIX}{name}"

    def atom(self, node: ast.AST, indent: int) -> tuple[str, str | None]:
        """(source of a name/constant/array read holding the value, its tangent or None)."""
        if isinstance(node, (ast.Name, ast.Constant)):
            return _src(node), (self.tan(node.id) if isinstance(node, ast.Name) and node.id in self.active else None)
        if (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id in self.arrays):
            if node.value.id not in self.active_arrays:
                return _src(node), None
            idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            return _src(node), f"{self.tan(node.value.id)}[{', '.join([_DIR] + [_src(i) for i in idx])}]"
        if isinstance(node, ast.Attribute):
            return _src(node), None
        prim, tan = self.lower(node, indent)
        if isinstance(node, ast.Call) and self.is_active(node):
            return prim, tan  # already a temporary (lower_call)
        name = self.temp()
        self.emit(f"{name} = {prim}", indent)
        if tan is not None:
            self.emit(f"{self.tan(name)} = {tan}", indent)
        return name, (self.tan(name) if tan is not None else None)

    def lower(self, node: ast.AST, indent: int) -> tuple[str, str | None]:
        """(primal expression with its operands reduced to atoms, tangent expression or None)."""
        if not self.is_active(node):
            return _src(node), None
        if isinstance(node, (ast.Name, ast.Constant)) or (isinstance(node, ast.Subscript) and isinstance(
                node.value, ast.Name) and node.value.id in self.arrays):
            return self.atom(node, indent)
        if isinstance(node, ast.Subscript):
            if self.is_active(node.slice):
                _fail(self.where, node, "an active index")
            a, ta = self.atom(node.value, indent)
            return f"{a}[{_src(node.slice)}]", f"{ta}[{_src(node.slice)}]"
        if isinstance(node, ast.UnaryOp):
            a, ta = self.atom(node.operand, indent)
            if isinstance(node.op, ast.USub):
                return f"-{a}", f"-({ta})"
            if isinstance(node.op, ast.UAdd):
                return a, ta
            _fail(self.where, node, "unary operator")
        if isinstance(node, ast.BinOp):
            a, ta = self.atom(node.left, indent)
            b, tb = self.atom(node.right, indent)
            if isinstance(node.op, ast.Add):
                return f"{a} + {b}", _plus(ta, tb)
            if isinstance(node.op, ast.Sub):
                return f"{a} - {b}", (f"-({tb})" if ta is None else ta if tb is None else f"{ta} - {tb}")
            if isinstance(node.op, ast.Mult):
                return f"{a} * {b}", _plus(None if ta is None else f"{ta} * {b}", None if tb is None else f"{a} * {tb}")
            if isinstance(node.op, ast.Div):
                if tb is None:
                    return f"{a} / {b}", f"{ta} / {b}"
                num = f"-({a} / {b}) * {tb}" if ta is None else f"{ta} - ({a} / {b}) * {tb}"
                return f"{a} / {b}", f"({num}) / {b}"
            _fail(self.where, node, f"binary operator {type(node.op).__name__}")
        if isinstance(node, ast.Call):
            return self.lower_call(node, indent)
        _fail(self.where, node, f"expression kind {type(node).__name__}")

    def lower_call(self, node: ast.Call, indent: int) -> tuple[str, str]:
        f = _src(node.func)
        obj = self._object(node.func)
        if node.keywords:
            _fail(self.where, node, "keyword arguments on an active call")
        if _is_project(obj):
            mask = tuple(self.is_active(a) for a in node.args)
            name, out = self.b.function_jvp(obj, mask)
            if len(out) != 1:
                _fail(self.where, node, "a function of several results in an expression")
            atoms = [self.atom(a, indent) for a in node.args]
            res = self.temp()
            call = ", ".join([a for a, _ in atoms] + [t for _, t in atoms if t])
            self.emit(f"{res}, {self.tan(res)} = {name}({call})", indent)
            return res, self.tan(res)
        atoms = [self.atom(a, indent) for a in node.args]
        args = [a for a, _ in atoms]
        tans = [t for _, t in atoms]
        res = self.temp()
        self.emit(f"{res} = {f}({', '.join(args)})", indent)

        def zero_like(i):  # a zero of the type of the active argument ``i``'s neighbour
            t = next(t for t in tans if t is not None)
            return tans[i] if tans[i] is not None else f"({t} - {t})"

        if f in _LINEAR1 and len(args) == 1:
            return res, f"{f}({tans[0]})"
        if f in _BILINEAR and len(args) == 2:
            return res, _plus(None if tans[0] is None else f"{f}({tans[0]}, {args[1]})",
                              None if tans[1] is None else f"{f}({args[0]}, {tans[1]})")
        if f == "wp.sqrt":
            return res, f"{tans[0]} / ({res} + {res})"
        if f == "wp.exp":
            return res, f"{res} * {tans[0]}"
        if f == "wp.log":
            return res, f"{tans[0]} / {args[0]}"
        if f == "wp.sin":
            return res, f"wp.cos({args[0]}) * {tans[0]}"
        if f == "wp.cos":
            return res, f"-wp.sin({args[0]}) * {tans[0]}"
        if f == "wp.length":
            return res, (f"wp.where({res} > ({res} - {res}), wp.dot({args[0]}, {tans[0]}) / {res}, "
                         f"({res} - {res}))")
        if f in ("wp.quat_rotate", "wp.quat_rotate_inv") and len(args) == 2:
            q, v = args
            tq = tans[0] if tans[0] is not None else "wp.quatd()"
            tv = tans[1] if tans[1] is not None else "wp.vec3d()"
            if f == "wp.quat_rotate_inv":
                q, tq = f"wp.quat_inverse({q})", f"wp.quat_inverse({tq})"
            return res, f"{self.b.alias(quat_rotate_tangent)}({q}, {v}, {tq}, {tv})"
        if f == "wp.max" and len(args) == 2:
            return res, f"wp.where({args[0]} > {args[1]}, {zero_like(0)}, {zero_like(1)})"
        if f == "wp.min" and len(args) == 2:
            return res, f"wp.where({args[0]} < {args[1]}, {zero_like(0)}, {zero_like(1)})"
        if f == "wp.clamp" and len(args) == 3:
            x, lo, hi = args
            return res, (f"wp.where(wp.max({lo}, {x}) < {hi}, wp.where({lo} > {x}, {zero_like(1)}, {zero_like(0)}), "
                         f"{zero_like(2)})")
        if f == "wp.abs" and len(args) == 1:
            return res, f"wp.where({args[0]} < ({args[0]} - {args[0]}), -({tans[0]}), {tans[0]})"
        if f == "wp.where" and len(args) == 3:
            if tans[0] is not None:
                _fail(self.where, node, "an active condition")
            t1 = tans[1] if tans[1] is not None else f"({tans[2]} - {tans[2]})"
            t2 = tans[2] if tans[2] is not None else f"({tans[1]} - {tans[1]})"
            return res, f"wp.where({args[0]}, {t1}, {t2})"
        scalar = getattr(obj, "_wp_scalar_type_", None)
        if scalar is not None or obj in (wp.float64, wp.float32):  # a constructor or cast: linear
            if len(args) == 1:
                return res, f"{f}({tans[0]})"
            zero = f"{self.b.alias(scalar)}(0.0)"
            return res, f"{f}({', '.join(t if t is not None else zero for t in tans)})"
        _fail(self.where, node, f"no rule for the function {f}")

    def zero(self, name: str) -> str:
        return f"{name} - {name}"

    def statements(self, body: list, indent: int) -> None:
        for st in body:
            self.statement(st, indent)

    def statement(self, st: ast.stmt, indent: int) -> None:
        if isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant):
            return  # docstring
        if isinstance(st, (ast.Pass, ast.Break, ast.Continue)):
            self.emit(_src(st), indent)
            return
        if isinstance(st, ast.Assign):
            if len(st.targets) != 1:
                _fail(self.where, st, "chained assignment")
            self.assign(st.targets[0], st.value, indent)
            return
        if isinstance(st, ast.AugAssign):
            if not isinstance(st.target, ast.Name) or not isinstance(st.op, (ast.Add, ast.Sub)):
                _fail(self.where, st, "augmented assignment other than += / -= on a local")
            self.assign(st.target, ast.BinOp(ast.Name(st.target.id), st.op, st.value), indent)
            return
        if isinstance(st, ast.If):
            if self.is_active(st.test):
                _fail(self.where, st.test, "an active condition")
            self.emit(f"if {_src(st.test)}:", indent)
            self.statements(st.body, indent + 1)
            if st.orelse:
                self.emit("else:", indent)
                self.statements(st.orelse, indent + 1)
            return
        if isinstance(st, ast.For):
            if st.orelse or self.is_active(st.iter):
                _fail(self.where, st, "a for loop with an else or an active range")
            self.emit(f"for {_src(st.target)} in {_src(st.iter)}:", indent)
            self.statements(st.body, indent + 1)
            return
        if isinstance(st, ast.Return):
            self.ret(st, indent)
            return
        if isinstance(st, ast.Expr) and isinstance(st.value, ast.Call) and _src(st.value.func) == "wp.atomic_add":
            self.atomic_add(st.value, indent)
            return
        _fail(self.where, st, f"statement kind {type(st).__name__}")

    def assign(self, t: ast.AST, v: ast.AST, indent: int) -> None:
        if isinstance(t, ast.Name) and isinstance(v, ast.Call) and _src(v.func) == "wp.tid":
            if not self.kernel:
                _fail(self.where, v, "wp.tid outside a kernel")
            self.emit(f"{_DIR}, {_src(t)} = wp.tid()", indent)
            return
        if isinstance(t, ast.Tuple) and isinstance(v, ast.Call) and _src(v.func) == "wp.tid":
            self.emit(f"{_DIR}, {', '.join(_src(e) for e in t.elts)} = wp.tid()", indent)
            return
        if isinstance(t, ast.Name):
            prim, tan = self.lower(v, indent)
            self.emit(f"{t.id} = {prim}", indent)
            if t.id in self.active:
                self.emit(f"{self.tan(t.id)} = {tan if tan is not None else self.zero(t.id)}", indent)
            return
        if isinstance(t, ast.Tuple):
            names = [e.id if isinstance(e, ast.Name) else _fail(self.where, e, "a tuple target") for e in t.elts]
            if isinstance(v, ast.Tuple):
                for e, x in zip(t.elts, v.elts):
                    self.assign(e, x, indent)
                return
            mask = self.call_mask(v)
            if not any(mask):
                self.emit(f"{_src(t)} = {_src(v)}", indent)
            else:
                obj = self._object(v.func)
                name, out = self.b.function_jvp(obj, tuple(self.is_active(a) for a in v.args))
                if len(out) != len(names):
                    _fail(self.where, v, f"{len(names)} targets for {len(out)} results")
                atoms = [self.atom(a, indent) for a in v.args]
                tnames = [self.tan(n) if n in self.active else self.temp() for n, a in zip(names, out) if a]
                self.emit(f"{', '.join(names + tnames)} = "
                          f"{name}({', '.join([a for a, _ in atoms] + [x for _, x in atoms if x])})", indent)
            for n, a in zip(names, mask):
                if n in self.active and not a:
                    self.emit(f"{self.tan(n)} = {self.zero(n)}", indent)
            return
        if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name):
            if self.is_active(t.slice):
                _fail(self.where, t, "an active index")
            x, tx = self.atom(v, indent)
            arr = t.value.id
            if arr in self.arrays:
                self.emit(f"if {_DIR} == 0:", indent)
                self.emit(f"{_src(t)} = {x}", indent + 1)
                idx = t.slice.elts if isinstance(t.slice, ast.Tuple) else [t.slice]
                self.emit(f"{self.tan(arr)}[{', '.join([_DIR] + [_src(i) for i in idx])}] = "
                          f"{tx if tx is not None else self.zero(x)}", indent)
            else:
                self.emit(f"{_src(t)} = {x}", indent)
                if arr in self.active:
                    self.emit(f"{self.tan(arr)}[{_src(t.slice)}] = {tx if tx is not None else self.zero(x)}", indent)
            return
        _fail(self.where, t, "assignment target")

    def atomic_add(self, call: ast.Call, indent: int) -> None:
        arr, *idx, value = call.args
        if any(self.is_active(i) for i in idx) or not isinstance(arr, ast.Name) or arr.id not in self.arrays:
            _fail(self.where, call, "an atomic add to something other than a parameter array")
        x, tx = self.atom(value, indent)
        ids = [_src(i) for i in idx]
        self.emit(f"if {_DIR} == 0:", indent)
        self.emit(f"wp.atomic_add({', '.join([arr.id] + ids + [x])})", indent + 1)
        if tx is not None:
            self.emit(f"wp.atomic_add({', '.join([self.tan(arr.id), _DIR] + ids + [tx])})", indent)

    def ret(self, st: ast.Return, indent: int) -> None:
        if self.kernel:
            if st.value is not None:
                _fail(self.where, st, "a kernel returning a value")
            self.emit("return", indent)
            return
        elts = st.value.elts if isinstance(st.value, ast.Tuple) else [st.value]
        atoms = [self.atom(e, indent) for e in elts]
        tans = [(t if t is not None else self.zero(a)) for (a, t), m in zip(atoms, self.out_mask) if m]
        self.emit(f"return {', '.join([a for a, _ in atoms] + tans)}", indent)

    # ------------------------------------------------------------ definitions
    def _signature(self, extra: list[str]) -> list[str]:
        return [f"{n}: {self.annotation_source(n)}" for n in self.params] + extra

    def emit_function(self, name: str) -> str:
        self.statements(self.fn.body, 1)
        extra = [f"{self.tan(n)}: {self.annotation_source(n)}" for n in self.params if n in self.active]
        head = ["@wp.func", f"def {name}(" + ", ".join(self._signature(extra)) + "):"]
        return "\n".join(head + self.lines) + "\n"

    def emit_kernel(self, name: str, groups: dict) -> str:
        """The tangent kernel: the primal's parameters in their groups (``groups``: name -> group of the
        primal's signature comments), ``Tangent in`` after the input groups, ``Tangent out`` last (the
        order ``tools/lint_kernels.py`` asks for); :attr:`arguments` records the order."""
        self.statements(self.fn.body, 1)
        tan_in = [n for n in self.params if n in self.active_arrays and n not in self.outputs]
        inputs = [n for n in self.params if groups.get(n) in _INPUT_GROUPS]
        outputs = [n for n in self.params if n not in inputs]
        order = [(groups.get(n), n) for n in inputs] + [("Tangent in", self.tan(n)) for n in tan_in]
        order += [(groups.get(n), n) for n in outputs] + [("Tangent out", self.tan(n)) for n in self.outputs]
        self.arguments = [n for _, n in order]
        head = ["@wp.kernel", f"def {name}("]
        group = None
        for g, n in order:
            if g != group and g is not None:
                head.append(f"    # {g}:")
            group = g
            ann = (self.annotation_source(n[len(_PREFIX):], 1) if n.startswith(_PREFIX) and n not in self.params
                   else self.annotation_source(n))
            head.append(f"    {n}: {ann},")
        head.append("):")
        return "\n".join(head + self.lines) + "\n"


_INPUT_GROUPS = ("Model", "State in", "Control", "Adjoint in", "Tangent in")


def _parameter_groups(pyfunc) -> dict:
    """name -> group of a kernel's parameters, from the comment lines of its signature (``# State in:``;
    a remark in parentheses dropped); empty where the signature has none."""
    lines = textwrap.dedent(inspect.getsource(pyfunc)).splitlines()
    groups, group = {}, None
    start = next(i for i, line in enumerate(lines) if line.lstrip().startswith("def "))
    for line in lines[start + 1:]:
        text = line.strip()
        if text.startswith("):") or text.startswith(")"):
            break
        if text.startswith("#"):
            group = text[1:].split(":")[0].split("(")[0].strip()
        elif ":" in text and group is not None:
            groups[text.split(":")[0].strip()] = group
    return groups


def _is_project(obj) -> bool:
    """A ``@wp.func`` written in Python (not a Warp builtin)."""
    return isinstance(obj, _FunctionType) and getattr(obj, "func", None) is not None and not getattr(
        obj, "is_builtin", lambda: False)()


def _plus(a: str | None, b: str | None) -> str | None:
    if a is None:
        return b
    if b is None:
        return a
    return f"({a}) + ({b})"


class TangentKernel:
    """A generated tangent kernel and how to launch it.

    Attributes:
        kernel: the Warp kernel ``<key>_tangent``.
        params: the primal kernel's parameter names, in order.
        tangent_inputs: the inputs whose tangent arrays it takes, in order.
        tangent_outputs: the arrays it writes, whose tangent arrays follow, in order.
        source: the generated source.
    """

    def __init__(self, kernel, params, arguments, tangent_inputs, tangent_outputs, source):
        self.kernel = kernel
        self.params = params
        self.arguments = arguments
        self.tangent_inputs = tangent_inputs
        self.tangent_outputs = tangent_outputs
        self.source = source

    def launch(self, dim, directions: int, args: list, tangents: dict, device=None) -> None:
        """Launches the primal pass (``args``: the primal kernel's arguments, inputs then outputs, in
        signature order) and its tangents along ``directions`` directions (``tangents``: name -> array
        with the leading direction axis, for every name in ``tangent_inputs`` and ``tangent_outputs``)."""
        dim = (dim,) if isinstance(dim, int) else tuple(dim)
        if len(args) != len(self.params):
            raise ValueError(f"{self.kernel.key}: {len(args)} arguments for {len(self.params)} parameters")
        missing = [n for n in self.tangent_inputs + self.tangent_outputs if n not in tangents]
        if missing:
            raise ValueError(f"{self.kernel.key}: no tangent arrays for {missing}")
        values = dict(zip(self.params, args))
        values.update({f"{_PREFIX}{n}": a for n, a in tangents.items()})
        wp.launch(self.kernel, dim=(int(directions), *dim), inputs=[values[n] for n in self.arguments],
                  device=device)


_CACHE: dict = {}


def tangent_kernel(kernel, tangent_names=TANGENT_NAMES) -> TangentKernel:
    """The tangent kernel of a Warp kernel (cached per kernel and set of tangent names).

    Args:
        kernel: a ``@wp.kernel`` (hand-written; closures are resolved).
        tangent_names: names of the array parameters whose tangents the kernel takes.
    """
    key = (id(kernel), frozenset(tangent_names))
    if key in _CACHE:
        return _CACHE[key]
    b = _Builder()
    t = _Transform(b, kernel.func, set(), kernel=True, tangent_names=frozenset(tangent_names))
    name = f"{kernel.key}_tangent"
    body = t.emit_kernel(name, _parameter_groups(kernel.func))
    described = "".join(f"# {a} = {_describe(o)}\n" for a, o in b.env.items())
    source = ("# Generated by dmarionette.kernels.kernel_tangent; do not edit.\n" + described
              + "import warp as wp\n\nwp.set_module_options({'enable_backward': False})\n\n\n"
              + "\n\n".join(b.funcs + [body]))
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    module = import_generated(f"dmarionette_tangent_{kernel.key}_{digest}", source, b.env)
    ins = [a for a in t.params if a in t.active_arrays and a not in t.outputs]
    result = TangentKernel(getattr(module, name), t.params, t.arguments, ins, list(t.outputs), source)
    _CACHE[key] = result
    return result
