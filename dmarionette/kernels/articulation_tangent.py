"""Tangent-linear (forward-mode) kernels of the generated articulation kernels, by a
source-to-source transformation of their straight-line code.

Warp's tape is reverse mode only. The kernels of :mod:`articulation_codegen` are
straight-line (SSA) code: one assignment per line, no loop, no branch, no value written
twice. :func:`tangent_kernel_source` parses such a kernel with :mod:`ast` and writes a
kernel ``<name>_tangent`` that computes, per thread (world), the primal values once (the
same statements, nested subexpressions hoisted into temporaries ``_a<n>``) and then, in
one loop ``for p in range(direction_count)``, the directional derivative of every active
value along direction ``p``: for ``y = expr`` it emits ``tan_y = d(expr)``.
:func:`build_articulation_tangent_kernels` does this for ``eval_body_kinematics``,
``solve_body_dynamics`` (joint limits compiled in or out, as the topology says),
``integrate_joint_coordinates`` and ``eval_mass_matrix`` of a topology, writes the module
next to the primal one (cache folder, named by hash) and imports it.

Tangent kernel signature: the primal kernel's parameters in their groups, then
``direction_count: int`` (Control), and a tangent array ``tan_<name>`` with a leading
direction axis (``wp.array2d`` -> ``wp.array3d``, same dtype; read as
``tan_<name>[p, w, ...]``) for every input in :data:`TANGENT_INPUTS` that the kernel has
(in the group of its primal) and for every array the kernel writes (State out). The
tangent kernel also writes the primal outputs: one launch gives the step and its P
directional derivatives. Every other input is a constant (tangent 0): the model (masses,
inertias, damping, gravity, limits, limit stiffness and damping) and the scalars ``h``,
``h_implicit``.

Rules (the derivative of the formula the primal evaluates, so that the tangent agrees
with Warp's adjoint of the same kernel to rounding):

- names and array reads: the tangent name / the tangent array read (0 for a constant);
- ``+``, ``-`` (binary, unary), indexing of a local value: linear;
- ``*``: product rule ``a_t b + a b_t`` (every ``*`` in the generated code is bilinear:
  scalar x scalar/vector/quaternion/matrix, matrix x vector, quaternion x quaternion,
  spatial66 x spatial6); ``/``: ``y = a / b`` with a scalar ``b``: ``(a_t - y b_t) / b``;
- the dynamics' tree-sparse ``L^T L`` factorisation and two triangular solves of
  ``H qdd = tau`` (the statements ``Emitter._factor_and_solve`` records as ``solve``):
  differentiated as a whole, ``qdd_t = H^-1 (tau_t - H_t qdd)`` by the same two solves
  with the primal's ``L`` (``H_t`` and ``tau_t`` from their statements' rules); no value
  inside the solve has a tangent of its own (a rule needing one raises). This is the
  same derivative with a quarter of the work of differentiating the factorisation;
- linear functions (``wp.vec3d``, ``wp.quatd``, ``spatial6`` constructors from scalars,
  ``compute_spatial``, ``compute_top``, ``compute_bottom``): the function of the
  tangents; bilinear ones (``wp.cross``, ``wp.dot``, ``compute_cross_motion``,
  ``compute_cross_force``): product rule;
- ``wp.sqrt``, ``wp.atan2``: closed form (as Warp's adjoints);
- ``wp.quat_rotate``, ``wp.quat_from_axis_angle``, ``compute_rotation_motion``,
  ``compute_quat_from_mj``, ``compute_quat_integrate``, ``compute_smooth_norm``: the
  ``@wp.func`` ``<name>_tangent`` of :mod:`articulation_math_tangent` (one rule per
  function, written once); ``compute_spatial_inertia``: ``..._tangent_pose``, along the
  pose only (mass and inertia are model constants; an active one raises);
- switches ``wp.max``, ``wp.min``, ``wp.clamp``, ``wp.abs``, ``wp.where`` (scalar
  float64 operands): the tangent of the branch taken, with ties broken as Warp's adjoints
  break them (``max(a, b)``: ``a`` if ``a > b`` else ``b``; ``min``: ``a`` if ``a < b``
  else ``b``; ``clamp(x, lo, hi) = min(max(lo, x), hi)`` composed from those; ``abs``:
  ``-x`` if ``x < 0``), so forward and reverse agree at exact ties too; comparisons and
  ``wp.where``'s condition carry no tangent.

Values the rules need that depend on the primal only (``1 / b`` of a division, ``0.5 / y``
of a square root, the branch a switch takes, and the partial derivatives of a
``<name>_tangent`` function whose active arguments have at most 4 scalar components, e.g.
the hinge quaternion's derivative in its angle, or ``quat_rotate(r, a)``'s 3x4 Jacobian in
``r`` for a constant ``a``) are computed once, before the direction loop, as ``_c<n>``:
the loop holds only what is linear in the tangents.

Cost (``benchmarks/bench_puppet_tangent.py``, CPU, -O2, 16 worlds, the shipped puppet):
one tangent step costs about 2-3 primal steps for P = 1 and about 1.3-1.4 more per
direction (P = 16: about 20-24x), above issue 13's target ``1 + 0.5 P``: the loop is
scalar code, about as many floating-point operations per direction as the primal (the
product rule doubles the bilinear terms); reaching 0.5 per direction needs the
directions packed into SIMD lanes (vector-valued tangents), not done.

Anything else (another statement kind, operator or function, keyword arguments, an
active index, ``wp.float64(...)`` of an active value) raises
:class:`TangentError` naming the construct: no term is ever dropped silently.

The hand-written kernels of a puppet step (body contact, the point springs and external
forces) and of the coupling and the feedback have loops and branches, not SSA code: their
tangents come from the interleaved transformer of :mod:`dmarionette.kernels.kernel_tangent`
(a thread per direction). Here the tangents of their outputs (``body_wrench``,
``body_stiffness``) are inputs of the dynamics tangent; the whole puppet step is
:class:`~dmarionette.articulation.step_tangent.PuppetStepTangent`.
"""

