"""Benchmark: one marionette step and its P tangents (``grad/marionette_tangent.MarionetteTangent``)
against the plain step (``SolverMarionette.step``), on a built-in scene.

Both run from Python (no graph capture): ``--steps`` puppet steps after one warm-up step,
the thread CPU time per puppet step reported (median of ``--repeats``), and the ratio
against the plain step with issue 13's target ``1 + 0.5 P``.

Usage::

    .venv/bin/python benchmarks/bench_marionette_tangent.py [--scene hanging] [--opt 2] [--steps 3] \\
        [--repeats 3] [--directions 1 4 8]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import dmarionette as dm
from dmarionette.grad.marionette_tangent import MarionetteTangent
from dmarionette.marionette.solver import MarionetteControl, MarionetteModel, MarionetteState, SolverMarionette


def _per_step(run, steps: int, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.thread_time()
        for _ in range(steps):
            run()
        times.append((time.thread_time() - t) / steps)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="hanging")
    ap.add_argument("--opt", type=int, default=2, help="optimisation level of the generated puppet kernels")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--directions", type=int, nargs="+", default=[1, 4, 8])
    args = ap.parse_args()
    model = MarionetteModel(dm.load_scene(args.scene), optimization_level=args.opt)
    solver = SolverMarionette(model)
    a, b = MarionetteState(model), MarionetteState(model)
    control = MarionetteControl(model)
    control.set_bars(model, 0.0)
    solver.step(a, b, control)  # compile, warm
    base = _per_step(lambda: solver.step(a, b, control), args.steps, args.repeats)
    print(f"{args.scene}: plain step {1e3 * base:.1f} ms CPU ({model.substeps} string steps per puppet step)")
    for P in args.directions:
        jvp = MarionetteTangent(solver, P, args.opt)
        ta, tb, tc = jvp.tangent_state(), jvp.tangent_state(), jvp.control_tangent()
        jvp.step(a, ta, b, tb, control, tc)  # compile, warm
        cost = _per_step(lambda: jvp.step(a, ta, b, tb, control, tc), args.steps, args.repeats)
        print(f"P = {P:2d}: tangent step {1e3 * cost:.1f} ms = {cost / base:.1f} plain steps "
              f"(target 1 + 0.5 P = {1 + 0.5 * P:.1f})")


if __name__ == "__main__":
    main()
