"""The import rules of the house (DESIGN.md "Rules of the house", docs/architecture.md), checked
on the source text with the standard library's ``ast``: nothing here imports the modules.

(a) no import cycles among the project's modules (``dmarionette`` and ``fitting``), counting
    imports inside functions (lazy imports) as edges too;
(b) no module imports a ``_private`` name from another module, nor reads one off a module it
    imported (``module._name``), nor off an object of another module's class
    (``solver._spare``; found as: ``obj._name`` with ``obj`` not ``self``/``cls``, where no
    line of this module defines ``_name`` and some other project module does);
(c) no ``wp._src`` (Warp's internals) anywhere in ``dmarionette/`` and ``fitting/``;
(d) ``dmarionette`` imports nothing from ``fitting`` (fitting plugs its commands in through the
    ``dmarionette.commands`` entry points);
(e) the descriptions (``dmarionette/scene/``) import no simulator (``strings``, ``articulation``,
    ``marionette``, ``grad``, ``live``, ``kernels``) and not ``warp``;
(f) ``dmarionette/kernels/`` never imports ``hw/``; ``hw/`` imports nothing from the rest of
    ``dmarionette`` but ``dmarionette.rotations`` (a numpy-only leaf);
(g) in ``tests/``: no module imports a test module (``test_*.py``; shared helpers live in
    ``tests/support/``), nor a ``_private`` name of a project or test module.

An import ``a.b.c`` is an edge to the module ``a.b.c`` only, not to the packages ``a`` and
``a.b`` it loads on the way (else every module would sit in a cycle through
``dmarionette/__init__.py``); ``from a.b import c`` is an edge to the module ``a.b.c`` when that
is a file, else to ``a.b``. Every rule has a test below that feeds it a small synthetic tree
with the violation and sees it caught.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dmarionette", "fitting")
TESTS = "tests"
SIMULATORS = ("strings", "articulation", "marionette", "grad", "live", "kernels")
HW_MAY_IMPORT = ("dmarionette.rotations",)


@dataclasses.dataclass(frozen=True)
class Import:
    """One imported module (or name of a module) at one place of one file."""

    module: str  # the importing module, e.g. dmarionette.scene.scene
    target: str  # the module the import loads, resolved to an absolute dotted name
    names: tuple[str, ...]  # the name a 'from' import takes (empty for 'import x')
    path: Path
    line: int


@dataclasses.dataclass(frozen=True)
class Violation:
    rule: str
    where: str  # file:line, relative to the tree's root
    what: str

    def __str__(self) -> str:
        return f"({self.rule}) {self.where}: {self.what}"


def module_files(root: Path) -> dict[str, Path]:
    """The project's modules and the tests under root: dotted name -> file."""
    files = {}
    for package in (*PACKAGES, TESTS):
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            files[".".join(parts)] = path
    return files


def _resolve(module: str, is_package: bool, level: int, name: str | None) -> str:
    """The absolute name of a (possibly relative) import's module."""
    if level == 0:
        return name or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join([*base, name] if name else base)


def _absolute(target: str, files: dict[str, Path]) -> str:
    """A test helper imported by its bare name (tests/ on sys.path) as tests.NAME."""
    top = f"{TESTS}.{target}"
    return top if target not in files and any(_within(m, top) for m in files) else target


def read_imports(root: Path, files: dict[str, Path]) -> tuple[list[Import], dict[Path, ast.Module]]:
    """Every import statement of every module, wherever it stands (lazy ones included)."""
    imports, trees = [], {}
    for module, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        trees[path] = tree
        is_package = path.name == "__init__.py"
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    imports.append(Import(module, _absolute(alias.name, files), (), path, node.lineno))
            elif isinstance(node, ast.ImportFrom):
                base = _absolute(_resolve(module, is_package, node.level, node.module), files)
                for alias in node.names:  # 'from pkg import mod' loads the module pkg.mod
                    target = f"{base}.{alias.name}" if f"{base}.{alias.name}" in files else base
                    imports.append(Import(module, target, (alias.name,), path, node.lineno))
    return imports, trees


def _within(target: str, prefix: str) -> bool:
    return target == prefix or target.startswith(prefix + ".")


def _where(root: Path, path: Path, line: int) -> str:
    return f"{path.relative_to(root)}:{line}"


def _edges(imports: list[Import], files: dict[str, Path]) -> dict[str, dict[str, Import]]:
    """module -> {imported project module -> the first import that makes the edge}."""
    edges: dict[str, dict[str, Import]] = {m: {} for m in files if not _within(m, TESTS)}
    for imp in imports:
        if imp.module in edges and imp.target in edges and imp.target != imp.module:
            edges[imp.module].setdefault(imp.target, imp)
    return edges


