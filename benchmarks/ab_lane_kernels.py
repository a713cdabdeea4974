"""The laned string kernels of this tree against those of a git revision, timed in pairs.

Run:  python benchmarks/ab_lane_kernels.py --rev 2140636 [--pairs 300] [--clock wall|cpu]

For the ``hanging`` scene's strings (6 x 50, every effect of the scene), captures three CPU
graphs of 100 launches each for both versions: the laned hand-written adjoint
(``kernels/string_step_adjoint_lanes``, recorded as ``SolverStringImplicit.record_step_adjoint``
does), the laned step with ``keep`` (a taped step's) and the plain laned step
(``kernels/string_step_lanes``). The revision's ``lane_ops``, ``string_step_lanes`` and
``string_step_adjoint_lanes`` are read with ``git show`` into a temporary folder and imported from
there (the rest, the solver and its launch code included, is this tree's; the revision's adjoint
gets as many laned scratch arrays as its signature names; a revision from before the kernels took
the string model as one ``StringModelArrays`` argument, or the state and control as
``StringStateArrays`` and ``StringControlArrays``, gets those structs' fields its signature names
in their place, ``_launch_expanding``). Each sample replays the two versions'
graphs back to back (which one first alternates), so that a change of the machine's load between
samples cancels in their ratio; printed: the median of the ratios (this tree / the revision) and
its quartiles, and each version's median and least time per launch (µs). ``--clock cpu``: the
calling thread's CPU time (Warp runs a CPU graph on the calling thread).
"""

from __future__ import annotations

import argparse
import atexit
import itertools
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.kernels.string_step_adjoint_lanes import string_step_adjoint_lanes_kernel  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

from bench_support import CLOCKS, add_clock_flag, capture_graph  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODULES = {"lane_ops": "rev_lane_ops", "string_step_lanes": "rev_string_step_lanes",
           "string_step_adjoint_lanes": "rev_string_step_adjoint_lanes"}
SCRATCH = ("lane_bar", "lane_x_bar", "lane_r", "lane_parts")  # the plan's adjoint scratch, in its order
LAUNCHES = 100


