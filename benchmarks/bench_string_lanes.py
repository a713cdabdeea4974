"""The plain string step with and without SIMD lanes, by string count and length (issue 19).

Run:  python benchmarks/bench_string_lanes.py [--repeats 9] [--sizes 6x50 8x50 64x50 6x10 5x50]

``SolverStringImplicit.step`` (plain, float64, CPU) with ``lanes = False`` (the scalar one-launch
kernel, ``kernels/string_step``) and ``lanes = True`` (``kernels/string_step_lanes``: four strings
of equal particle count per thread), on ``probe_simd_step.make_model``'s strings (every effect on,
some particles on the ground, most strings tied). Each is captured as a CPU graph of many steps and
replayed (``bench_support.graph_cost``: the least thread CPU time of ``--repeats`` replays), twice,
interleaved (off, on, off, on), the lesser kept; ns per particle-step.
"""

import argparse

import warp as wp

wp.config.log_level = wp.LOG_WARNING

from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402

from bench_support import graph_cost  # noqa: E402  (this folder is on sys.path when run as a script)
from probe_simd_step import make_model  # noqa: E402


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
