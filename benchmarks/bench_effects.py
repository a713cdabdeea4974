"""What each effect costs: the full marionette with every effect on, and with one compiled out.

Run:  python benchmarks/bench_effects.py [--seconds 4] [--repeats 5]

Scene: ``hanging`` with all effects on, a chair and a ball placed out of the puppet's reach
(so their contact tests run every step but never fire). Each figure is the median over
``--repeats`` runs of the stepping alone (captured graphs, optimised kernels; the first run
compiles each variant's puppet kernels, about a minute each, then they are cached). The
variants are timed in interleaved rounds (one run of each per round), so that a drift of
the machine's speed during the benchmark affects all of them alike.
"µs per ms" is the cost of the effect per millisecond of simulated time: the difference
of wall time per simulated second between all-on and that effect off, divided by 1000.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics

import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402
from dmarionette.marionette.rollout import simulate_marionette  # noqa: E402
from dmarionette.scene.scene import BallSpec  # noqa: E402

STRING_EFFECTS = ("air_drag", "internal_friction", "ground_contact")
BODY_EFFECTS = ("body_ground", "chair", "ball", "joint_limits", "feedback")


def scene_with(off: str | None):
    scene = dm.load_scene("hanging")
    body = dict(scene.body_effects, chair=True, ball=True)
    strings = scene.effects
    if off in BODY_EFFECTS:
        body[off] = False
    elif off is not None:
        strings = dataclasses.replace(strings, **{off: False})
    return dataclasses.replace(scene, effects=strings, body_effects=body,
                               chair=((1.0, 0.1, 0.0), (0.1, 0.1, 0.1)) if body["chair"] else None,
                               ball=BallSpec((-1.0, 0.05, 0.0), 0.05, 0.05) if body["ball"] else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    variants = (None, *STRING_EFFECTS, *BODY_EFFECTS)
    models = {}
    for off in variants:
        models[off] = MarionetteModel(scene_with(off), optimization_level=2)
        simulate_marionette(models[off], 0.2, progress=False)  # compile + capture warm-up
    walls = {off: [] for off in variants}
    for _ in range(args.repeats):
        for off in variants:
            walls[off].append(simulate_marionette(models[off], args.seconds, progress=False).wall_seconds)
    per_second = {off: statistics.median(w) / args.seconds for off, w in walls.items()}
    print(f"# Effect costs — {platform.machine()}, Warp {wp.config.version}; 'hanging' + chair + ball, "
          f"strings 1 kHz, puppet 30 Hz; median of {args.repeats} interleaved rounds x {args.seconds:g} s\n")
    base = per_second[None]
    print(f"All effects on: {1.0 / base:.1f}x real time.\n")
    print("| effect compiled out | real-time factor | effect's cost [µs per simulated ms] |")
    print("|---|---:|---:|")
    for off in variants[1:]:
        print(f"| {off} | {1.0 / per_second[off]:.1f}x | {(base - per_second[off]) * 1e3:+.2f} |")


if __name__ == "__main__":
    main()
