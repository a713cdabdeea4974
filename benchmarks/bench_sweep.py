"""Sweep throughput in this process against Ray with 1 and 2 workers, and what a Ray task costs.

Run:  python benchmarks/bench_sweep.py [--variants 8] [--duration 2] [--repeats 3] [--particles 50]

- **Sweep**: ``--variants`` variants of the shipped ``hanging`` scene (eq. 2 ``k`` from 200 N/m
  up, ``--particles`` per string, ``--duration`` s each), run as ``dmarionette sweep`` runs them:
  ``run_variants`` per variant through ``dmarionette.scale.imap_variants``, in this process
  (``off``) and on the embedded local Ray cluster with 1 and 2 workers. Each Ray run starts its
  actors (they import dmarionette, start Warp and load the kernels from the cache: ``setup``) and
  kills them at the end, as a sweep does; that start is in the time. The cluster itself is started
  once before (its start is reported on its own line).
- **Per-task overhead**: a function that does nothing, ``--tasks`` items on 1 warm worker: the time
  from the first result's arrival to the last one's, over ``tasks - 1``, is what one more item costs
  (submit, run, return), without the worker's start.
- **Actor start**: the wall time of one such no-op item on a fresh worker, with and without the
  sweep's ``setup`` (Warp and the kernels loaded).

Every number is the median over ``--repeats`` runs; the modes are interleaved run by run so that
the machine's load (printed: the 1-minute load average before and after) affects them alike.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import platform
import statistics
import time

from dmarionette.scale import imap_variants, start_local_ray
from dmarionette.scene.scene import load_scene
from dmarionette.sweep import run_variants
from dmarionette.sweep.run import warm_up


def nothing(item):
    """A task that does no work (the overhead's probe)."""
    return item


def variants(count: int, particles: int):
    base = load_scene("hanging")
    scenes = []
    for i in range(count):
        strings = tuple(dataclasses.replace(s, particle_count=particles, tie_stiffness=200.0 + 25.0 * i)
                        for s in base.strings)
        scenes.append(dataclasses.replace(base, strings=strings))
    return scenes


def timed(fn, items, ray: str, workers: int | None, setup) -> float:
    """Wall time [s] of a whole map (workers started and stopped in it)."""
    start = time.perf_counter()
    for _ in imap_variants(fn, items, ray=ray, workers=workers, setup=setup):
        pass
    return time.perf_counter() - start


def per_task(count: int) -> float:
    """Seconds per item between the first and the last result of ``count`` no-op items on 1 worker."""
    arrivals = [time.perf_counter() for _ in imap_variants(nothing, range(count), ray="local", workers=1)]
    return (arrivals[-1] - arrivals[0]) / (count - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", type=int, default=8)
    parser.add_argument("--duration", type=float, default=2.0, help="simulated seconds per variant")
    parser.add_argument("--particles", type=int, default=50, help="particles per string")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tasks", type=int, default=500, help="no-op tasks for the per-task overhead")
    args = parser.parse_args()

    scenes = variants(args.variants, args.particles)
    setup = functools.partial(warm_up, scenes[0], 2)
    warm_up(scenes[0], 2)  # this process's kernels (and the cache the workers load from)
    fn = functools.partial(run_variants, duration=args.duration)
    items = [[scene] for scene in scenes]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    start_local_ray(workers=2)
    ray_start = time.perf_counter() - start
    modes = {"in-process": ("off", None), "Ray, 1 worker": ("local", 1), "Ray, 2 workers": ("local", 2)}
    sweep = {name: [] for name in modes}
    one, overhead, actor = [], [], []
    for _ in range(args.repeats):
        for name, (ray, workers) in modes.items():
            sweep[name].append(timed(fn, items, ray, workers, setup))
        actor.append(timed(nothing, [0], "local", 1, setup))
        one.append(timed(nothing, [0], "local", 1, None))
        overhead.append(per_task(args.tasks))
    load_after = os.getloadavg()[0]
    import ray

    ray.shutdown()

    simulated = args.variants * args.duration
    base = statistics.median(sweep["in-process"])
    print(f"# sweep throughput: {args.variants} variants of hanging, {args.particles} particles per string, "
          f"{args.duration:g} s each ({platform.node()}, {os.cpu_count()} CPUs, load {load_before:.1f} before, "
          f"{load_after:.1f} after; medians of {args.repeats})\n")
    print("| mode | sweep wall [s] | variants / min | simulated s / wall s | speed-up |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, times in sweep.items():
        t = statistics.median(times)
        print(f"| {name} | {t:.2f} | {60.0 * args.variants / t:.1f} | {simulated / t:.2f} | {base / t:.2f} |")
    print(f"\nlocal cluster start: {ray_start:.1f} s; actor start with the kernels loaded (setup): "
          f"{statistics.median(actor):.2f} s; without: {statistics.median(one):.2f} s; per-task overhead: "
          f"{1e3 * statistics.median(overhead):.2f} ms ({args.tasks} no-op tasks on 1 warm worker)")
    print(json.dumps({"sweep_s": sweep, "ray_start_s": ray_start, "actor_start_s": actor, "one_task_s": one,
                      "per_task_s": overhead, "tasks": args.tasks, "load": [load_before, load_after]}))


if __name__ == "__main__":
    main()
