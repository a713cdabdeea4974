"""Cost of checkpointed marionette gradients (``MarionetteGradient``): time and memory.

Run:  python benchmarks/bench_gradients.py [--seconds 1 4 16] [--memory-seconds 60] [--repeats 3] [--no-lanes]
      [--jvp [1 4 12 16]]

The scene is ``hanging`` (6 strings x 50 particles, 12 bodies, ground contact on and
smoothed, joint limits and feedback on) at the paper's rates (strings 1 kHz, puppet 30 Hz),
with its swaying bars; the loss cotangents are ones on every output. Each rollout length
runs in its own process (so that its peak memory is its own), on one core (the kernels are
serial on the CPU). Reported per length, medians over ``--repeats``:

- ``forward``: ``MarionetteGradient.forward`` (captured graphs of ``C`` puppet steps, the
  checkpoints copied out, the outputs copied to the host);
- ``backward``: ``MarionetteGradient.backward`` (per segment: the captured taped re-run,
  the cotangent seeds written in, the captured reverse pass, the gradients read out);
- ``backward, no capture``: the same with ``capture=False`` (every launch from Python), at
  the shortest length only, to show what capture buys;
- ``backward / forward``: the median over the repeats of each backward's time over the
  forward run just before it (adjacent in time, so that a changing machine load cancels);
- memory: the bytes the engine allocates for gradients (``engine.memory()``: the taped
  segment's arrays and gradients, the checkpoints, the host outputs), and the process's
  peak resident set (``ru_maxrss``) above its size after the model was built and the
  kernels loaded (a coarser number: it includes Python objects of the tape and the graphs).

``--jvp P...``: a second table, forward mode (``MarionetteGradient.jvp``, issue 13 item 4) at the
shortest length: for each P the JVP of the rollout along P random directions in every input
(one rollout carrying all P tangents), its median time, and ``JVP / forward``: the median over
the repeats of each JVP's time over the (captured) forward run just before it, against the
target ``1 + 0.5 P``; also the forward without capture (every launch from Python, as the JVP
launches its passes) for scale.

The string steps run in SIMD lanes (``SolverStringImplicit.lanes``, the default: the plain step
and the taped one with its laned adjoint); ``--no-lanes``: the scalar kernels.

The first run compiles the puppet kernels at -O2 (about a minute; cached afterwards).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402
from dmarionette.grad.engine import MarionetteGradient  # noqa: E402

from bench_support import time_forward_backward, time_interleaved  # noqa: E402

MIB = 2**20


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / MIB


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _hanging_smooth(seconds: float, lanes: bool) -> tuple[MarionetteModel, int]:
    """The ``hanging`` scene with smooth contact, taped (``requires_grad``), and its puppet steps in
    ``seconds``; ``lanes``: the string steps in SIMD lanes."""
    scene = dm.load_scene("hanging")
    scene = dataclasses.replace(scene, contact=dict(scene.contact, smooth=True))
    model = MarionetteModel(scene, requires_grad=True)
    model.string_solver.lanes = lanes
    return model, round(seconds / model.puppet_dt)


def one(seconds: float, repeats: int, capture: bool, checkpoint_steps: int | None = None, lanes: bool = True) -> dict:
    model, steps = _hanging_smooth(seconds, lanes)
    engine = MarionetteGradient(model, steps, capture=capture, checkpoint_steps=checkpoint_steps)
    inputs = engine.scene_inputs()
    cot = {k: np.ones(s) for k, s in engine.output_shapes.items()}
    base = _rss_mib()
    start = time.perf_counter()
    engine.forward(inputs)
    engine.backward(cot)  # plans the taped segments and captures their graphs
    first = time.perf_counter() - start
    forward, backward = time_forward_backward(engine, inputs, cot, repeats)
    mem = engine.memory()
    return {"seconds": seconds, "puppet_steps": steps, "string_steps": engine.string_steps,
            "checkpoint_steps": engine.checkpoint_steps, "segments": len(engine.segments), "capture": capture,
            "forward_s": statistics.median(forward), "backward_s": statistics.median(backward),
            "ratio": statistics.median(b / f for f, b in zip(forward, backward)),
            "spread_backward": (max(backward) - min(backward)) / statistics.median(backward),
            "first_s": first, "tape_mib": mem["tape"] / MIB, "checkpoints_mib": mem["checkpoints"] / MIB,
            "outputs_mib": mem["outputs"] / MIB, "rss_above_model_mib": _peak_mib() - base}


def one_jvp(seconds: float, repeats: int, directions: list[int], lanes: bool = True) -> list[dict]:
    """The JVP rows (module doc): ``seconds`` of rollout, each P in ``directions``."""
    model, steps = _hanging_smooth(seconds, lanes)
    engine = MarionetteGradient(model, steps)
    plain = MarionetteGradient(model, steps, capture=False)
    inputs = engine.scene_inputs()
    rng = np.random.default_rng(0)
    rows = []
    for p in directions:
        tangents = {k: rng.normal(size=(p, *shape)) * 1e-3 for k, shape in engine.input_shapes.items()}
        engine.forward(inputs)
        plain.forward(inputs)
        engine.jvp(inputs, tangents)  # builds the tangent kernels and arrays for this P
        forward, jvp, uncaptured = time_interleaved(
            [lambda: engine.forward(inputs), lambda t=tangents: engine.jvp(inputs, t), lambda: plain.forward(inputs)],
            repeats)
        rows.append({"seconds": seconds, "puppet_steps": steps, "P": p, "forward_s": statistics.median(forward),
                     "forward_uncaptured_s": statistics.median(uncaptured), "jvp_s": statistics.median(jvp),
                     "ratio": statistics.median(j / f for f, j in zip(forward, jvp))})
    return rows


LANES = True  # --no-lanes: False


def _run(seconds: float, repeats: int, capture: bool = True, checkpoint_steps: int | None = None) -> dict:
    cmd = [sys.executable, __file__, "--one", str(seconds), "--repeats", str(repeats)]
    if not LANES:
        cmd.append("--no-lanes")
    if not capture:
        cmd.append("--no-capture")
    if checkpoint_steps:
        cmd += ["--checkpoint-steps", str(checkpoint_steps)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, nargs="+", default=[1.0, 4.0, 16.0])
    p.add_argument("--memory-seconds", type=float, default=60.0, help="one longer rollout (0: skip)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--one", type=float, help=argparse.SUPPRESS)
    p.add_argument("--no-capture", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--checkpoint-steps", type=int, nargs="*", default=[],
                   help="also run every length with these segment lengths C (besides the default sqrt(P))")
    p.add_argument("--no-lanes", action="store_true", help="the scalar string kernels (plain and taped)")
    p.add_argument("--jvp", type=int, nargs="*", default=None,
                   help="also the forward-mode cost at the shortest length for these direction counts P "
                        "(no values: 1 4 12 16)")
    p.add_argument("--one-jvp", type=float, help=argparse.SUPPRESS)
    args = p.parse_args()
    global LANES
    LANES = not args.no_lanes
    if args.one_jvp is not None:
        print(json.dumps(one_jvp(args.one_jvp, args.repeats, args.jvp, LANES)))
        return
    if args.one is not None:
        c = args.checkpoint_steps[0] if args.checkpoint_steps else None
        print(json.dumps(one(args.one, args.repeats, not args.no_capture, c, LANES)))
        return
    print(f"# {platform.processor() or platform.machine()}, warp {wp.__version__}, hanging scene 6 x 50, "
          f"1 kHz / 30 Hz, smoothed contact, string steps {'in lanes' if LANES else 'scalar (--no-lanes)'}")
    rows = []
    for s in args.seconds:
        rows.append(_run(s, args.repeats))
        rows += [_run(s, args.repeats, checkpoint_steps=c) for c in args.checkpoint_steps]
    if args.memory_seconds:
        rows.append(_run(args.memory_seconds, 1))
        rows += [_run(args.memory_seconds, 1, checkpoint_steps=c) for c in args.checkpoint_steps]
    rows.append(_run(min(args.seconds), args.repeats, capture=False))
    print("| rollout | P | C | forward [s] | backward [s] | backward / forward | tape [MiB] | checkpoints [MiB] "
          "| outputs [MiB] | peak RSS above model [MiB] |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        label = f"{r['seconds']:g} s" + ("" if r["capture"] else " (no capture)")
        print(f"| {label} | {r['puppet_steps']} | {r['checkpoint_steps']} | {r['forward_s']:.3f} | "
              f"{r['backward_s']:.3f} | {r['ratio']:.1f} | {r['tape_mib']:.1f} | "
              f"{r['checkpoints_mib']:.2f} | {r['outputs_mib']:.1f} | {r['rss_above_model_mib']:.0f} |")
    print("\nfirst backward (plans the segments, captures their graphs):",
          ", ".join(f"{r['seconds']:g} s: {r['first_s']:.1f} s" for r in rows))
    if args.jvp is not None:
        directions = args.jvp or [1, 4, 12, 16]
        cmd = [sys.executable, __file__, "--one-jvp", str(min(args.seconds)), "--repeats", str(args.repeats),
               "--jvp", *map(str, directions)] + ([] if LANES else ["--no-lanes"])
        jvp_rows = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip()
                              .splitlines()[-1])
        print("\n| rollout | P directions | forward [s] | forward, no capture [s] | JVP [s] | JVP / forward "
              "| target 1 + 0.5 P |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for r in jvp_rows:
            print(f"| {r['seconds']:g} s | {r['P']} | {r['forward_s']:.3f} | {r['forward_uncaptured_s']:.3f} | "
                  f"{r['jvp_s']:.3f} | {r['ratio']:.1f} | {1 + 0.5 * r['P']:g} |")


if __name__ == "__main__":
    main()
