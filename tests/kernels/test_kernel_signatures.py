"""Kernel signatures laid out one way (STYLE.md item 4), checked by ``tools/lint_kernels.py``.

The project's kernels (hand-written and generated) must lint clean, and the linter must
catch each kind of violation it claims to (small bad examples below), so that a clean
result means something.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINTER = ROOT / "tools" / "lint_kernels.py"


def _load_linter():
    spec = importlib.util.spec_from_file_location("lint_kernels", LINTER)
    module = importlib.util.module_from_spec(spec)
    sys.modules["lint_kernels"] = module
    spec.loader.exec_module(module)
    return module


lint = _load_linter()


def _problems(source: str) -> list[str]:
    return [p.message for p in lint.lint_source(textwrap.dedent(source), "example.py")]


def test_project_kernels_are_clean():
    """The whole package, as CI runs it: no output, exit status 0."""
    result = subprocess.run([sys.executable, str(LINTER), str(ROOT / "dmarionette")], capture_output=True,
                            text=True, check=False)
    assert result.returncode == 0 and result.stdout == "", result.stdout + result.stderr


def test_generated_articulation_kernels_are_clean(tmp_path, monkeypatch):
    """The kernels ``articulation_codegen`` writes out, for a tree with every joint type."""
    monkeypatch.setenv("DMARIONETTE_CACHE", str(tmp_path))
    from dmarionette.kernels.articulation_codegen import (ArticulationTopology, JointTopology,
                                                          build_articulation_kernels)
    from dmarionette.kernels.articulation_tangent import build_articulation_tangent_kernels

    joints = (JointTopology("free", -1, 0, 0), JointTopology("ball", 0, 7, 6, lower=(0.0,), upper=(1.0,)),
              JointTopology("universal", 0, 11, 9, axes=((1, 0, 0), (0, 0, 1)), lower=(-1, -1), upper=(1, 1)),
              JointTopology("hinge", 2, 13, 11, axes=((1, 0, 0),), lower=(-1,), upper=(1,)))
    for limits, one_sided in ((True, False), (True, True), (False, False)):
        topology = ArticulationTopology(joints, joint_limits=limits, one_sided_limits=one_sided)
        module = build_articulation_kernels(topology)
        problems = lint.lint_paths([Path(module.__file__)])
        assert not problems, "\n".join(map(str, problems))
        assert sum(1 for line in Path(module.__file__).read_text().splitlines() if line == "@wp.kernel") == 4
        tangent = build_articulation_tangent_kernels(topology)
        problems = lint.lint_paths([Path(tangent.__file__)])
        assert not problems, "\n".join(map(str, problems))


GOOD = """
    import warp as wp

    @wp.kernel
    def eval_good(
        # Model:
        stiffness: wp.array(dtype=float),
        # State in:
        q: wp.array(dtype=float),
        # Control:
        dt: float,
        # State in and out (accumulated):
        total: wp.array(dtype=float),
        # State out:
        q_out: wp.array(dtype=float),
    ):
        i = wp.tid()
        q_out[i] = q[i] + dt * stiffness[0]
        wp.atomic_add(total, 0, q[i])
"""


def test_a_good_kernel_passes():
    assert _problems(GOOD) == []


@pytest.mark.parametrize(
    "body, expected",
    [
        ("q[i] = 0.0", "writes its input 'q' (State in)"),
        ("q[i] += 1.0", "writes its input 'q' (State in)"),
        ("wp.atomic_add(stiffness, i, 1.0)", "writes its input 'stiffness' (Model)"),
        ("compute_fill(q, i)", "writes its input 'q' (State in)"),
        ("compute_outer(q, i)", "writes its input 'q' (State in)"),  # through two funcs
    ],
)
def test_a_write_to_an_input_is_caught(body, expected):
    source = f"""
    import warp as wp

    @wp.func
    def compute_fill(a: wp.array(dtype=float), i: int):
        a[i] = 1.0

    @wp.func
    def compute_outer(b: wp.array(dtype=float), i: int):
        compute_fill(b, i)

    @wp.kernel
    def eval_bad(
        # Model:
        stiffness: wp.array(dtype=float),
        # State in:
        q: wp.array(dtype=float),
        # State out:
        q_out: wp.array(dtype=float),
    ):
        i = wp.tid()
        q_out[i] = q[i]
        {body}
    """
    assert expected in _problems(source)


@pytest.mark.parametrize("body, expected", [
    ("q_out_dot[p, i] = q_dot[p, i]", []),
    ("q_dot[p, i] = 0.0", ["writes its input 'q_dot' (Tangent in)"]),
])
def test_tangent_groups(body, expected):
    """A tangent-linear kernel's tangents stand in their own groups, an input and an output one."""
    source = f"""
    import warp as wp

    @wp.kernel
    def eval_tangent(
        # State in:
        q: wp.array(dtype=float),
        # Tangent in (leading axis: the direction):
        q_dot: wp.array2d(dtype=float),
        # State out:
        q_out: wp.array(dtype=float),
        # Tangent out:
        q_out_dot: wp.array2d(dtype=float),
    ):
        p, i = wp.tid()
        q_out[i] = q[i]
        {body}
    """
    assert [problem for problem in _problems(source) if "Tangent" in problem] == expected


