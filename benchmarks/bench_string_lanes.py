"""The plain string step with and without SIMD lanes, by string count and length (issue 19).

Run:  python benchmarks/bench_string_lanes.py [--repeats 9] [--sizes 6x50 8x50 64x50 6x10 5x50]

``SolverStringImplicit.step`` (plain, float64, CPU) with ``lanes = False`` (the scalar one-launch
kernel, ``kernels/string_step``) and ``lanes = True`` (``kernels/string_step_lanes``: four strings
of equal particle count per thread), on :func:`make_model`'s strings (every effect on,
some particles on the ground, most strings tied). Each is captured as a CPU graph of many steps and
replayed (``bench_support.graph_cost``: the least thread CPU time of ``--repeats`` replays), twice,
interleaved (off, on, off, on), the lesser kept; ns per particle-step.
"""

import argparse

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

from dmarionette.strings.model import StringEffects, StringModel, StringSpec  # noqa: E402
from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402

from bench_support import graph_cost  # noqa: E402  (this folder is on sys.path when run as a script)

EFFECTS = StringEffects()  # every effect on, printed springs
GROUND_HEIGHT = 0.45


def make_model(strings: int, particles: int, seed: int = 19) -> StringModel:
    """``strings`` strings of ``particles`` particles, every effect on: tops at y = 1, bottoms at
    y = 0.2-0.45 (below the ground at 0.45 for most: particles in contact), varied constants, three
    in four tied (to points near their bottoms)."""
    rng = np.random.default_rng(seed)
    specs = []
    for s in range(strings):
        top = (0.1 * s, 1.0, 0.05 * (s % 3))
        bottom = (0.1 * s + rng.uniform(-0.3, 0.3), rng.uniform(0.2, 0.45), rng.uniform(-0.2, 0.2))
        span = float(np.linalg.norm(np.subtract(top, bottom)))
        tied = s % 4 != 3
        specs.append(StringSpec(
            name=f"s{s}", top=top, bottom=bottom, length=span * rng.uniform(0.97, 1.05), particle_count=particles,
            mass=rng.uniform(0.001, 0.004), load_mass=0.0, stiffness=rng.uniform(300.0, 900.0),
            internal_friction=rng.uniform(0.2, 0.8), air_drag=rng.uniform(0.005, 0.02),
            ground_stiffness=rng.uniform(1000.0, 3000.0), ground_absorption=rng.uniform(2.0, 8.0),
            ground_friction=rng.uniform(1.0, 3.0), tied=tied,
            tie_point=tuple(np.add(bottom, rng.uniform(-0.02, 0.02, 3))) if tied else None,
            tie_stiffness=rng.uniform(200.0, 400.0), tie_damping=rng.uniform(2.0, 4.0)))
    return StringModel(specs, effects=EFFECTS, gravity=(0.0, -9.81, 0.0), ground_height=GROUND_HEIGHT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--sizes", nargs="+", default=["6x50", "8x50", "64x50", "6x10", "5x50"],
                        help="strings x particles per string")
    args = parser.parse_args()
    print(f"# Plain string step, float64, thread CPU time, ns per particle-step (min of {args.repeats}, x2)\n")
    print("| strings x particles | scalar kernel | lanes | ratio |")
    print("|---|---:|---:|---:|")
    for size in args.sizes:
        strings, particles = (int(v) for v in size.split("x"))
        model = make_model(strings, particles)
        solver = SolverStringImplicit(model)
        a, b, control = model.state(), model.state(), model.control()
        count = max(50, 300_000 // (strings * particles))

        def step(lanes: bool) -> None:
            solver.lanes = lanes
            solver.step(a, b, control, 1e-3)

        ns = {False: [], True: []}
        for lanes in (False, True, False, True):
            seconds = graph_cost(lambda lanes=lanes: step(lanes), count, args.repeats, least=True)
            ns[lanes].append(seconds * 1e9 / model.particle_count)
        scalar, laned = min(ns[False]), min(ns[True])
        print(f"| {strings} x {particles} | {scalar:.1f} | {laned:.1f} | {scalar / laned:.2f} |")


if __name__ == "__main__":
    main()