def _cycles(edges: dict[str, dict[str, Import]]) -> list[list[str]]:
    """One cycle through each strongly connected component of more than one module (Tarjan)."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            connect(v)
    cycles = []
    for component in components:  # the shortest way back to the component's first module
        members, start = set(component), component[0]
        paths, frontier = {start: [start]}, [start]
        cycle = None
        while frontier and cycle is None:
            following = []
            for v in frontier:
                for w in sorted(edges[v]):
                    if w == start:
                        cycle = paths[v]
                        break
                    if w in members and w not in paths:
                        paths[w] = [*paths[v], w]
                        following.append(w)
                if cycle is not None:
                    break
            frontier = following
        cycles.append(cycle)
    return cycles


def _module_aliases(tree: ast.Module, module: str, is_package: bool, files: dict[str, Path]) -> dict[str, str]:
    """Names a file binds to modules by import: local name -> absolute module name."""
    aliases = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.asname:
                    aliases[alias.asname] = _absolute(alias.name, files)
                else:
                    aliases[alias.name.split(".")[0]] = _absolute(alias.name.split(".")[0], files)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(_resolve(module, is_package, node.level, node.module), files)
            for alias in node.names:
                aliases[alias.asname or alias.name] = f"{base}.{alias.name}"
    return aliases


def _dotted(node: ast.AST) -> list[str] | None:
    """a.b.c as ['a', 'b', 'c'], or None when it is not a plain chain of names."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return [node.id, *reversed(parts)]