from __future__ import annotations

import ast
import hashlib
import re

from dmarionette.kernels.articulation_codegen import ArticulationTopology, Emitter, import_generated

__all__ = [
    "TANGENT_INPUTS",
    "TangentError",
    "articulation_tangent_source",
    "build_articulation_tangent_kernels",
    "tangent_kernel_source",
]

# Inputs whose tangents the kernels take (every other input is a constant).
TANGENT_INPUTS = ("joint_q", "joint_qd", "body_pos", "body_rot", "body_w", "body_v",
                  "body_wrench", "body_stiffness", "joint_f")

_HEADER = '''# Generated by dmarionette.kernels.articulation_tangent; do not edit.
import warp as wp
from dmarionette.kernels.articulation_math import (
    spatial6, spatial66, compute_spatial, compute_top, compute_bottom,
    compute_rotation_motion, compute_cross_motion, compute_cross_force,
    compute_spatial_inertia, compute_quat_from_mj, compute_quat_integrate,
    compute_smooth_norm,
)
from dmarionette.kernels.articulation_math_tangent import (
    quat_rotate_tangent, quat_from_axis_angle_tangent, compute_rotation_motion_tangent,
    compute_spatial_inertia_tangent_pose, compute_quat_from_mj_tangent,
    compute_quat_integrate_tangent, compute_smooth_norm_tangent,
)
'''

_PREFIX = "tan_"
_TEMP = "_a"
_COEF = "_c"
_SOLVE = "_s"

# Zero of a type, as a name the tangent kernel defines first.
_ZERO = {"wp.float64": "_zero", "wp.vec3d": "_zero3", "wp.quatd": "_zeroq", "spatial6": "spatial6()",
         "spatial66": "spatial66()"}
_ZERO_LINES = ("_zero = wp.float64(0.0)", "_zero3 = wp.vec3d(_zero, _zero, _zero)",
               "_zeroq = wp.quatd(_zero, _zero, _zero, _zero)")

_LINEAR = {"wp.vec3d": ("wp.float64",) * 3, "wp.quatd": ("wp.float64",) * 4, "spatial6": ("wp.float64",) * 6,
           "compute_spatial": ("wp.vec3d", "wp.vec3d"), "compute_top": ("spatial6",),
           "compute_bottom": ("spatial6",)}
