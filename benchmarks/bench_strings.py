"""String simulator speed on one core: steps per second, scaling, and the cost of each effect.

Run:  python benchmarks/bench_strings.py [--repeats 7] [--steps 3000] [--clock wall|cpu] [--only-6x50] [--no-lanes]

Every number is the median of ``--repeats`` timed runs of ``--steps`` steps (after one
untimed warm-up run that also compiles the kernels), replayed as a captured CPU graph
in chunks of 100 steps, on the default scene's six strings with their top attach points
swaying. The spread (min-max over repeats, relative to the median) is printed so the
machine's noise can be judged. Warp's CPU backend runs each launch on one thread.

``--clock cpu`` times the calling thread's CPU time (``time.thread_time``) instead of the wall
clock: on a machine shared with other work it leaves out the time the thread waited for a core
(not the slowdown other processes cause through the caches). ``--only-6x50`` prints the first
table only (for interleaved A/B runs of two checkouts, ``docs/performance.md``). float64 steps
with the laned kernel, the default (``SolverStringImplicit.lanes``, ``kernels/string_step_lanes``);
``--no-lanes`` with the scalar one-launch kernel instead (``kernels/string_step``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

from dmarionette.scene.scene import load_scene  # noqa: E402
from dmarionette.strings.model import StringEffects, StringModel  # noqa: E402
from dmarionette.strings.rollout import StringRollout  # noqa: E402
from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402

from bench_support import CLOCKS, add_clock_flag, median_spread  # noqa: E402

DT = 1e-3
CHUNK = 100
LANES = True  # --no-lanes: False


def _model(particle_count=50, effects=None, precision="float64") -> StringModel:
    scene = load_scene("strings")
    specs = [dataclasses.replace(s, particle_count=particle_count) for s in scene.strings]
    return StringModel(specs, effects=effects or scene.effects, gravity=scene.gravity,
                       ground_height=scene.ground_height, precision=precision)


def measure(model: StringModel, steps: int, repeats: int, clock=time.perf_counter) -> tuple[float, float]:
    """Median steps per second and relative spread (max-min)/median of the run times (``clock``:
    ``time.perf_counter`` for wall time, ``time.thread_time`` for the thread's CPU time)."""
    solver = SolverStringImplicit(model)
    if not LANES:
        solver.lanes = False  # else the default: lanes wherever they apply (float64 printed springs)
    rollout = StringRollout(solver, DT, chunk_steps=CHUNK)
    steps = CHUNK * max(1, steps // CHUNK)
    t = DT * np.arange(1, steps + 1)
    tops = np.array([s.top for s in model.specs])
    top_q = tops[None] + (0.05 * np.sin(2 * np.pi * 0.5 * t))[:, None, None] * np.array([1.0, 0.0, 0.0])
    state = model.state()
    rollout.run(state, top_q)  # warm-up
    times = []
    for _ in range(repeats):
        state = model.state()
        start = clock()
        rollout.run(state, top_q)
        times.append(clock() - start)
    median, spread = median_spread(times)
    return steps / median, spread


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--steps", type=int, default=3000)
    add_clock_flag(parser)
    parser.add_argument("--only-6x50", action="store_true", help="only the 6 x 50 table")
    parser.add_argument("--no-lanes", action="store_true",
                        help="float64 with the scalar kernel (SolverStringImplicit.lanes = False)")
    args = parser.parse_args()
    global LANES
    LANES = not args.no_lanes
    clock = CLOCKS[args.clock]
    print(f"# String benchmark — {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
          f"Warp {wp.config.version}; dt = {DT * 1e3:g} ms; median of {args.repeats} runs of {args.steps} steps"
          f"{'' if args.clock == 'wall' else ', thread CPU time'}; float64 lanes {'on' if LANES else 'off'}"
          f"; load average {os.getloadavg()[0]:.2f}\n")

    print("## 6 strings x 50 particles\n")
    print("| precision | steps/s | real-time factor | ns per particle-step | spread |")
    print("|---|---:|---:|---:|---:|")
    for precision in ("float64", "float32"):
        rate, spread = measure(_model(precision=precision), args.steps, args.repeats, clock)
        print(f"| {precision} | {rate:,.0f} | {rate * DT:.1f}x | {1e9 / rate / 300:.1f} | {spread:.0%} |")
    if args.only_6x50:
        return

    print("\n## Scaling with particles per string (6 strings, float64)\n")
    print("| particles/string | steps/s | µs/step | ns per particle-step | spread |")
    print("|---:|---:|---:|---:|---:|")
    for n in (10, 25, 50, 100, 200):
        rate, spread = measure(_model(particle_count=n), args.steps, args.repeats, clock)
        print(f"| {n} | {rate:,.0f} | {1e6 / rate:.1f} | {1e9 / rate / (6 * n):.1f} | {spread:.0%} |")

    print("\n## Cost of each effect (6 x 50, float64): all on vs. that one compiled out\n")
    print("| effect | steps/s with it | steps/s without | µs/step it costs | spread |")
    print("|---|---:|---:|---:|---:|")
    all_on, spread_on = measure(_model(effects=StringEffects()), args.steps, args.repeats, clock)
    for name in ("gravity", "internal_friction", "air_drag", "ground_contact", "ground_friction"):
        effects = dataclasses.replace(StringEffects(), **{name: False})
        rate, spread = measure(_model(effects=effects), args.steps, args.repeats, clock)
        cost = 1e6 / all_on - 1e6 / rate
        print(f"| {name} | {all_on:,.0f} | {rate:,.0f} | {cost:+.2f} | {max(spread, spread_on):.0%} |")
    none, spread = measure(_model(effects=StringEffects(False, False, False, False, False)), args.steps, args.repeats,
                          clock)
    print(f"| (all five off: springs only) | {all_on:,.0f} | {none:,.0f} | {1e6 / all_on - 1e6 / none:+.2f} | "
          f"{max(spread, spread_on):.0%} |")


if __name__ == "__main__":
    main()
