"""The interleaved tangent transformation of one Warp kernel (:mod:`kernel_tangent`): the analysis
and the emission of each statement's primal, then its tangent.

:class:`TangentTransform` parses a kernel's (or a ``@wp.func``'s) Python source with :mod:`ast`.
Free names (a closure's cells, module globals, attribute chains on non-module objects) are resolved
to the objects they name, which the generated module holds as globals ``_glb<n>``
(:class:`TangentBuilder`); Python scalar constants are written in as literals. Activity is
flow-insensitive: a fixed point over all assignments, starting from the kernel's array parameters
named in ``tangent_names`` and the array fields of its struct parameters so named that it reads
(``model.string_stiffness[s]``: the tangent array ``tan_string_stiffness``, named by the field; a
function's: the active arguments); a value that is active somewhere
but assigned a constant elsewhere gets the tangent ``y - y``, zero of its type (finite ``y``).

Emission: ``wp.tid()`` gains a leading direction index ``_dir``; control flow is kept as it is
(``if``/``for``, early ``return``, ``+=``/``-=`` on locals, element writes of local vectors and
matrices), an ``if`` running the branch the primal runs (its condition carries no tangent). Every
active value ``y`` gets its tangent ``tan_y`` right after it, operands reduced to atoms (temporaries
``_tmp<n>``) and the tangent written by the rules of :mod:`kernel_tangent_rules`. Calls of project
``@wp.func``s with an active argument become ``<name>_jvp<n>`` functions (one per function and
pattern of active arguments, emitted once, after their callees) returning the primal results, then
the tangents of the active ones. ``wp.atomic_add(a, i.., x)``: also ``wp.atomic_add(tan_a, _dir,
i.., x_t)``; ``a[i] = x``: also ``tan_a[_dir, i] = x_t``; the primal outputs are written by the
direction-0 threads only. Unrolled layout (``TangentBuilder(width)``): ``wp.tid()`` gains the
block index ``_blk`` and the directions ``_dir_d<k> = _blk * width + k``; a tangent line carries a
mark where the direction number goes and :meth:`TangentTransform.emit` writes it once per
direction (locals ``tan_y_d<k>``); a jvp function takes and returns ``width`` tangents per active
value (:meth:`TangentTransform.each_of`); the primal outputs are written by block 0.

Anything else (``**``, keyword arguments on an active call, an active ``if`` condition or index, a
tuple returned into an expression, another statement kind) raises
:class:`~dmarionette.kernels.articulation_tangent.TangentError` naming the construct.
"""

from __future__ import annotations

import ast
import builtins
import inspect
import textwrap
import typing

import warp as wp

from dmarionette.kernels.articulation_math import compute_spatial
from dmarionette.kernels.articulation_tangent import TangentError
from dmarionette.kernels.kernel_tangent_rules import RuleMissing, binary_tangent, call_tangent, unary_tangent

__all__ = ["TANGENT_PREFIX", "TangentBuilder", "TangentTransform", "parameter_groups"]

_FunctionType = type(compute_spatial)  # warp's @wp.func object
TANGENT_PREFIX = "tan_"
_DIR = "_dir"
_BLOCK = "_blk"  # the launch's leading index in the unrolled layout: the block of directions
_MARK = "@D"  # in the unrolled layout, where a tangent line's direction number goes (``emit``)
_TMP = "_tmp"
_GLB = "_glb"
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


class TangentBuilder:
    """One tangent module: the globals its source refers to and the functions it has generated."""

    def __init__(self, width: int | None = None):
        self.width = width  # None: one thread per (direction, thread); n: n directions unrolled per thread
        self.env: dict[str, object] = {}
        self.alias_of: dict[int, str] = {}
        self.funcs: list[str] = []
        self.analysed: dict[tuple, TangentTransform] = {}  # (id(function), active mask) -> its analysed transform
        self.jvp: dict[tuple, str] = {}  # (id(function), active mask) -> the name of its emitted jvp function
        self.count = 0

    def alias(self, obj) -> str:
        if id(obj) not in self.alias_of:
            name = f"{_GLB}{len(self.alias_of)}"
            self.alias_of[id(obj)] = name
            self.env[name] = obj
        return self.alias_of[id(obj)]

    def described_globals(self) -> str:
        """One comment line per global the module's source refers to, saying what it is."""
        return "".join(f"# {a} = {_describe(o)}\n" for a, o in self.env.items())

    def analysis(self, fn, mask: tuple) -> TangentTransform:
        """The transform of ``fn`` with the arguments of ``mask`` active, analysed (not emitted)."""
        key = (id(fn), mask)
        if key not in self.analysed:
            self.analysed[key] = TangentTransform(self, fn.func, {i for i, a in enumerate(mask) if a}, kernel=False)
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