_BILINEAR = ("wp.cross", "wp.dot", "compute_cross_motion", "compute_cross_force")
# name -> (tangent function, argument types)
_TANGENT_FUNC = {
    "wp.quat_rotate": ("quat_rotate_tangent", ("wp.quatd", "wp.vec3d")),
    "wp.quat_from_axis_angle": ("quat_from_axis_angle_tangent", ("wp.vec3d", "wp.float64")),
    "compute_rotation_motion": ("compute_rotation_motion_tangent", ("wp.vec3d", "wp.vec3d")),
    "compute_spatial_inertia": (None, ("wp.float64", "wp.vec3d", "wp.quatd", "wp.vec3d")),  # see _CONSTANT_ARGS
    "compute_quat_from_mj": ("compute_quat_from_mj_tangent", ("wp.float64",) * 4),
    "compute_quat_integrate": ("compute_quat_integrate_tangent", ("wp.quatd", "wp.vec3d", "wp.float64")),
    "compute_smooth_norm": ("compute_smooth_norm_tangent", ("wp.vec3d",)),
}
# Functions whose tangent rule holds some arguments constant: name -> (tangent function, constant argument
# indices); it takes the primal arguments, then the tangents of the others.
_CONSTANT_ARGS = {"compute_spatial_inertia": ("compute_spatial_inertia_tangent_pose", (0, 1))}
# Scalar components per type; at most _PARTIALS_MAX active components: partial derivatives hoisted.
_DIM = {"wp.float64": 1, "wp.vec3d": 3, "wp.quatd": 4}
_PARTIALS_MAX = 4


def _unit(ty: str, k: int) -> str:
    """The k-th unit value of a type (``wp.float64``: one)."""
    if ty == "wp.float64":
        return "wp.float64(1.0)"
    comps = ["wp.float64(1.0)" if i == k else "_zero" for i in range(_DIM[ty])]
    return f"{ty}({', '.join(comps)})"


_CONSTANT_FUNCS = ("wp.tid", "wp.float64")  # results carry no tangent (their arguments must be constant)


class TangentError(ValueError):
    """A construct the forward-mode transformer has no rule for."""


def _src(node: ast.AST) -> str:
    return ast.unparse(node)


def _fail(node: ast.AST, why: str):
    raise TangentError(f"articulation_tangent: no tangent rule for `{_src(node)}`: {why}")


