"""Many marionettes at once: throughput of a batched marionette (``W`` worlds per launch; issue #16).

Run:  python benchmarks/bench_worlds.py [--worlds 1,4,16,64,256] [--seconds 1] [--repeats 3]
                                        [--device cpu|cuda] [--scene hanging] [--particles 50]

The scene is ``hanging`` as shipped (6 strings x 50 particles, 12 bodies, paper rates: strings 1 kHz,
puppet 30 Hz, ground contact, joint limits and feedback on), its ``W`` copies stepped as the worlds of
one ``MarionetteModel(scene, world_count=W)`` by the captured rollout ``simulate_worlds`` uses
(``MarionetteRollout``: one graph per ~30 Hz frame; the per-frame host reads are not timed). Each
figure is the median over ``--repeats`` runs of ``--seconds`` simulated seconds after a warm-up run
(kernels compiled and the graph captured before); "spread" is (max - min) / median over the repeats.

Columns: wall seconds per simulated second; world string steps per second (``W`` times the string
steps per wall second); the real-time factor of each world (simulated / wall); the total real-time
factor (``W`` times that); and the efficiency, the total throughput over the W = 1 throughput: 1 means
``W`` worlds cost ``W`` times one world (no per-world overhead beyond the work itself), more than 1
that batching saved per-launch overhead, less than 1 that a world costs more in a batch (the issue's
goal at W = 64 is >= 0.9).
On the CPU Warp runs a launch on one thread: the figures are one core's.
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

import dmarionette as dm  # noqa: E402
from dmarionette.marionette.rollout import MarionetteRollout  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette  # noqa: E402


def time_worlds(scene, worlds: int, seconds: float, repeats: int, device: str) -> dict:
    model = MarionetteModel(scene, world_count=worlds, optimization_level=2, device=device)
    chunk = max(1, round(1.0 / (30.0 * model.puppet_dt)))
    rollout = MarionetteRollout(SolverMarionette(model), chunk)
    chunks = max(1, round(seconds / (chunk * model.puppet_dt)))
    simulated = chunks * chunk * model.puppet_dt
    state = model.state()
    rollout.run(state, 0.0, 1)  # warm-up: modules loaded, graph captured and replayed once
    walls = []
    for _ in range(repeats):
        state = model.state()
        wp.synchronize_device(model.device)
        start = time.perf_counter()
        rollout.run(state, 0.0, chunks)
        wp.synchronize_device(model.device)
        walls.append(time.perf_counter() - start)
    joint_q = state.puppet.joint_q.numpy()
    if not np.all(np.isfinite(joint_q)):
        raise SystemExit(f"W = {worlds}: the rollout produced non-finite values")
    wall = statistics.median(walls)
    steps = simulated / model.string_dt
    return {"worlds": worlds, "wall_per_s": wall / simulated, "world_steps_per_s": worlds * steps / wall,
            "rtf_each": simulated / wall, "rtf_total": worlds * simulated / wall,
            "spread": (max(walls) - min(walls)) / wall, "particles": model.strings.particle_count // worlds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worlds", default="1,4,16,64,256", help="world counts, comma separated")
    parser.add_argument("--seconds", type=float, default=1.0, help="simulated seconds per run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--scene", default="hanging")
    parser.add_argument("--particles", type=int, default=None, help="particles per string (default: the scene's)")
    args = parser.parse_args()
    counts = [int(w) for w in args.worlds.split(",")]
    scene = dm.load_scene(args.scene)
    if args.particles is not None:
        scene = dataclasses.replace(scene, strings=tuple(dataclasses.replace(s, particle_count=args.particles)
                                                         for s in scene.strings))
    device = wp.get_device(args.device)
    print(f"# bench_worlds: {scene.name}, {len(scene.strings)} strings x {scene.strings[0].particle_count} particles, "
          f"strings {scene.string_hz:g} Hz, puppet {scene.puppet_hz:g} Hz; {args.seconds:g} s simulated per run, "
          f"median of {args.repeats}; device {device.name} ({device.alias}); {platform.processor() or platform.machine()}")
    print("| W | wall s per simulated s | world string steps/s | real-time factor each | total | efficiency | spread |")
    print("|---|---|---|---|---|---|---|")
    base = None
    for w in counts:
        r = time_worlds(scene, w, args.seconds, args.repeats, args.device)
        base = base if base is not None else r["rtf_total"]
        efficiency = r["rtf_total"] / base
        print(f"| {w} | {r['wall_per_s']:.4g} | {r['world_steps_per_s']:.4g} | {r['rtf_each']:.3g} | "
              f"{r['rtf_total']:.4g} | {efficiency:.2f} | {r['spread']:.0%} |", flush=True)


if __name__ == "__main__":
    main()