class TangentTransform:
    """The transformation of one kernel or function (module doc)."""

    def __init__(self, builder: TangentBuilder, pyfunc, active_params: set, kernel: bool, tangent_names=()):
        self.b = builder
        self.width = builder.width
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
        clash = sorted(n for n in self.locals if n.startswith((TANGENT_PREFIX, _TMP, _GLB)) or n in (_DIR, _BLOCK)
                       or n.startswith(_DIR + "_d"))
        if clash:
            raise TangentError(f"kernel_tangent: {self.where}: names {clash} clash with the tangent code's own")
        # Annotations are evaluated where the function is defined (a closure's are not cells): their objects.
        self.annotation = {}
        for a in fn.args.args:
            ann = pyfunc.__annotations__.get(a.arg)
            self.annotation[a.arg] = eval(ann, scope) if isinstance(ann, str) else ann  # noqa: S307 (the source's own)
        self._resolve(scope)
        self.arrays = {n for n, a in self.annotation.items() if isinstance(a, wp.array)}
        # A struct parameter's array fields, by field name: (parameter, array type) (:meth:`_struct_fields`).
        self.fields = self._struct_fields(tangent_names) if kernel else {}
        if kernel:
            self.active_arrays = {n for n in self.arrays if n in tangent_names}
            self.active_fields = self._read_fields() & set(tangent_names)
            self.active = set()
        else:
            if self.arrays:
                raise TangentError(f"kernel_tangent: {self.where}: a function taking arrays")
            self.active_arrays = set()
            self.active_fields = set()
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
            return self.array_source(a, lead)
        if lead:
            raise TangentError(f"kernel_tangent: {self.where}: a tangent of the non-array {name}")
        return self._type_source(a)

    def array_source(self, a, lead: int = 0) -> str:
        """The source of the array type ``a`` with ``lead`` more leading dimensions."""
        return f"wp.array{a.ndim + lead}d(dtype={self._type_source(a.dtype)})"

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

    def _struct_fields(self, tangent_names) -> dict:
        """Field name -> (struct parameter, array type) of the struct parameters' array fields; a field
        named in ``tangent_names`` that is also another parameter's or another struct's field raises (a
        tangent is named by its field)."""
        fields: dict = {}
        for n in self.params:
            a = self.annotation[n]
            if not _is_struct(a):
                continue
            for f, var in a.vars.items():
                if not isinstance(var.type, wp.array) or f in fields or f in self.params:
                    if f in tangent_names and isinstance(var.type, wp.array):
                        raise TangentError(f"kernel_tangent: {self.where}: the array field {n}.{f} has the name "
                                           f"of another parameter or field (a field's tangent is named by the field)")
                    continue
                fields[f] = (n, var.type)
        return fields

    def field_of(self, node: ast.AST) -> str | None:
        """The field name where ``node`` is a struct parameter's array field (``model.string_stiffness``)."""
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.attr in self.fields
                and self.fields[node.attr][0] == node.value.id):
            return node.attr
        return None

    def _read_fields(self) -> set:
        """The struct parameters' array fields the kernel reads (an element read ``p.f[i]``)."""
        return {f for n in ast.walk(self.fn) if isinstance(n, ast.Subscript) and isinstance(n.ctx, ast.Load)
                and (f := self.field_of(n.value)) is not None}

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
            if self.field_of(node.value) is not None:
                return self.field_of(node.value) in self.active_fields
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
        """Appends a line; in the unrolled layout a tangent line (one holding the mark) once per direction."""
        for text in self.each(line):
            self.lines.append("    " * indent + text)

    def each(self, text: str) -> list[str]:
        """``text`` for each direction of a thread: itself in the one-direction layout; in the unrolled
        layout, once per direction with the mark replaced by the direction's number (``tan_y_d0``, ...)."""
        if self.width is None or _MARK not in text:
            return [text]
        return [text.replace(_MARK, str(k)) for k in range(self.width)]

    def each_of(self, texts) -> list[str]:
        """Every item once per direction, in order (the tangents of one value together); an item without
        the mark (a zero ``y - y``) is the same in every direction."""
        if self.width is None:
            return list(texts)
        return [t.replace(_MARK, str(k)) for t in texts for k in range(self.width)]

    def direction(self) -> str:
        """The direction index of a tangent array's element, in a tangent line."""
        return _DIR if self.width is None else f"{_DIR}_d{_MARK}"

    def first(self) -> str:
        """The condition of the threads that write the primal outputs."""
        return f"{_DIR} == 0" if self.width is None else f"{_BLOCK} == 0"

    def temp(self) -> str:
        self.temps += 1
        return f"{_TMP}{self.temps}"

    def tan(self, name: str) -> str:
        """The tangent of a local (in the unrolled layout: with the mark, one per direction)."""
        return f"{TANGENT_PREFIX}{name}" if self.width is None else f"{TANGENT_PREFIX}{name}_d{_MARK}"

    def tan_array(self, name: str) -> str:
        """The tangent array of an array parameter (all directions along its leading axis)."""
        return f"{TANGENT_PREFIX}{name}"

    def atom(self, node: ast.AST, indent: int) -> tuple[str, str | None]:
        """(source of a name/constant/array read holding the value, its tangent or None)."""
        if isinstance(node, (ast.Name, ast.Constant)):
            return _src(node), (self.tan(node.id) if isinstance(node, ast.Name) and node.id in self.active else None)
        if (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id in self.arrays):
            if node.value.id not in self.active_arrays:
                return _src(node), None
            idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            return _src(node), f"{self.tan_array(node.value.id)}[{', '.join([self.direction()] + [_src(i) for i in idx])}]"
        if isinstance(node, ast.Subscript) and (field := self.field_of(node.value)) is not None:
            if field not in self.active_fields:
                return _src(node), None
            idx = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            return _src(node), f"{self.tan_array(field)}[{', '.join([self.direction()] + [_src(i) for i in idx])}]"
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
        if isinstance(node, (ast.Name, ast.Constant)) or (isinstance(node, ast.Subscript) and (isinstance(
                node.value, ast.Name) and node.value.id in self.arrays or self.field_of(node.value) is not None)):
            return self.atom(node, indent)
        if isinstance(node, ast.Subscript):
            if self.is_active(node.slice):
                _fail(self.where, node, "an active index")
            a, ta = self.atom(node.value, indent)
            return f"{a}[{_src(node.slice)}]", f"{ta}[{_src(node.slice)}]"
        if isinstance(node, ast.UnaryOp):
            a, ta = self.atom(node.operand, indent)
            return self._rule(node, unary_tangent, node.op, a, ta)
        if isinstance(node, ast.BinOp):
            a, ta = self.atom(node.left, indent)
            b, tb = self.atom(node.right, indent)
            return self._rule(node, binary_tangent, node.op, a, ta, b, tb)
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
            call = ", ".join([a for a, _ in atoms] + self.each_of(t for _, t in atoms if t))
            self.emit(f"{', '.join([res] + self.each(self.tan(res)))} = {name}({call})", indent)
            return res, self.tan(res)
        atoms = [self.atom(a, indent) for a in node.args]
        args = [a for a, _ in atoms]
        tans = [t for _, t in atoms]
        res = self.temp()
        self.emit(f"{res} = {f}({', '.join(args)})", indent)
        return res, self._rule(node, call_tangent, f, obj, args, tans, res, self.b.alias)

    def _rule(self, node: ast.AST, rule, *operands):
        """``rule(*operands)`` (:mod:`kernel_tangent_rules`), its missing rule a :class:`TangentError`."""
        try:
            return rule(*operands)
        except RuleMissing as e:
            _fail(self.where, node, str(e))

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
            self.tid(_src(t), indent)
            return
        if isinstance(t, ast.Tuple) and isinstance(v, ast.Call) and _src(v.func) == "wp.tid":
            self.tid(', '.join(_src(e) for e in t.elts), indent)
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
                tnames = [self.tan(n) if n in self.active else self.temp_tangent() for n, a in zip(names, out) if a]
                self.emit(f"{', '.join(names + self.each_of(tnames))} = "
                          f"{name}({', '.join([a for a, _ in atoms] + self.each_of(x for _, x in atoms if x))})",
                          indent)
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
                self.emit(f"if {self.first()}:", indent)
                self.emit(f"{_src(t)} = {x}", indent + 1)
                idx = t.slice.elts if isinstance(t.slice, ast.Tuple) else [t.slice]
                self.emit(f"{self.tan_array(arr)}[{', '.join([self.direction()] + [_src(i) for i in idx])}] = "
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
        self.emit(f"if {self.first()}:", indent)
        self.emit(f"wp.atomic_add({', '.join([arr.id] + ids + [x])})", indent + 1)
        if tx is not None:
            self.emit(f"wp.atomic_add({', '.join([self.tan_array(arr.id), self.direction()] + ids + [tx])})", indent)

    def tid(self, targets: str, indent: int) -> None:
        """``wp.tid()`` with the leading direction index (one-direction layout) or the leading block of
        ``width`` directions and their numbers (unrolled layout)."""
        if self.width is None:
            self.emit(f"{_DIR}, {targets} = wp.tid()", indent)
            return
        self.emit(f"{_BLOCK}, {targets} = wp.tid()", indent)
        self.emit(f"{_DIR}_d{_MARK} = {_BLOCK} * {self.width} + {_MARK}", indent)

    def temp_tangent(self) -> str:
        """A temporary for an unused tangent result (one per direction in the unrolled layout)."""
        name = self.temp()
        return name if self.width is None else f"{name}_d{_MARK}"

    def ret(self, st: ast.Return, indent: int) -> None:
        if self.kernel:
            if st.value is not None:
                _fail(self.where, st, "a kernel returning a value")
            self.emit("return", indent)
            return
        elts = st.value.elts if isinstance(st.value, ast.Tuple) else [st.value]
        atoms = [self.atom(e, indent) for e in elts]
        tans = [(t if t is not None else self.zero(a)) for (a, t), m in zip(atoms, self.out_mask) if m]
        self.emit(f"return {', '.join([a for a, _ in atoms] + self.each_of(tans))}", indent)

    # ------------------------------------------------------------ definitions
    def _signature(self, extra: list[str]) -> list[str]:
        return [f"{n}: {self.annotation_source(n)}" for n in self.params] + extra

    def emit_function(self, name: str) -> str:
        self.statements(self.fn.body, 1)
        extra = self.each_of(f"{self.tan(n)}: {self.annotation_source(n)}" for n in self.params if n in self.active)
        head = ["@wp.func", f"def {name}(" + ", ".join(self._signature(extra)) + "):"]
        return "\n".join(head + self.lines) + "\n"

    def emit_kernel(self, name: str, groups: dict) -> str:
        """The tangent kernel: the primal's parameters in their groups (``groups``: name -> group of the
        primal's signature comments), ``Tangent in`` after the input groups, ``Tangent out`` last (the
        order ``tools/lint_kernels.py`` asks for); :attr:`arguments` records the order."""
        self.statements(self.fn.body, 1)
        tan_in = [n for n in self.params if n in self.active_arrays and n not in self.outputs]
        tan_in += [f for f in self.fields if f in self.active_fields]  # a struct's fields read with tangents
        inputs = [n for n in self.params if groups.get(n) in _INPUT_GROUPS]
        outputs = [n for n in self.params if n not in inputs]
        order = [(groups.get(n), n) for n in inputs] + [("Tangent in", self.tan_array(n)) for n in tan_in]
        order += [(groups.get(n), n) for n in outputs] + [("Tangent out", self.tan_array(n)) for n in self.outputs]
        self.arguments = [n for _, n in order]
        head = ["@wp.kernel", f"def {name}("]
        group = None
        for g, n in order:
            if g != group and g is not None:
                head.append(f"    # {g}:")
            group = g
            tangent_of = n[len(TANGENT_PREFIX):] if n.startswith(TANGENT_PREFIX) and n not in self.params else None
            if tangent_of in self.fields:
                ann = self.array_source(self.fields[tangent_of][1], 1)
            else:
                ann = self.annotation_source(tangent_of, 1) if tangent_of is not None else self.annotation_source(n)
            head.append(f"    {n}: {ann},")
        head.append("):")
        return "\n".join(head + self.lines) + "\n"


_INPUT_GROUPS = ("Model", "State in", "Control", "Adjoint in", "Tangent in")


def parameter_groups(pyfunc) -> dict:
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


def _is_struct(t) -> bool:
    """A ``wp.struct`` type."""
    return hasattr(t, "vars") and hasattr(t, "cls")


def _is_project(obj) -> bool:
    """A ``@wp.func`` written in Python (not a Warp builtin)."""
    return isinstance(obj, _FunctionType) and getattr(obj, "func", None) is not None and not getattr(
        obj, "is_builtin", lambda: False)()