def _private_names_defined(tree: ast.Module) -> set[str]:
    """The ``_names`` a file defines: functions, classes, names and attributes it assigns, arguments."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
        elif isinstance(node, ast.alias):
            names.add(node.asname or node.name.split(".")[0])
        elif isinstance(node, ast.keyword) and node.arg:
            names.add(node.arg)  # dataclasses.replace(x, _field=...) and the like
    return {n for n in names if n.startswith("_") and not n.startswith("__")}


def _attribute_reach_ins(root: Path, files: dict[str, Path], trees: dict[Path, ast.Module]) -> list[Violation]:
    """``obj._name`` where ``_name`` belongs to another project module (rule b, or g in tests)."""
    defined = {path: _private_names_defined(trees[path]) for path in files.values()}
    project = {path for module, path in files.items() if not _within(module, TESTS)}
    found = []
    for module, path in files.items():
        rule = "g" if _within(module, TESTS) else "b"
        for node in ast.walk(trees[path]):
            if (not isinstance(node, ast.Attribute) or not node.attr.startswith("_") or node.attr.startswith("__")
                    or (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
                    or node.attr in defined[path]):
                continue
            owners = sorted(str(p.relative_to(root)) for p in project if node.attr in defined[p])
            if owners:
                found.append(Violation(rule, _where(root, path, node.lineno),
                                       f"reads {ast.unparse(node)}: a private name of {', '.join(owners)}"))
    return found


def check(root: Path) -> list[Violation]:
    """Every violation of rules (a)-(g) in the tree under root."""
    files = module_files(root)
    imports, trees = read_imports(root, files)
    found = []
    edges = _edges(imports, files)
    for cycle in _cycles(edges):
        steps = [edges[a][b] for a, b in zip(cycle, [*cycle[1:], cycle[0]])]
        found.append(Violation(
            "a", _where(root, steps[0].path, steps[0].line),
            "import cycle " + " -> ".join([*cycle, cycle[0]]) + " ("
            + ", ".join(f"{_where(root, s.path, s.line)} imports {s.target}" for s in steps) + ")"))
    private: dict[tuple[str, str], list[str]] = {}  # (file:line, module) -> the private names imported
    for imp in imports:
        for name in imp.names:
            if name.startswith("_") and not name.startswith("__"):
                private.setdefault((_where(root, imp.path, imp.line), imp.target), []).append(name)
    for imp in imports:
        where = _where(root, imp.path, imp.line)
        names = private.pop((where, imp.target), None)
        if _within(imp.module, TESTS):
            ours = any(_within(imp.target, p) for p in (*PACKAGES, TESTS))
            if names and ours:
                found.append(Violation("g", where, f"a test imports private {', '.join(names)} from {imp.target}"))
            if imp.target.rpartition(".")[2].startswith("test_") and imp.target != imp.module:
                found.append(Violation("g", where, f"imports the test module {imp.target} (shared helpers belong "
                                                   f"in {TESTS}/support/)"))
            continue
        if names:
            found.append(Violation("b", where, f"imports private {', '.join(names)} from {imp.target}"))
        if _within(imp.target, "warp._src") or (imp.target == "warp" and "_src" in imp.names):  # (c)
            found.append(Violation("c", where, f"imports Warp's internals ({imp.target})"))
        if imp.module.startswith("dmarionette") and _within(imp.target, "fitting"):
            found.append(Violation("d", where, f"dmarionette imports {imp.target}"))
        if _within(imp.module, "dmarionette.scene"):
            bad = [_within(imp.target, f"dmarionette.{s}") for s in SIMULATORS]
            if any(bad) or _within(imp.target, "warp") or imp.target == "dmarionette":
                found.append(Violation("e", where, f"a description imports {imp.target}"))
        if _within(imp.module, "dmarionette.kernels") and _within(imp.target, "dmarionette.hw"):
            found.append(Violation("f", where, f"a kernel module imports {imp.target}"))
        if (_within(imp.module, "dmarionette.hw") and _within(imp.target, "dmarionette")
                and not _within(imp.target, "dmarionette.hw") and imp.target not in HW_MAY_IMPORT):
            found.append(Violation("f", where, f"hw imports {imp.target} (only dmarionette.hw.* and "
                                               f"{', '.join(HW_MAY_IMPORT)} are allowed)"))
    for module, path in files.items():  # module._name, setattr(module, "_name", ...) and wp._src
        aliases = _module_aliases(trees[path], module, path.name == "__init__.py", files)
        rule = "g" if _within(module, TESTS) else "b"
        for node in ast.walk(trees[path]):
            if isinstance(node, ast.Attribute):
                chain, name = _dotted(node), node.attr
            elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Name, ast.Attribute))
                  and getattr(node.func, "id", getattr(node.func, "attr", None)) in ("setattr", "getattr")
                  and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                  and isinstance(node.args[1].value, str)):
                chain, name = _dotted(node.args[0]), node.args[1].value
                chain = None if chain is None else [*chain, name]
            else:
                continue
            if chain is None or chain[0] not in aliases:
                continue
            full = [*aliases[chain[0]].split("."), *chain[1:]]
            where = _where(root, path, node.lineno)
            if full[:2] == ["warp", "_src"] and len(chain) == 2 and rule == "b":
                found.append(Violation("c", where, f"reads Warp's internals ({'.'.join(chain)})"))
            elif (name.startswith("_") and not name.startswith("__") and full[0] in (*PACKAGES, TESTS)
                  and ".".join(full[:-1]) in files and ".".join(full[:-1]) != module):
                found.append(Violation(rule, where, f"reaches into private {name} of module {'.'.join(full[:-1])}"))
    found += _attribute_reach_ins(root, files, trees)
    return sorted(set(found), key=lambda v: (v.rule, v.where.rpartition(":")[0], int(v.where.rpartition(":")[2]),
                                             v.what))


def test_the_project_follows_the_import_rules():
    violations = check(ROOT)
    assert not violations, f"{len(violations)} import-rule violations:\n" + "\n".join(map(str, violations))


# ------------------------------------------------------------------ each rule catches its violation

def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    """A synthetic project: {relative path: source}; packages get an empty __init__.py."""
    for name in ("dmarionette/__init__.py", "fitting/__init__.py", *files):
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        for folder in path.relative_to(tmp_path).parents:
            if str(folder) != ".":
                (tmp_path / folder / "__init__.py").touch()
        path.write_text(files.get(name, ""))
    return tmp_path


def _caught(tmp_path: Path, files: dict[str, str]) -> list[tuple[str, str]]:
    return [(v.rule, v.where) for v in check(_tree(tmp_path, files))]


@pytest.mark.parametrize("files, caught", [
    pytest.param({
        "dmarionette/rotations.py": "import numpy as np\n",
        "dmarionette/hw/device.py": "from dmarionette.rotations import x\nfrom . import mapping\n",
        "dmarionette/hw/mapping.py": "import numpy\n",
        "dmarionette/scene/scene.py": "from .puppet import Puppet\nimport tomllib\n",
        "dmarionette/scene/puppet.py": "import numpy\n",
        "dmarionette/strings/solver.py": "import warp as wp\nfrom ..scene.scene import Scene\n"
                                         "def f():\n    return wp.Tape()\n",
        "fitting/cli.py": "from dmarionette.scene import scene\ndef g():\n    return scene.load_scene\n",
    }, [], id="a_clean_tree_passes"),
    pytest.param({
        "dmarionette/live/process.py": "from dmarionette.live.run import _record_tick, public\n",
        "dmarionette/live/run.py": "",
    }, [("b", "dmarionette/live/process.py:1")], id="rule_b_catches_a_private_name_imported"),
    pytest.param({
        "dmarionette/scene/scene.py": "",
        "fitting/author.py": "from dmarionette.scene import scene\n\ndef f():\n    return scene._puppet_table\n",
    }, [("b", "fitting/author.py:4")], id="rule_b_catches_a_private_name_read_off_a_module"),
    pytest.param({
        "dmarionette/grad/tape.py": "import warp as wp\n\ndef f():\n    return wp._src.context.runtime\n",
        "fitting/x.py": "from warp._src.context import runtime\n",
    }, [("c", "dmarionette/grad/tape.py:4"), ("c", "fitting/x.py:1")], id="rule_c_catches_warp_internals"),
    pytest.param({
        "dmarionette/cli.py": "def run():\n    from fitting.author import author\n",
        "fitting/author.py": "",
    }, [("d", "dmarionette/cli.py:2")], id="rule_d_catches_dmarionette_importing_fitting_lazily"),
    pytest.param({
        "tests/test_hard_cases.py": "def check():\n    pass\n",
        "tests/marionette/test_float32.py": "from test_hard_cases import check\n",
        "tests/grad/test_tape.py": "import numpy\nfrom ..test_hard_cases import check\n",
        "tests/support/strings.py": "",
        "tests/strings/test_physics.py": "from tests.support.strings import make_model\n",
    }, [("g", "tests/grad/test_tape.py:2"), ("g", "tests/marionette/test_float32.py:1")],
        id="rule_g_catches_a_test_importing_another_test_module"),
    pytest.param({
        "dmarionette/grad/tape.py": "",
        "tests/support/export.py": "",
        "tests/io/test_export.py": "from tests.support.export import _synthetic\n",
        "tests/grad/test_tape.py": "from dmarionette.grad import tape\n\ndef test(monkeypatch):\n"
                                   "    monkeypatch.setattr(tape, '_copy_unrecorded', None)\n",
        "tests/live/test_view.py": "from viser import _messages\n",  # a third party's: not this rule's
    }, [("g", "tests/grad/test_tape.py:4"), ("g", "tests/io/test_export.py:1")],
        id="rule_g_catches_a_test_reaching_into_private_names"),
    pytest.param({
        "dmarionette/marionette/solver.py": "class SolverMarionette:\n    def __init__(self):\n"
                                            "        self._spare = [1]\n\n    def step(self, other):\n"
                                            "        return other._spare  # the same class: fine\n",
        "dmarionette/grad/tape.py": "def record(solver, q):\n    q._private_of_numpy_or_warp\n"
                                    "    return solver._spare[0]\n",
    }, [("b", "dmarionette/grad/tape.py:3")], id="rule_b_catches_a_private_attribute_of_another_modules_object"),
])
def test_each_rule_catches_its_violation(tmp_path, files, caught):
    """A synthetic tree ({relative path: source}) and the violations it holds, (rule, where) each."""
    assert _caught(tmp_path, files) == caught


def test_rule_a_catches_a_cycle_through_a_lazy_import(tmp_path):
    caught = _caught(tmp_path, {
        "dmarionette/live/run.py": "from . import process\n",
        "dmarionette/live/process.py": "def f():\n    from .run import g\n",
    })
    assert caught == [("a", "dmarionette/live/process.py:2")]
    (violation,) = check(tmp_path)
    assert "dmarionette.live.process -> dmarionette.live.run -> dmarionette.live.process" in violation.what
    assert "dmarionette/live/run.py:1 imports dmarionette.live.process" in violation.what


def test_rule_a_catches_a_longer_cycle_across_packages(tmp_path):
    caught = _caught(tmp_path, {
        "dmarionette/a.py": "import dmarionette.b\n",
        "dmarionette/b.py": "from fitting import c\n",
        "fitting/c.py": "from dmarionette.a import x\n",
    })
    assert [rule for rule, _ in caught] == ["a", "d"]


@pytest.mark.parametrize("statement", ["import warp as wp", "from ..strings.model import StringModel",
                                       "from dmarionette.kernels import body_contact", "import dmarionette"])
def test_rule_e_catches_a_description_importing_a_simulator(tmp_path, statement):
    assert _caught(tmp_path, {
        "dmarionette/scene/puppet.py": f"import numpy\n{statement}\n",
        "dmarionette/strings/model.py": "",
        "dmarionette/kernels/body_contact.py": "",
    }) == [("e", "dmarionette/scene/puppet.py:2")]


@pytest.mark.parametrize("source, statement", [
    ("dmarionette/kernels/bar_feedback.py", "from ..hw.device import HapticDevice"),
    ("dmarionette/hw/servo.py", "from ..kernels.bar_feedback import eval_feedback"),
    ("dmarionette/hw/servo.py", "from dmarionette.scene.bars import euler_to_matrix"),
])
def test_rule_f_catches_kernels_and_hw_reaching_out(tmp_path, source, statement):
    others = {name: "" for name in ("dmarionette/hw/device.py", "dmarionette/kernels/bar_feedback.py",
                                    "dmarionette/scene/bars.py")}
    assert _caught(tmp_path, {**others, source: f"import numpy\n{statement}\n"}) == [("f", f"{source}:2")]
