"""Where the time of a string step and of a marionette step goes: the cost of each pass.

Run:  python benchmarks/profile_steps.py [--repeats 9] [--puppet-hz 30 1000] [--live-ticks 3000] [--no-lanes]

Each pass (a solver method, as ``SolverStringImplicit.step`` and ``SolverMarionette.step`` call
it) is captured ``R`` times in a row as one CPU graph and replayed ``--repeats`` times; the
figure is the *minimum* over the replays of the calling thread's CPU time
(``time.thread_time``) per pass: the thread's own cost, the least disturbed by other processes
on a shared machine (wall-clock medians are for ``bench_strings.py``/``bench_marionette.py``).
``empty launch`` is a kernel that does nothing, for the fixed cost of one launch in a graph.

Strings: the ``strings`` scene (6 x 50 particles, float64, all effects on): the five passes of
the taped step (spring, system, solve, integrate, tie force) one by one and together, and the
plain step (``step``: one launch; ``kernels/string_step_lanes``, four strings per thread, and
with ``lanes = False`` the scalar ``kernels/string_step``; before issue 19, the five passes). Marionette: the ``hanging`` scene at each ``--puppet-hz``, per puppet step and
per simulated millisecond: the passes of ``SolverMarionette.step``. Live: the wall and CPU
time of one live tick (``LiveMarionette.advance``, as the servo loop's physics calls it).
The marionette and live steps run the default laned string kernel (``SolverStringImplicit.lanes``);
``--no-lanes``: the scalar one instead. Per puppet rate, also the puppet step's own passes, and the
wall time of ``MarionetteRollout.run`` against its captured chunks replayed alone (the host work
between replays).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette  # noqa: E402
from dmarionette.strings.model import StringModel  # noqa: E402
from dmarionette.strings.solver import SolverStringImplicit  # noqa: E402

from bench_support import graph_cost  # noqa: E402


@wp.kernel
def _empty(
    # State out:
    a: wp.array(dtype=wp.int32),
):
    wp.tid()


def cost(fn, count: int, repeats: int) -> float:
    """Least thread CPU time [s] of one ``fn()`` replayed from a graph of ``count`` calls."""
    return graph_cost(fn, count, repeats, least=True)


def profile_strings(repeats: int) -> None:
    scene = dm.load_scene("strings")
    model = StringModel(scene.strings, effects=scene.effects, gravity=scene.gravity,
                        ground_height=scene.ground_height)
    solver = SolverStringImplicit(model)
    a, b, control = model.state(), model.state(), model.control()
    h, ws = model.scalar(1e-3), solver.workspace
    forced = solver.new_workspace(taped=False).segment_active  # zeros: no segment forced
    flags = wp.zeros(model.particle_count, dtype=wp.int32)
    for _ in range(3):
        solver.step(a, b, control, 1e-3)
        a.assign(b)

    def plain_step(lanes: bool):
        solver.lanes = lanes  # read when the step is captured: the graph holds that kernel
        solver.step(a, b, control, 1e-3)

    def five():
        solver.eval_string_spring(a, forced, ws)
        solver.eval_string_system(a, control, h, ws)
        solver.solve_string_system(ws, None)
        solver.integrate_string(a, b, control, h, ws)
        solver.eval_string_tie_force(b, control)

    rows = [
        ("empty launch (dim = particles)", lambda: wp.launch(_empty, dim=model.particle_count, outputs=[flags])),
        ("eval_string_spring", lambda: solver.eval_string_spring(a, forced, ws)),
        ("eval_string_system", lambda: solver.eval_string_system(a, control, h, ws)),
        ("solve_string_system", lambda: solver.solve_string_system(ws, None)),
        ("integrate_string", lambda: solver.integrate_string(a, b, control, h, ws)),
        ("eval_string_tie_force", lambda: solver.eval_string_tie_force(b, control)),
        ("the five passes", five),
        ("step (plain, scalar kernel: lanes off)", lambda: plain_step(False)),
        ("step (plain, lanes)", lambda: plain_step(True)),
    ]
    print(f"## Strings: 6 x 50 float64, thread CPU time per pass (min of {repeats})\n")
    print("| pass | µs | ns per particle |")
    print("|---|---:|---:|")
    for name, fn in rows:
        seconds = cost(fn, 1000, repeats)
        print(f"| {name} | {seconds * 1e6:.2f} | {seconds * 1e9 / model.particle_count:.1f} |")


LANES = True  # --no-lanes: False (the marionette and live steps)


def profile_marionette(puppet_hz: float, repeats: int) -> None:
    scene = dataclasses.replace(dm.load_scene("hanging"), puppet_hz=puppet_hz)
    model = MarionetteModel(scene, optimization_level=2)
    model.string_solver.lanes = LANES
    solver = SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    for _ in range(3):
        solver.step(a, b, control)
        a.assign(b)
    n, ws = model.substeps, solver.workspace
    rows = [
        ("step (all passes)", lambda: solver.step(a, b, control)),
        ("eval_body_points", lambda: solver.eval_body_points(a, ws.points)),
        ("predict_body_points (the trial puppet step)", lambda: solver.predict_body_points(a, ws)),
        ("begin_step (the two above + the tie path)", lambda: solver.begin_step(a, b)),
        (f"{n} x step_string (string step + feedback)",
         lambda: [solver.step_string(a, b, control, j) for j in range(n)]),
        (f"{n} x eval_bar_feedback", lambda: [solver.eval_bar_feedback(b.strings, control, b, j) for j in range(n)]),
        ("end_step (anchors + the puppet step)", lambda: solver.end_step(a, b)),
    ]
    # The puppet step's own passes (SolverArticulation.step), on the workspace the step just used.
    ps, pw, pc = model.puppet_solver, ws.puppet_workspace, ws.puppet_control
    h, hi = ps.step_sizes(model.puppet_dt)
    rows += [
        ("  puppet step: eval_kinematics", lambda: ps.eval_kinematics(a.puppet, pw)),
        ("  puppet step: eval_external_forces", lambda: ps.eval_external_forces(pw, pc)),
        ("  puppet step: eval_point_springs", lambda: ps.eval_point_springs(pw, pc, hi)),
        ("  puppet step: eval_contacts (ground)", lambda: ps.eval_contacts(pw, hi)),
        ("  puppet step: solve_dynamics", lambda: ps.solve_dynamics(a.puppet, b.puppet, pc, pw, h, hi)),
        ("  puppet step: integrate", lambda: ps.integrate(a.puppet, b.puppet, h)),
    ]
    print(f"\n## Marionette 'hanging', strings {scene.string_hz:g} Hz, puppet {puppet_hz:g} Hz "
          f"(n = {n}), thread CPU time (min of {repeats})\n")
    print("| pass | µs per puppet step | µs per simulated ms |")
    print("|---|---:|---:|")
    for name, fn in rows:
        seconds = cost(fn, max(1, 300 // n), repeats)
        print(f"| {name} | {seconds * 1e6:.1f} | {seconds / model.puppet_dt * 1e3:.2f} |")


def profile_rollout(puppet_hz: float, seconds: float = 5.0) -> None:
    """``MarionetteRollout.run`` against replaying its captured chunks alone: the host work between
    replays (bar inputs in, outputs out), wall time per simulated ms, medians of 5."""
    import statistics

    from dmarionette.marionette.rollout import MarionetteRollout

    scene = dataclasses.replace(dm.load_scene("hanging"), puppet_hz=puppet_hz)
    model = MarionetteModel(scene, optimization_level=2)
    model.string_solver.lanes = LANES
    chunk = max(1, round(1.0 / (30.0 * model.puppet_dt)))  # one picture frame, as simulate does
    rollout = MarionetteRollout(SolverMarionette(model), chunk)
    chunks = max(1, round(seconds / (chunk * model.puppet_dt)))
    state = model.state()
    rollout.run(state, 0.0, 1)  # capture
    ms = chunks * chunk * model.puppet_dt * 1e3
    replay, run = [], []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(chunks):
            rollout._chunk.run()
        replay.append((time.perf_counter() - start) / ms)
        start = time.perf_counter()
        rollout.run(state, 0.0, chunks)
        run.append((time.perf_counter() - start) / ms)
    print(f"\n## Rollout 'hanging', puppet {puppet_hz:g} Hz ({chunk} puppet steps per chunk), wall µs per "
          f"simulated ms, median of 5\n")
    print(f"chunk replays alone {statistics.median(replay) * 1e6:.1f}, MarionetteRollout.run "
          f"{statistics.median(run) * 1e6:.1f}")


def profile_live_tick(ticks: int) -> None:
    """``LiveMarionette.advance`` (one string step per tick, the puppet passes at the first and last
    tick of a puppet step), the bars on their scene trajectories: median wall and thread CPU time."""
    import numpy as np

    from dmarionette.live.physics import LiveMarionette
    from dmarionette.marionette.solver import bar_inputs

    model = MarionetteModel(dm.load_scene("hanging"), optimization_level=2)
    model.string_solver.lanes = LANES
    live = LiveMarionette(model)
    times = model.string_dt * np.arange(1, ticks + 1)
    tops, bar_q, bar_qd = bar_inputs(model, times)
    for k in range(model.substeps):  # warm-up (graphs captured on construction)
        live.advance(tops[k], bar_q[k], bar_qd[k])
    wall, cpu = [], []
    for k in range(model.substeps, ticks):
        w, c = time.perf_counter(), time.thread_time()
        live.advance(tops[k], bar_q[k], bar_qd[k])
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - w)
    print(f"\n## Live tick ('hanging', LiveMarionette.advance, {ticks - model.substeps} ticks)\n")
    print(f"median wall {np.median(wall) * 1e6:.1f} µs, median thread CPU {np.median(cpu) * 1e6:.1f} µs, "
          f"p99 wall {np.percentile(wall, 99) * 1e6:.1f} µs")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=9, help="replays of each captured pass (the least is kept)")
    p.add_argument("--puppet-hz", type=float, nargs="*", default=[30.0, 1000.0],
                   help="puppet rates of the marionette profiles (none: skip them)")
    p.add_argument("--live-ticks", type=int, default=3000, help="ticks of the live-tick timing (0: skip)")
    p.add_argument("--no-lanes", action="store_true", help="marionette and live: the scalar string kernel")
    args = p.parse_args()
    global LANES
    LANES = not args.no_lanes
    print(f"# Step profile — Warp {wp.config.version}, CPU (one thread); marionette string lanes "
          f"{'on' if LANES else 'off'}\n")
    profile_strings(args.repeats)
    for hz in args.puppet_hz:
        profile_marionette(hz, args.repeats)
        profile_rollout(hz)
    if args.live_ticks:
        profile_live_tick(args.live_ticks)


if __name__ == "__main__":
    main()
