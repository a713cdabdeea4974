"""Forward-mode cost of string rollouts: P tangents against one plain forward rollout (issue 13, item 4).

Run:  python benchmarks/bench_string_tangent.py [--repeats 5] [--steps 1000] [--clock wall|cpu] [--no-lanes]
          [--layout minor|major|both] [--directions 1 4 12 16]

The strings of the built-in ``strings`` scene (six strings of 50 particles, every effect on, the
two hand strings tied as in ``tests/grad/test_string_rollout_tangent.py``), 1 kHz, tops swaying.
Timed (median of ``--repeats`` runs after an untimed warm-up, spread printed):

- the plain forward rollout (``StringRollout``, captured chunks of 100 steps), with the laned step
  (the default) and with the scalar one-launch step (``lanes = False``);
- ``StringRolloutTangent`` with P = 1, 4, 12, 16 directions (every input group: initial state,
  masses, constants, tops and tie targets per step): the forward (the laned step with ``keep``)
  and the P tangents (one launch per chunk of directions per step), in captured chunks of 100
  steps, including the upload of the per-step tangents and the download of the tie forces' tangents;
  the tangent kernel as ``StringRolloutTangent`` chooses it (4 or 8 directions per SIMD lane
  vector for P >= 2, ``string_step_tangent.direction_chunks``; for P = 1 the strings 4 per SIMD
  lane vector, ``string_step_tangent_lanes``), or with ``--no-lanes`` one direction at a time (the
  scalar tangent kernel, one thread per string) for every P; the carried
  particle tangents stored direction-minor (``--layout minor``, the default: a lane group's
  directions of one particle contiguous) or with a leading direction axis (``major``), or both
  one after the other for each P (``both``: an A/B in one process).

The issue's target: P tangents cost at most (1 + 0.5 P) x one forward rollout (P <= 16). The
ratio is printed against both forwards (the laned default is the harder reference).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dmarionette.grad.string_tangent import CONSTANTS, StringRolloutTangent, StringTangentInputs  # noqa: E402
from dmarionette.strings.rollout import StringRollout  # noqa: E402
from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402
from tests.grad.test_string_rollout_tangent import DT, scene_controls, scene_model  # noqa: E402

from bench_support import CLOCKS, add_clock_flag, median_spread  # noqa: E402

CHUNK = 100
DIRECTIONS = (1, 4, 12, 16)


def _timed(run, repeats: int, clock) -> tuple[float, float]:
    run()  # warm-up (compiles, captures)
    times = []
    for _ in range(repeats):
        start = clock()
        run()
        times.append(clock() - start)
    return median_spread(times)


def _tangents(model, p: int, steps: int, rng) -> StringTangentInputs:
    n, s = model.particle_count, model.string_count
    return StringTangentInputs(
        particle_q=1e-3 * rng.normal(size=(p, n, 3)), particle_qd=1e-2 * rng.normal(size=(p, n, 3)),
        particle_mass=1e-4 * rng.normal(size=(p, n)), constants=rng.normal(size=(p, s, len(CONSTANTS))),
        top_q=1e-3 * rng.normal(size=(p, steps, s, 3)), tie_q=1e-3 * rng.normal(size=(p, steps, s, 3)),
        tie_qd=1e-2 * rng.normal(size=(p, steps, s, 3)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=1000)
    add_clock_flag(parser)
    parser.add_argument("--no-lanes", action="store_true",
                        help="the scalar tangent kernel (one direction at a time) instead of directions in lanes")
    parser.add_argument("--layout", choices=("minor", "major", "both"), default="minor",
                        help="the carried particle tangents' layout (StringRolloutTangent(minor=)); both: A/B per P")
    parser.add_argument("--directions", type=int, nargs="+", default=list(DIRECTIONS), help="the P to time")
    args = parser.parse_args()
    clock = CLOCKS[args.clock]
    steps = CHUNK * max(1, args.steps // CHUNK)
    model = scene_model()
    tops, tie, tie_v = scene_controls(model, steps)
    print(f"# String tangent benchmark — {platform.processor() or platform.machine()}, Python "
          f"{platform.python_version()}, Warp {wp.config.version}; {model.string_count} strings, "
          f"{model.particle_count} particles, {steps} steps at {1 / DT:g} Hz; median of {args.repeats} runs"
          f"{'' if args.clock == 'wall' else ', thread CPU time'}; tangent directions "
          f"{'one at a time (--no-lanes)' if args.no_lanes else 'in SIMD lanes (P >= 2)'}; "
          f"load average {os.getloadavg()[0]:.2f}\n")

    forward = {}
    for lanes in (True, False):
        solver = SolverStringImplicit(model)
        solver.lanes = lanes
        rollout = StringRollout(solver, DT, chunk_steps=CHUNK)
        forward[lanes] = _timed(lambda r=rollout: r.run(model.state(), tops, tie, tie_v), args.repeats, clock)
        print(f"forward rollout, {'laned step (default)' if lanes else 'scalar step'}: "
              f"{forward[lanes][0] * 1e3:.1f} ms (spread {forward[lanes][1]:.0%})")
    print()
    print("| P | layout | tangent rollout [ms] | spread | / laned forward | / scalar forward | target 1 + 0.5 P |")
    print("|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    layouts = ("minor", "major") if args.layout == "both" else (args.layout,)
    for p in args.directions:
        tangents = _tangents(model, p, steps, rng)
        for layout in layouts:
            rollout = StringRolloutTangent(SolverStringImplicit(model), DT, p, chunk_steps=CHUNK,
                                           lanes=False if args.no_lanes else None, minor=layout == "minor")
            median, spread = _timed(lambda r=rollout, v=tangents: r.run(model.state(), tops, tie, tie_v, v),
                                    args.repeats, clock)
            print(f"| {p} | {layout} | {median * 1e3:.1f} | {spread:.0%} | {median / forward[True][0]:.2f} | "
                  f"{median / forward[False][0]:.2f} | {1 + 0.5 * p:.1f} |")
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