class _Kernel:
    """One kernel's transformation (see the module doc)."""

    def __init__(self, source: str, solve: dict | None = None):
        tree = ast.parse(source)
        self.solve = solve
        self.forbidden: set[str] = set()  # defined inside the linear solve; no tangent of their own
        if len(tree.body) != 1 or not isinstance(tree.body[0], ast.FunctionDef):
            raise TangentError("articulation_tangent: expected the source of one kernel")
        self.fn = tree.body[0]
        self.groups = _parameter_groups(source)  # [(group, [(name, annotation)])]
        self.params = {n: a for _, ps in self.groups for n, a in ps}
        used = {n.id for n in ast.walk(self.fn) if isinstance(n, ast.Name)} | set(self.params)
        clash = sorted(n for n in used
                       if n.startswith((_PREFIX, _TEMP, _COEF, _SOLVE, "_zero")) or n in ("p", "direction_count"))
        if clash:
            raise TangentError(f"articulation_tangent: names {clash} clash with the tangent kernel's own")
        self.active: set[str] = {n for n in TANGENT_INPUTS if n in self.params}
        self.outputs: list[str] = []
        self.primal: list[str] = []
        self.tangent: list[str] = []
        self.temps = 0
        self.pending: list[str] = []  # coefficients of the statement being lowered (primal-only values)

    # ------------------------------------------------------------ activity
    def is_array(self, name: str) -> bool:
        return name in self.params and self.params[name].startswith("wp.array")

    def is_active(self, node: ast.AST) -> bool:
        if isinstance(node, ast.Name):
            if node.id in self.forbidden:
                _fail(node, "a value inside the linear solve (only its solution has a tangent)")
            return node.id in self.active and not self.is_array(node.id)
        if isinstance(node, ast.Constant) or isinstance(node, ast.Compare):
            return False
        if isinstance(node, ast.Subscript):
            if isinstance(node.value, ast.Name) and self.is_array(node.value.id):
                return node.value.id in self.active
            return self.is_active(node.value)
        if isinstance(node, ast.Call):
            return any(self.is_active(a) for a in node.args)
        if isinstance(node, ast.BinOp):
            return self.is_active(node.left) or self.is_active(node.right)
        if isinstance(node, ast.UnaryOp):
            return self.is_active(node.operand)
        if isinstance(node, ast.Attribute):
            return False
        if isinstance(node, ast.Tuple):
            return any(self.is_active(e) for e in node.elts)
        _fail(node, f"unsupported expression kind {type(node).__name__}")

    # ------------------------------------------------------------ lowering
    def atom(self, node: ast.AST) -> ast.AST:
        """``node`` if it is constant, a name or an array read; else a fresh temporary holding it."""
        if not self.is_active(node) or isinstance(node, ast.Name):
            return node
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and self.is_array(node.value.id):
            return node
        self.temps += 1
        name = f"{_TEMP}{self.temps}"
        self.assign(name, node)
        return ast.Name(name)

    def assign(self, name: str, node: ast.AST) -> None:
        """``name = node``: the primal statement and, if active, its tangent statement."""
        node, tan = self.lower(node, name)
        self.primal.append(f"{name} = {_src(node)}")
        self.primal += self.pending
        self.pending = []
        if tan is not None:
            self.active.add(name)
            self.tangent.append(f"{_PREFIX}{name} = {tan}")

    def lower(self, node: ast.AST, result: str) -> tuple[ast.AST, str | None]:
        """(the node with active operands reduced to atoms, its tangent expression or None)."""
        if not self.is_active(node):
            return node, None
        if isinstance(node, ast.Name) or (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name)
                                          and self.is_array(node.value.id)):
            return node, self.tan(node)
        if isinstance(node, ast.Subscript):
            if self.is_active(node.slice):
                _fail(node, "an active index")
            node = ast.Subscript(self.atom(node.value), node.slice)
            return node, f"{self.tan(node.value)}[{_src(node.slice)}]"
        if isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, ast.USub):
                _fail(node, f"unary operator {type(node.op).__name__}")
            node = ast.UnaryOp(node.op, self.atom(node.operand))
            return node, f"-({self.tan(node.operand)})"
        if isinstance(node, ast.BinOp):
            node = ast.BinOp(self.atom(node.left), node.op, self.atom(node.right))
            return node, self.binop(node, result)
        if isinstance(node, ast.Call):
            if node.keywords:
                _fail(node, "keyword arguments")
            node = ast.Call(node.func, [self.atom(a) for a in node.args], [])
            return node, self.call(node, result)
        _fail(node, f"unsupported expression kind {type(node).__name__}")

    def tan(self, node: ast.AST) -> str | None:
        """Tangent of an atom (None: constant)."""
        if not self.is_active(node):
            return None
        if isinstance(node, ast.Name):
            return f"{_PREFIX}{node.id}"
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and self.is_array(node.value.id):
            idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            return f"{_PREFIX}{node.value.id}[{', '.join(['p'] + [_src(i) for i in idx])}]"
        _fail(node, "not an atom (internal)")

    def coef(self, expr: str) -> str:
        """A name for ``expr``, a value of the primal only, computed once before the direction loop
        (after the statement being lowered: it may use its result)."""
        self.temps += 1
        name = f"{_COEF}{self.temps}"
        self.pending.append(f"{name} = {expr}")
        return name

    # ------------------------------------------------------------ rules
    def binop(self, node: ast.BinOp, result: str) -> str:
        a, b = _src(node.left), _src(node.right)
        ta, tb = self.tan(node.left), self.tan(node.right)
        if isinstance(node.op, ast.Add):
            return _sum([ta, tb])
        if isinstance(node.op, ast.Sub):
            if ta is None:
                return f"-({tb})"
            return ta if tb is None else f"{ta} - {tb}"
        if isinstance(node.op, ast.Mult):
            return _sum([None if ta is None else f"{ta} * {b}", None if tb is None else f"{a} * {tb}"])
        if isinstance(node.op, ast.Div):  # a scalar divisor: 1 / b once, then products
            inv = self.coef(f"wp.float64(1.0) / {b}")
            if tb is None:
                return f"{ta} * {inv}"
            num = f"-({result} * {tb})" if ta is None else f"{ta} - {result} * {tb}"
            return f"({num}) * {inv}"
        _fail(node, f"binary operator {type(node.op).__name__}")

    def call(self, node: ast.Call, result: str) -> str:
        f = _src(node.func)
        args = [_src(a) for a in node.args]
        tans = [self.tan(a) for a in node.args]
        if f in _LINEAR:
            types = _LINEAR[f]
            if len(args) != len(types):
                _fail(node, f"{f} with {len(args)} arguments (rule for {len(types)})")
            return f"{f}({', '.join(t if t is not None else _ZERO[ty] for t, ty in zip(tans, types))})"
        if f in _BILINEAR:
            if len(args) != 2:
                _fail(node, f"{f} with {len(args)} arguments")
            return _sum([None if tans[0] is None else f"{f}({tans[0]}, {args[1]})",
                         None if tans[1] is None else f"{f}({args[0]}, {tans[1]})"])
        if f in _TANGENT_FUNC:
            name, types = _TANGENT_FUNC[f]
            if len(args) != len(types):
                _fail(node, f"{f} with {len(args)} arguments (rule for {len(types)})")
            if f in _CONSTANT_ARGS:
                name, constant = _CONSTANT_ARGS[f]
                if any(tans[i] is not None for i in constant):
                    _fail(node, f"an active argument {[args[i] for i in constant]} (model constants here)")
                rest = [t or _ZERO[ty] for i, (t, ty) in enumerate(zip(tans, types)) if i not in constant]
                return f"{name}({', '.join(args + rest)})"
            if sum(_DIM[ty] for t, ty in zip(tans, types) if t is not None) <= _PARTIALS_MAX:
                # few active scalar components: the partial derivatives once, then sum_k d_k x_t[k]
                terms = []
                for i, (t, ty) in enumerate(zip(tans, types)):
                    for k in range(_DIM[ty] if t is not None else 0):
                        unit = [_unit(ty2, k) if j == i else _ZERO[ty2] for j, ty2 in enumerate(types)]
                        partial = self.coef(f"{name}({', '.join(args + unit)})")
                        terms.append(f"{partial} * {t}" if ty == "wp.float64" else f"{partial} * {t}[{k}]")
                return _sum(terms)
            zeros = [t if t is not None else _ZERO[ty] for t, ty in zip(tans, types)]
            return f"{name}({', '.join(args + zeros)})"
        t = [x if x is not None else "_zero" for x in tans]  # switches and scalar functions: float64 operands
        if f == "wp.sqrt" and len(args) == 1:
            return f"{t[0]} * {self.coef(f'wp.float64(0.5) / {result}')}"
        if f == "wp.atan2" and len(args) == 2:
            y, x = args
            return f"({x} * {t[0]} - {y} * {t[1]}) * {self.coef(f'wp.float64(1.0) / ({x} * {x} + {y} * {y})')}"
        if f == "wp.max" and len(args) == 2:
            return f"wp.where({self.coef(f'{args[0]} > {args[1]}')}, {t[0]}, {t[1]})"
        if f == "wp.min" and len(args) == 2:
            return f"wp.where({self.coef(f'{args[0]} < {args[1]}')}, {t[0]}, {t[1]})"
        if f == "wp.clamp" and len(args) == 3:
            x, lo, hi = args
            inside, low = self.coef(f"wp.max({lo}, {x}) < {hi}"), self.coef(f"{lo} > {x}")
            return f"wp.where({inside}, wp.where({low}, {t[1]}, {t[0]}), {t[2]})"
        if f == "wp.abs" and len(args) == 1:
            return f"wp.where({self.coef(f'{args[0]} < _zero')}, -({t[0]}), {t[0]})"
        if f == "wp.where" and len(args) == 3:
            return f"wp.where({args[0]}, {t[1]}, {t[2]})"
        if f in _CONSTANT_FUNCS:
            _fail(node, f"{f} of an active value")
        _fail(node, f"no rule for function {f}")

    # ------------------------------------------------------------ statements
    def transform(self) -> str:
        body = self.fn.body
        doc = ""
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            doc, body = body[0].value.value, body[1:]
        internal = self.solve["internal"] if self.solve else []
        for st in body:
            if not (isinstance(st, ast.Assign) and len(st.targets) == 1):
                _fail(st, f"statement kind {type(st).__name__} (only single assignments)")
            target = st.targets[0]
            if isinstance(target, ast.Name) and target.id in internal:
                self.primal.append(_src(st))  # the factorisation and solves: primal only
                self.forbidden.add(target.id)
                if target.id == internal[-1]:
                    self.solve_tangent()
            elif isinstance(target, ast.Name):
                self.assign(target.id, st.value)
            elif (isinstance(target, ast.Subscript) and isinstance(target.value, ast.Name)
                  and self.is_array(target.value.id)):
                self.write(target, st.value)
            else:
                _fail(st, "assignment target (a name or an array element)")
        return self.emit(doc)

    def solve_tangent(self) -> None:
        """The tangent of the solution of ``H x = b`` (``L^T L`` factorisation ``L`` already computed):
        ``x' = H^-1 (b' - H' x)``, by the same two triangular solves with ``L``."""
        sv = self.solve
        lam, L, x = sv["lam"], sv["L"], sv["x"]
        n = len(x)

        def anc(i):
            while i >= 0:
                yield i
                i = lam[i]

        def tan_of(name):
            return self.tan(ast.Name(name))

        inv = {i: self.coef(f"wp.float64(1.0) / {L[i, i]}") for i in range(n)}
        self.primal += self.pending
        self.pending = []
        y, version = {}, {}

        def fresh(i):
            version[i] = version.get(i, 0) + 1
            return f"{_PREFIX}{_SOLVE}{i}_{version[i]}"

        for i in range(n):  # b' - H' x (H symmetric, its lower triangle stored)
            terms = [f"{t} * {x[k]}" for (j, k), h in sv["H"].items() if j == i and (t := tan_of(h))]
            terms += [f"{t} * {x[j]}" for (j, k), h in sv["H"].items() if k == i != j and (t := tan_of(h))]
            tb = tan_of(sv["b"][i])
            if tb is None and not terms:
                _fail(ast.Name(x[i]), "a solve with a constant row (internal)")
            y[i] = fresh(i)
            self.tangent.append(f"{y[i]} = {tb or '_zero'} - ({' + '.join(terms) or '_zero'})")
        for i in reversed(range(n)):
            name = fresh(i)
            self.tangent.append(f"{name} = {y[i]} * {inv[i]}")
            y[i] = name
            for j in anc(lam[i]):
                name = fresh(j)
                self.tangent.append(f"{name} = {y[j]} - {L[i, j]} * {y[i]}")
                y[j] = name
        for i in range(n):
            terms = " - ".join([y[i]] + [f"{L[i, j]} * {_PREFIX}{x[j]}" for j in anc(lam[i])])
            self.tangent.append(f"{_PREFIX}{x[i]} = ({terms}) * {inv[i]}")
            self.forbidden.discard(x[i])
            self.active.add(x[i])

    def write(self, target: ast.Subscript, value: ast.AST) -> None:
        arr = target.value.id
        if self.is_active(target.slice):
            _fail(target, "an active index")
        if arr not in self.outputs:
            self.outputs.append(arr)
        value = self.atom(value)
        self.primal.append(f"{_src(target)} = {_src(value)}")
        idx = target.slice.elts if isinstance(target.slice, ast.Tuple) else [target.slice]
        tan = self.tan(value)
        if tan is None:
            tan = _ZERO[_dtype(self.params[arr])]
        self.tangent.append(f"{_PREFIX}{arr}[{', '.join(['p'] + [_src(i) for i in idx])}] = {tan}")

    def emit(self, doc: str) -> str:
        lines = ["@wp.kernel", f"def {self.fn.name}_tangent("]
        ins = [n for n in TANGENT_INPUTS if n in self.params and n not in self.outputs]
        groups = list(self.groups)
        names = [g for g, _ in groups]
        if "State out" not in names:
            raise TangentError(f"articulation_tangent: {self.fn.name} has no State out group")
        if "Control" not in names:
            groups.insert(names.index("State out"), ("Control", []))
        for group, ps in groups:
            lines.append(f"    # {group}:")
            for n, a in ps:
                lines.append(f"    {n}: {a},")
            if group == "Control":
                lines.append("    direction_count: int,")
            for n, a in ps:
                if n in ins:
                    lines.append(f"    {_PREFIX}{n}: {_tangent_annotation(a)},")
            if group == "State out":
                for n in self.outputs:
                    lines.append(f"    {_PREFIX}{n}: {_tangent_annotation(self.params[n])},")
        lines.append("):")
        lines.append(f'    """Tangent (forward mode) of ``{self.fn.name}``: {doc.strip()} '
                     f'Directional derivatives along ``direction_count`` directions."""')
        lines += [f"    {s}" for s in _ZERO_LINES]
        lines += [f"    {s}" for s in self.primal]
        lines.append("    for p in range(direction_count):")
        lines += [f"        {s}" for s in self.tangent]
        return "\n".join(lines) + "\n"


