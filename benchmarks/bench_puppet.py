"""Benchmark: one step of the puppet alone (12 bodies, 23 velocity DOF), float64, CPU.

Each configuration is captured once as a Warp CPU graph (``wp.ScopedCapture`` +
``wp.capture_launch``), so Python overhead is one call per step. Reported: the median
over repeats of the time per step.

Usage::

    .venv/bin/python benchmarks/bench_puppet.py [--steps 2000] [--repeats 7] [--opt 2]

The generated articulation kernels compile once per topology and optimisation level
(about a minute at -O2 on one core; cached on disk afterwards).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import warp as wp

from dmarionette.articulation.solver import (
    BallDescription,
    ContactSettings,
    SolverArticulation,
    build_articulation_model,
)
from dmarionette.scene.puppet import load_puppet

POINTS = ("head", "back", "hand_left", "hand_right", "knee_left", "knee_right")


def _configurations():
    springs = tuple((p, 500.0, 1.0) for p in POINTS)
    yield "no contact", dict(springs=())
    yield "6 string springs", dict(springs=springs)
    yield "6 springs + ground", dict(springs=springs, contacts=ContactSettings(ground=True))
    yield "6 springs + ground (smooth)", dict(springs=springs, contacts=ContactSettings(ground=True, smooth=True))
    yield "6 springs + ground + chair + ball", dict(
        springs=springs, ball=BallDescription(position=(0.3, 0.05, 0.2)),
        contacts=ContactSettings(ground=True, chair=((0.0, 0.1, -0.4), (0.2, 0.1, 0.2)), ball=True))


def bench(kwargs, steps, repeats, opt, dt=1.0 / 30.0):
    model = build_articulation_model(load_puppet(), **kwargs)
    solver = SolverArticulation(model, optimization_level=opt)
    a, b = model.state(), model.state()
    control = model.control()
    q = model.q_rest.copy()
    q[1] += 0.01
    a.joint_q.assign(q[None])
    solver.step(a, b, control, dt)  # compile / load
    solver.step(b, a, control, dt)
    with wp.ScopedCapture(device="cpu") as capture:
        solver.step(a, b, control, dt)
        solver.step(b, a, control, dt)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(steps // 2):
            wp.capture_launch(capture.graph)
        times.append((time.perf_counter() - t) / (2 * (steps // 2)))
    assert np.all(np.isfinite(a.joint_q.numpy()))
    # plain Python launches, for comparison
    t = time.perf_counter()
    for _ in range(200):
        solver.step(a, b, control, dt)
    python = (time.perf_counter() - t) / 200
    return statistics.median(times), python, model.qd_count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--opt", type=int, default=2, help="C++ optimisation level of the generated kernels")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING  # no banner
    wp.init()
    print(f"warp {wp.config.version}, CPU, {os.cpu_count()} cores visible (Warp CPU kernels run on one), "
          f"float64, -O{args.opt}, median of {args.repeats} x {args.steps} steps")
    print(f"| configuration | DOF | us/step (graph) | steps/s | us/step (Python launches) |")
    print("| --- | --- | --- | --- | --- |")
    for name, kwargs in _configurations():
        t, python, dof = bench(kwargs, args.steps, args.repeats, args.opt)
        print(f"| {name} | {dof} | {t * 1e6:.1f} | {1.0 / t:,.0f} | {python * 1e6:.0f} |", flush=True)


if __name__ == "__main__":
    main()
