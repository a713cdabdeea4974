"""Cost of tension-only string springs (``StringEffects(tension_only=True)``) against the
paper's printed spring, on one core.

Run:  python benchmarks/bench_tension_only.py [--rounds 7] [--steps 3000]

Two motions of the ``strings`` scene's six strings (50 particles, float64, 1 kHz), replayed
as captured CPU graphs in chunks of 100 steps:

- ``sway``: the tops sway 5 cm at 0.5 Hz; the loaded strings stay taut, so the tension-only
  step only adds its active-set check (no segment is ever activated);
- ``lowered``: the tops come down 0.6 m at 0.3 m/s, so the strings go slack and pile up on
  their loads and on the ground, and segments snap taut again: the steps where a chain is
  solved again.

Printed and tension-only runs are interleaved round by round (so machine load affects both
alike); each number is the median over the rounds.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import time

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

from dmarionette.scene.scene import load_scene  # noqa: E402
from dmarionette.strings.model import StringModel  # noqa: E402
from dmarionette.strings.rollout import StringRollout  # noqa: E402
from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402

DT = 1e-3
CHUNK = 100


def _tops(model, motion, steps):
    t = DT * np.arange(1, steps + 1)
    tops = np.array([s.top for s in model.specs])
    if motion == "sway":
        return tops[None] + (0.05 * np.sin(2 * np.pi * 0.5 * t))[:, None, None] * np.array([1.0, 0.0, 0.0])
    return tops[None] - np.minimum(0.3 * t, 0.6)[:, None, None] * np.array([0.0, 1.0, 0.0])


def _time_once(model, motion, steps):
    rollout = StringRollout(SolverStringImplicit(model), DT, chunk_steps=CHUNK)
    top_q = _tops(model, motion, steps)
    rollout.run(model.state(), top_q)  # warm-up (compiles on the first round)
    state = model.state()
    start = time.perf_counter()
    rollout.run(state, top_q)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()
    steps = CHUNK * max(1, args.steps // CHUNK)
    scene = load_scene("strings")
    models = {}
    for tension_only in (False, True):
        effects = dataclasses.replace(scene.effects, tension_only=tension_only)
        models[tension_only] = StringModel.from_scene(dataclasses.replace(scene, effects=effects))
    print(f"# Tension-only springs — {platform.processor() or platform.machine()}, Warp {wp.config.version}; "
          f"6 x 50 particles, float64, dt = 1 ms; median of {args.rounds} interleaved rounds of {steps} steps\n")
    print("| motion | printed: steps/s | tension-only: steps/s | tension-only costs | spread |")
    print("|---|---:|---:|---:|---:|")
    for motion in ("sway", "lowered"):
        times = {False: [], True: []}
        for _ in range(args.rounds):
            for tension_only in (False, True):
                times[tension_only].append(_time_once(models[tension_only], motion, steps))
        med = {k: statistics.median(v) for k, v in times.items()}
        spread = max((max(v) - min(v)) / statistics.median(v) for v in times.values())
        cost = (med[True] - med[False]) / steps * 1e6
        print(f"| {motion} | {steps / med[False]:,.0f} | {steps / med[True]:,.0f} | {cost:+.2f} µs/step "
              f"({med[True] / med[False] - 1:+.0%}) | {spread:.0%} |")


if __name__ == "__main__":
    main()