def _sum(terms: list) -> str:
    terms = [t for t in terms if t is not None]
    return " + ".join(f"({t})" if len(terms) > 1 else t for t in terms)


def _dtype(annotation: str) -> str:
    m = re.search(r"dtype=([\w.]+)", annotation)
    if not m or m.group(1) not in _ZERO:
        raise TangentError(f"articulation_tangent: no zero for the array type `{annotation}`")
    return m.group(1)


def _tangent_annotation(annotation: str) -> str:
    """The type of a tangent array: one more (leading) dimension."""
    m = re.fullmatch(r"wp\.array(\d?)d?\((.*)\)", annotation)
    if not m:
        raise TangentError(f"articulation_tangent: not an array type: `{annotation}`")
    dims = int(m.group(1) or 1)
    return f"wp.array{dims + 1}d({m.group(2)})"


def _parameter_groups(source: str) -> list:
    """``[(group, [(name, annotation)])]`` of a generated kernel's signature (its comment groups)."""
    head = source.split("):\n", 1)[0].split("(\n", 1)[1]
    groups = []
    for line in head.splitlines():
        line = line.strip()
        if line.startswith("#"):
            groups.append((line[1:].strip().rstrip(":"), []))
        elif line:
            name, annotation = line.rstrip(",").split(":", 1)
            if not groups:
                raise TangentError("articulation_tangent: a parameter outside a group")
            groups[-1][1].append((name.strip(), annotation.strip()))
    return groups


