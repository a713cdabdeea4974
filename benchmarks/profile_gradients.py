"""Where a marionette gradient's backward pass goes (issue 13): the taped re-run against the reverse
pass, and the string step's hand-written adjoint against its forward.

    .venv/bin/python benchmarks/profile_gradients.py [--seconds 4] [--repeats 3] [--no-lanes] [--clock wall|cpu]
        [--checkpoint-steps C]

Prints, for the ``hanging`` scene (6 x 50 particles, 1 kHz / 30 Hz, smoothed contact):

- the engine (``MarionetteGradient``, captured graphs): the forward, and the backward split into
  its captured taped re-runs, its captured reverse passes and the rest (host work between
  replays: checkpoints, inputs and seeds written in, gradients read out), each as a multiple
  of the forward (medians of ``--repeats``);
- one string step (300 particles) as captured graphs of 100 launches: the plain one-launch
  step, the same step keeping its pivot inverses (a taped step's), and its adjoint
  (``kernels/string_step_adjoint``), µs per launch (medians of 5 replays); with lanes (the
  default, ``SolverStringImplicit.lanes``) also the laned ones (``kernels/string_step_lanes``,
  ``kernels/string_step_adjoint_lanes``);
- the reverse pass of one taped puppet step (``SolverMarionette.step`` on a ``wp.Tape``), captured,
  by groups of its launches: all of them, without the string steps' adjoints, without those and
  the bar feedback's, and the feedback's and the puppet's implicit solve's alone (µs, medians of
  5 replays of 20). The arrays of one step stay in the cache here, unlike in the engine's segments.

``--no-lanes``: the string steps of the engine and of the puppet step with the scalar kernels.
``--checkpoint-steps C``: the engine's taped segments of ``C`` puppet steps (default: the engine's,
``ceil(sqrt(P))`` capped at ``SEGMENT_STRING_STEPS // substeps``).
``--clock cpu``: the captured launches (the one string step and the puppet step's reverse) timed by
the calling thread's CPU time (``time.thread_time``) instead of the wall clock (on a shared machine
it leaves out the time the thread waited for a core; Warp runs a CPU graph on the calling thread).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
import dmarionette.capture as capture  # noqa: E402
from dmarionette.grad.engine import MarionetteGradient  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

from bench_support import CLOCKS, add_clock_flag, graph_cost  # noqa: E402


class ChunkClock:
    """Times every ``CapturedChunk.run`` by chunk (the engine's re-run and reverse graphs)."""

    def __init__(self):
        self.times: dict[int, float] = {}
        self._run = capture.CapturedChunk.run

        def run(chunk):
            t0 = time.perf_counter()
            self._run(chunk)
            self.times[id(chunk)] = self.times.get(id(chunk), 0.0) + time.perf_counter() - t0

        capture.CapturedChunk.run = run


def _engine_split(model, seconds: float, repeats: int, clock: ChunkClock,
                  checkpoint_steps: int | None = None) -> dict[str, float]:
    engine = MarionetteGradient(model, int(round(seconds / model.puppet_dt)), checkpoint_steps=checkpoint_steps)
    inputs = engine.scene_inputs()
    rng = np.random.default_rng(0)
    weights = {k: rng.normal(size=s) for k, s in engine.output_shapes.items()}
    engine.forward(inputs)
    engine.backward(weights)  # plans and captures
    graphs = engine._taped._graphs.values()  # (re-run, reverse, tape) per segment length
    reruns, reverses = {id(g[0]) for g in graphs}, {id(g[1]) for g in graphs}
    rows = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        engine.forward(inputs)
        forward = time.perf_counter() - t0
        clock.times.clear()
        t0 = time.perf_counter()
        engine.backward(weights)
        backward = time.perf_counter() - t0
        rerun = sum(t for k, t in clock.times.items() if k in reruns)
        reverse = sum(t for k, t in clock.times.items() if k in reverses)
        rows.append({"forward": forward, "backward": backward, "rerun": rerun, "reverse": reverse,
                     "rest": backward - rerun - reverse})
    split = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    split["C"], split["segments"] = engine.checkpoint_steps, len(engine.segments)
    return split


CLOCK = time.perf_counter  # --clock cpu: time.thread_time


def _per_launch(launch, n: int = 100) -> float:
    """µs per ``launch()``, the median of 5 replays of a CPU graph of ``n`` launches (``--clock``)."""
    return graph_cost(launch, n, 5, clock=CLOCK, device="cpu") * 1e6


def _string_step(model) -> dict[str, float]:
    solver, strings = model.string_solver, model.strings
    state_in, state_out, control = strings.state(), strings.state(), strings.control()
    ws = solver.new_workspace(True)
    h = strings.scalar(model.string_dt)
    tape = wp.Tape()
    solver.record_step_adjoint(state_in, state_out, control, h, ws, tape)
    rows = {
        "plain step": _per_launch(lambda: solver.integrate_string_implicit(state_in, state_out, control, h,
                                                                           solver.workspace)),
        "taped step (keeps its pivots)": _per_launch(
            lambda: solver.integrate_string_implicit(state_in, state_out, control, h, ws, keep=True)),
        "its adjoint": _per_launch(tape.launches[-1]),
    }
    if solver.lanes:
        solver.record_step_adjoint(state_in, state_out, control, h, ws, tape, lanes=True)
        rows.update({
            "plain step, lanes": _per_launch(lambda: solver.integrate_string_lanes(state_in, state_out, control, h,
                                                                                  solver.workspace)),
            "taped step, lanes": _per_launch(
                lambda: solver.integrate_string_lanes(state_in, state_out, control, h, ws, keep=True)),
            "its adjoint, lanes": _per_launch(tape.launches[-1]),
        })
    return rows


def _reverse_by_group(model) -> dict[str, float]:
    from dmarionette.marionette.solver import MarionetteControl, SolverMarionette

    solver = SolverMarionette(model)
    a, b = model.state(requires_grad=True), model.state(requires_grad=True)
    control = MarionetteControl(model, requires_grad=True)
    tape = wp.Tape()
    with tape:
        solver.step(a, b, control, tape=tape)

    def name(launch):
        return "string adjoint" if callable(launch) else launch[0].key

    def reverse(keep) -> float:
        part = wp.Tape()
        part.launches = [launch for launch in tape.launches if keep(name(launch))]
        part.gradients = tape.gradients
        return _per_launch(part.backward, 20)

    feedback = [k for k in {name(launch) for launch in tape.launches} if "bar_feedback" in k]
    return {
        "all": reverse(lambda k: True),
        "without the string adjoints": reverse(lambda k: k != "string adjoint"),
        "without those and the feedback": reverse(lambda k: k != "string adjoint" and k not in feedback),
        "the feedback alone": reverse(lambda k: k in feedback),
        "solve_body_dynamics alone": reverse(lambda k: k == "solve_body_dynamics"),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-lanes", action="store_true", help="the scalar string kernels (plain and taped)")
    add_clock_flag(p, help="the captured launches' clock (cpu: the thread's CPU time)")
    p.add_argument("--checkpoint-steps", type=int, default=None, help="the engine's segment length C")
    args = p.parse_args()
    global CLOCK
    CLOCK = CLOCKS[args.clock]
    clock = ChunkClock()
    model = MarionetteModel(dm.load_scene("hanging"), requires_grad=True)
    model.string_solver.lanes = not args.no_lanes
    split = _engine_split(model, args.seconds, args.repeats, clock, args.checkpoint_steps)
    f = split["forward"]
    print(f"# hanging 6 x 50, {args.seconds:g} s rollout, C = {split['C']} ({split['segments']} segments), medians of "
          f"{args.repeats}, string steps {'scalar (--no-lanes)' if args.no_lanes else 'in lanes'}")
    print(f"forward {f:.3f} s; backward {split['backward']:.3f} s = {split['backward'] / f:.2f} forwards:")
    for name in ("rerun", "reverse", "rest"):
        print(f"  {name:8s} {split[name]:.3f} s  {split[name] / f:.2f} forwards")
    print(f"# one string step, 300 particles, captured (µs per launch, {args.clock} clock)")
    for name, us in _string_step(model).items():
        print(f"  {name:32s} {us:.1f}")
    print(f"# the reverse pass of one taped puppet step ({model.substeps} string steps), captured (µs, "
          f"{args.clock} clock)")
    for name, us in _reverse_by_group(model).items():
        print(f"  {name:32s} {us:.0f}")


if __name__ == "__main__":
    main()