def test_a_kernel_inside_a_factory_is_checked():
    source = """
    import warp as wp

    def eval_bad_kernel(scalar):
        @wp.kernel(module="unique")
        def eval_bad(
            # State in:
            q: wp.array(dtype=scalar),
            # State out:
            q_out: wp.array(dtype=scalar),
        ):
            q[0] = q_out[0]
        return eval_bad
    """
    assert _problems(source) == ["writes its input 'q' (State in)"]


def test_a_default_is_caught():
    source = GOOD.replace("q_out: wp.array(dtype=float),", "q_out: wp.array(dtype=float) = None,")
    assert "parameter 'q_out' has a default" in _problems(source)


def test_outputs_before_inputs_are_caught():
    source = GOOD.replace("""        # State out:
        q_out: wp.array(dtype=float),
""", "").replace("""        # Model:
""", """        # State out:
        q_out: wp.array(dtype=float),
        # Model:
""")
    problems = _problems(source)
    assert "group 'Model' after 'State out' (order: " + ", ".join(lint.GROUPS) + ")" in problems
    assert "input 'stiffness' (Model) after output 'q_out'" in problems


def test_a_missing_group_comment_is_caught():
    source = GOOD.replace("""        # Model:
""", "")
    assert "parameter 'stiffness' stands under no group comment" in _problems(source)


def test_an_unknown_or_repeated_group_is_caught():
    assert any(p.startswith("unknown group comment '# Inputs:'")
               for p in _problems(GOOD.replace("# Control:", "# Inputs:")))
    assert "group 'State in' appears twice" in _problems(GOOD.replace("# Control:", "# State in:"))


def test_packed_constants_are_caught():
    source = GOOD.replace("q_out[i] = q[i] + dt * stiffness[0]", "q_out[i] = q[i] + stiffness[1] * stiffness[0]")
    assert "'stiffness' is read at constant indices [0, 1]: packed constants, give each its own parameter" in \
        _problems(source)


def test_the_command_reports_and_fails(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text(textwrap.dedent(GOOD.replace("q_out[i] = q[i]", "q[i] = q[i]")))
    result = subprocess.run([sys.executable, str(LINTER), str(tmp_path)], capture_output=True, text=True,
                            check=False)
    assert result.returncode == 1
    line = next(n for n, text in enumerate(bad.read_text().splitlines(), 1) if "q[i] = q[i]" in text)
    assert result.stdout.strip() == f"{bad}:{line} eval_good: writes its input 'q' (State in)"


def test_generated_kernel_tangents_are_clean(tmp_path, monkeypatch):
    """The tangent kernels ``kernel_tangent`` writes out for the hand-written puppet-side kernels."""
    monkeypatch.setenv("DMARIONETTE_CACHE", str(tmp_path))
    from types import SimpleNamespace

    import warp as wp

    from dmarionette.kernels.articulation_forces import eval_body_point_springs
    from dmarionette.kernels.bar_feedback import eval_bar_feedback_kernel
    from dmarionette.kernels.kernel_tangent import UNROLL, tangent_kernel
    from dmarionette.kernels.string_body_coupling import (apply_string_forces_to_anchors_kernel,
                                                          eval_string_response_kernel, eval_tie_path)

    from dmarionette.kernels.body_contact import ContactSet, ContactSettings

    contacts = ContactSettings(ground=True, chair=((0, 0, 0), (1, 1, 1)), ball=True)
    model = SimpleNamespace(device="cpu", contacts=contacts,
                            body_shape=[("box", (0.2, 0.2, 0.2)), ("sphere", (0.1,))], body_contact=[True, True],
                            body_mass=wp.array([1.0, 0.3], dtype=wp.float64, device="cpu"),
                            body_names=["torso", "ball"], ball=SimpleNamespace(radius=0.1))
    ground, box, ball = ContactSet(model).kernels
    kernels = [eval_body_point_springs, ground, box, ball, eval_tie_path, apply_string_forces_to_anchors_kernel(3),
               eval_string_response_kernel(wp.float64, True, 3), eval_bar_feedback_kernel(wp.float64, True)]
    for kernel in kernels:
        for unroll in (0, UNROLL):  # both layouts (kernel_tangent)
            tangent = tangent_kernel(kernel, frozenset({"body_pos", "particle_q", "tie_q", "tie_target"}), unroll)
            path = Path(sys.modules[tangent.kernel.func.__module__].__file__)
            problems = lint.lint_paths([path])
            assert not problems, "\n".join(map(str, problems))
            assert "    # Tangent in:" in path.read_text() and "    # Tangent out:" in path.read_text()