def tangent_kernel_source(source: str, solve: dict | None = None) -> str:
    """The source of ``<name>_tangent`` for the source of one generated straight-line kernel.

    Args:
        source: the kernel's source (decorator, signature with its parameter groups, body).
        solve: a linear solve in it, as ``Emitter`` records it (``_factor_and_solve``), to
            differentiate as a whole (or None: every statement by its rule).
    """
    return _Kernel(source, solve).transform()


def articulation_tangent_source(topo: ArticulationTopology, optimization_level: int = 1) -> str:
    """The tangent module's source for ``topo`` (see :func:`build_articulation_tangent_kernels`)."""
    em = Emitter(topo)
    # no adjoint code: the tangent kernels are not differentiated again (and compile in half the time)
    options = (f'wp.set_module_options({{"optimization_level": {int(optimization_level)}, '
               f'"enable_backward": False}})\n')
    kernels = [(em.kinematics(), None)]
    kernels.append((em.dynamics(), em.solve))
    kernels += [(em.integrate(), None), (em.mass_matrix(), None)]
    return "\n\n".join([_HEADER + options] + [tangent_kernel_source(k, solve) for k, solve in kernels])


def build_articulation_tangent_kernels(topo: ArticulationTopology, optimization_level: int = 1):
    """Generates, writes and imports the tangent kernels for ``topo`` (cached per topology).

    Returns:
        A module with ``eval_body_kinematics_tangent``, ``solve_body_dynamics_tangent``,
        ``integrate_joint_coordinates_tangent`` and ``eval_mass_matrix_tangent``.
    """
    source = articulation_tangent_source(topo, optimization_level)
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    return import_generated(f"dmarionette_articulation_tangent_{digest}", source)