def _revision_modules(rev: str):
    """The revision's three kernel modules, imported from a temporary folder."""
    folder = Path(tempfile.mkdtemp(prefix="ab_lane_kernels_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    for name, alias in MODULES.items():
        text = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:dmarionette/kernels/{name}.py"],
                              capture_output=True, text=True, check=True).stdout
        for other, other_alias in MODULES.items():
            text = text.replace(f"from .{other} import", f"from {other_alias} import")
        text = text.replace("from .", "from dmarionette.kernels.")  # this tree's other kernel modules
        (folder / f"{alias}.py").write_text(text)
    sys.path.insert(0, str(folder))
    import rev_string_step_adjoint_lanes
    import rev_string_step_lanes
    return rev_string_step_lanes, rev_string_step_adjoint_lanes


def _fields(value, labels: list[str]) -> list[str]:
    """The fields of the struct ``value`` that a kernel's next arguments ``labels`` name, in their
    order (``x``; ``x_out``: of a state out; ``x_grad``, ``x_out_grad``: of a gradients' struct), up
    to the first that names none or one already taken."""
    fields = []
    for label in labels:
        name = label if label in value._cls.vars else label.removesuffix("_grad").removesuffix("_out")
        if name not in value._cls.vars or name in fields:
            break
        fields.append(name)
    return fields


def _launch_expanding(launch):
    """``wp.launch`` that, for a kernel of a revision that takes one by one what this tree's takes
    as a struct (the string model's constants before ``kernels/string_model_arrays``, the state and
    control before ``kernels/string_state_arrays``), passes a struct argument's fields the kernel
    names in its place, in the kernel's order (``_fields``)."""

    def expanding(kernel, dim, inputs=(), outputs=(), **kwargs):
        labels = [a.label for a in kernel.adj.args]
        types = {a.label: a.type for a in kernel.adj.args}
        flat = []
        for value in [*inputs, *outputs]:
            label = labels[len(flat)] if len(flat) < len(labels) else None
            if hasattr(value, "_cls") and not (label and types[label] is value._cls):  # a struct it takes apart
                flat += [getattr(value, name) for name in _fields(value, labels[len(flat):])]
            else:
                flat.append(value)
        return launch(kernel, dim, inputs=flat, **kwargs)  # (Warp reads inputs and outputs as one list)

    return expanding


def _graphs(model, kernels) -> dict[str, object]:
    """The three graphs of one version: its ``(adjoint, keep step, plain step)`` kernels."""
    solver, strings = model.string_solver, model.strings
    adjoint, keep, plain = kernels
    plan = solver._lane_plan
    launch = wp.launch
    wp.launch = _launch_expanding(launch)
    scratch = sum(1 for a in adjoint.adj.args if a.label in SCRATCH)
    solver._integrate_lanes_adjoint, solver._integrate_lanes_keep, solver._integrate_lanes = kernels
    solver._lane_plan = (plan[0], plan[1][:2 + scratch])  # C', d', then the adjoint's scratch
    state_in, state_out, control = strings.state(), strings.state(), strings.control()
    ws = solver.new_workspace(True)
    h = strings.scalar(model.string_dt)
    tape = wp.Tape()
    solver.integrate_string_lanes(state_in, state_out, control, h, ws, keep=True)
    solver.record_step_adjoint(state_in, state_out, control, h, ws, tape, lanes=True)
    launches = {
        "adjoint": tape.launches[-1],
        "keep step": lambda: solver.integrate_string_lanes(state_in, state_out, control, h, ws, keep=True),
        "plain step": lambda: solver.integrate_string_lanes(state_in, state_out, control, h, solver.workspace),
    }
    graphs = {name: capture_graph(launch, LAUNCHES, "cpu") for name, launch in launches.items()}
    solver._lane_plan = plan
    wp.launch = launch
    return graphs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rev", required=True, help="the git revision to compare with")
    p.add_argument("--pairs", type=int, default=300)
    add_clock_flag(p)
    args = p.parse_args()
    clock = CLOCKS[args.clock]
    model = MarionetteModel(dm.load_scene("hanging"), requires_grad=True)
    solver = model.string_solver
    solver.lanes = True
    (effects,) = [e for e in itertools.product((False, True), repeat=5)
                  if string_step_adjoint_lanes_kernel(e) is solver._integrate_lanes_adjoint]
    rev_lanes, rev_adjoint = _revision_modules(args.rev)
    ours = (solver._integrate_lanes_adjoint, solver._integrate_lanes_keep, solver._integrate_lanes)
    theirs = (rev_adjoint.string_step_adjoint_lanes_kernel(effects),
              rev_lanes.integrate_string_lanes_kernel(effects, keep=True), rev_lanes.integrate_string_lanes_kernel(effects))
    new, old = _graphs(model, ours), _graphs(model, theirs)
    print(f"# hanging 6 x 50, this tree / {args.rev}, {args.pairs} pairs of replays of {LAUNCHES} launches, "
          f"{args.clock} clock")
    for name in new:
        times = {"new": [], "old": []}
        ratios = []
        for i in range(args.pairs):
            for which in (("new", "old") if i % 2 == 0 else ("old", "new")):
                graph = new[name] if which == "new" else old[name]
                t0 = clock()
                wp.capture_launch(graph)
                times[which].append((clock() - t0) / LAUNCHES * 1e6)
            ratios.append(times["new"][-1] / times["old"][-1])
        q1, _q2, q3 = statistics.quantiles(ratios, n=4)
        print(f"{name:10s} ratio {statistics.median(ratios):.3f} (quartiles {q1:.3f}-{q3:.3f}); µs per launch: "
              f"this tree median {statistics.median(times['new']):.2f}, least {min(times['new']):.2f}; "
              f"{args.rev} median {statistics.median(times['old']):.2f}, least {min(times['old']):.2f}")


if __name__ == "__main__":
    main()
