"""Where a whole-rollout JVP goes (issue 13 item 4): ``MarionetteGradient.jvp`` broken down by group
of launches, each as a share of one forward rollout.

    .venv/bin/python benchmarks/profile_tangent.py [--seconds 1] [--directions 1 4 16] [--repeats 5]
                                                   [--kernels] [--shipped-contact]

The scene is ``hanging`` as ``benchmarks/bench_gradients.py`` runs it (6 strings x 50 particles,
12 bodies, smoothed ground contact, joint limits and feedback on, 1 kHz / 30 Hz, string steps in
SIMD lanes), ``--seconds`` of rollout, P random directions in every input. For each P it times,
interleaved per repeat (medians of ``--repeats``; wall clock and the calling thread's CPU time,
``time.thread_time``: Warp replays a CPU graph on the calling thread, so the CPU time leaves out
the time the thread waited for a core on a shared machine):

- ``forward``: one ``MarionetteGradient.forward`` (captured graphs, host work included): the unit;
- ``JVP``: one :meth:`RolloutTangent.jvp` (what ``MarionetteGradient.jvp`` runs after its checks);
- its parts: :meth:`RolloutTangent.load` (host: constants, controls, start state and their
  tangents written in), the replay of the captured :meth:`RolloutTangent.launch` graph,
  :meth:`RolloutTangent.read` (host: outputs and tangents copied out), and the rest;
- the launches by group, each group captured alone as a graph of the rollout's launches of that
  group (the others left out: the numbers they compute are not the rollout's, the time is):

  - ``string forward (keep)``: the string steps keeping their factorisation (laned step and its
    unpacking into the scalar layout);
  - ``string tangent``: the string steps' tangent-linear kernel;
  - ``puppet generated``: the generated puppet tangent kernels (kinematics, dynamics,
    integration: ``kernels/articulation_tangent``), in the trial, the step and the pose outputs;
  - ``puppet forces/contact/points``: the interleaved tangents of the applied forces, the point
    springs, the contacts and the body points (``kernels/kernel_tangent``), and the kept contact
    tangents added into the puppet step's (``kernels/body_load_tangent``);
  - ``coupling``: the strings' response, the tie path and the anchors (interleaved tangents);
  - ``bar feedback``: eq. 4 and the exact reaction after every string step (interleaved);
  - ``primal only``: plain (forward) launches inside the JVP (the input's body points, the puppet
    step's contacts);
  - ``copies, zeroing``: ``wp.copy`` and ``array.zero_`` (outputs into their rows, resets);

  and the sum of the groups against the whole graph (their difference: what one launch costs in
  a bigger graph or a colder cache). ``--kernels``: also each kernel alone.

A group is told by its kernel's key (:data:`GROUPS`); a launch of no group shows as ``other``.

``--shipped-contact``: the scene's own (hard) contact instead of the smoothed one: a hard contact
skips the points apart from the ground, which are all of them in ``hanging``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import os
import platform
import statistics
import time

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.grad.engine import MarionetteGradient  # noqa: E402
from dmarionette.grad.rollout_tangent import RolloutTangent  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

# group -> substrings of the kernel keys it holds (the first group that matches wins)
GROUPS = {
    "string forward (keep)": ("integrate_string_lanes", "unpack_lane_factorisation", "integrate_string_implicit_kernel",
                              "integrate_string_implicit__"),
    "string tangent": ("integrate_string_implicit_tangent", "string_step_tangent"),
    "puppet generated": ("eval_body_kinematics_tangent", "solve_body_dynamics_tangent",
                         "integrate_joint_coordinates_tangent"),
    "puppet forces/contact/points": ("eval_body_external_forces_tangent", "eval_body_point_springs_tangent",
                                     "contact_tangent", "eval_body_points_tangent", "apply_body_load_tangents"),
    "coupling": ("eval_string_response", "eval_tie_path", "apply_string_forces_to_anchors"),
    "bar feedback": ("eval_bar_feedback",),
    "copies, zeroing": ("<copy>", "<zero_>"),
}
PRIMAL = "primal only"
OTHER = "other"


def group_of(key: str) -> str:
    """The group of a launch by its kernel key (``<copy>``, ``<zero_>`` for those operations)."""
    for name, parts in GROUPS.items():
        if any(p in key for p in parts):
            return name
    return PRIMAL if not key.endswith("_tangent") and "tangent" not in key else OTHER


@contextlib.contextmanager
def only(keep):
    """Within: ``wp.launch``, ``wp.copy`` and ``array.zero_`` run only where ``keep(key)`` (key: the
    kernel's, or ``<copy>``, ``<zero_>``); every key seen is counted into the yielded Counter."""
    launch, copy, zero = wp.launch, wp.copy, wp.array.zero_
    seen = collections.Counter()

    def launch_(kernel, *a, **k):
        seen[kernel.key] += 1
        if keep(kernel.key):
            launch(kernel, *a, **k)

    def copy_(*a, **k):
        seen["<copy>"] += 1
        if keep("<copy>"):
            copy(*a, **k)

    def zero_(self):
        seen["<zero_>"] += 1
        if keep("<zero_>"):
            zero(self)

    wp.launch, wp.copy, wp.array.zero_ = launch_, copy_, zero_
    try:
        yield seen
    finally:
        wp.launch, wp.copy, wp.array.zero_ = launch, copy, zero


def capture(fn, keep) -> tuple[object, collections.Counter]:
    """``fn``'s launches that ``keep`` keeps, captured as one graph; and the launches it saw, by key."""
    with only(keep) as seen:
        with wp.ScopedCapture() as c:
            fn()
    return c.graph, seen


def timed(fn) -> tuple[float, float]:
    """Wall and thread CPU seconds of one ``fn()``."""
    w, c = time.perf_counter(), time.thread_time()
    fn()
    return time.perf_counter() - w, time.thread_time() - c


def profile(seconds: float, directions: int, repeats: int, kernels: bool, smooth: bool = True) -> dict:
    scene = dm.load_scene("hanging")
    if smooth:
        scene = dataclasses.replace(scene, contact=dict(scene.contact, smooth=True))
    model = MarionetteModel(scene, requires_grad=True)
    engine = MarionetteGradient(model, round(seconds / model.puppet_dt))
    inputs = engine.check_inputs(engine.scene_inputs())
    rng = np.random.default_rng(0)
    tangents = {k: rng.normal(size=(directions, *s)) * 1e-3 for k, s in engine.input_shapes.items()}
    rt = RolloutTangent(engine, directions)
    engine.forward(inputs)
    rt.jvp(inputs, tangents)  # compiles, captures the whole graph
    whole, seen = capture(rt.launch, lambda key: True)
    groups = {g: capture(rt.launch, lambda key, g=g: group_of(key) == g)[0]
              for g in sorted({group_of(k) for k in seen}, key=_order)}
    singles = {k: capture(rt.launch, lambda key, k=k: key == k)[0] for k in seen} if kernels else {}
    t = collections.defaultdict(list)
    for _ in range(repeats):
        t["forward"].append(timed(lambda: engine.forward(inputs)))
        t["JVP"].append(timed(lambda: rt.jvp(inputs, tangents)))
        t["load (host)"].append(timed(lambda: rt.load(inputs, tangents)))
        t["launches (graph)"].append(timed(lambda: wp.capture_launch(whole)))
        t["read (host)"].append(timed(rt.read))
        for name, graph in (*groups.items(), *singles.items()):
            t[name].append(timed(lambda graph=graph: wp.capture_launch(graph)))
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in t.items()}
    counts = collections.Counter()
    for k, v in seen.items():
        counts[group_of(k)] += v
    return {"P": directions, "steps": engine.puppet_steps, "median": med, "groups": list(groups),
            "counts": counts, "seen": seen, "singles": list(singles)}


def _order(group: str) -> int:
    names = [*GROUPS, PRIMAL, OTHER]
    return names.index(group)


def report(r: dict) -> None:
    med = r["median"]
    fw, fc = med["forward"]

    def row(label, name, count=""):
        w, c = med[name]
        print(f"| {label} | {count} | {1e3 * w:.2f} | {w / fw:.2f} | {1e3 * c:.2f} | {c / fc:.2f} |")

    print(f"\n### P = {r['P']} ({r['steps']} puppet steps)\n")
    print("| part | launches | wall [ms] | / forward (wall) | thread CPU [ms] | / forward (CPU) |")
    print("| --- | --- | --- | --- | --- | --- |")
    row("forward (unit)", "forward")
    row("**JVP**", "JVP")
    row("load (host)", "load (host)")
    row("launches (captured graph)", "launches (graph)", sum(r["seen"].values()))
    row("read (host)", "read (host)")
    rest = tuple(med["JVP"][i] - sum(med[k][i] for k in ("load (host)", "launches (graph)", "read (host)"))
                 for i in (0, 1))
    print(f"| rest of jvp (host) | | {1e3 * rest[0]:.2f} | {rest[0] / fw:.2f} | {1e3 * rest[1]:.2f} | "
          f"{rest[1] / fc:.2f} |")
    for g in r["groups"]:
        row(f"group: {g}", g, r["counts"][g])
    total = tuple(sum(med[g][i] for g in r["groups"]) for i in (0, 1))
    print(f"| sum of the groups alone | | {1e3 * total[0]:.2f} | {total[0] / fw:.2f} | {1e3 * total[1]:.2f} | "
          f"{total[1] / fc:.2f} |")
    for k in sorted(r["singles"], key=lambda k: -med[k][1]):
        row(f"kernel: {k}", k, r["seen"][k])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=1.0)
    p.add_argument("--directions", type=int, nargs="+", default=[1, 4, 16])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--kernels", action="store_true", help="also each kernel alone")
    p.add_argument("--shipped-contact", action="store_true", help="the scene's hard contact, not the smoothed")
    args = p.parse_args()
    print(f"# {platform.processor() or platform.machine()}, warp {wp.__version__}, hanging 6 x 50, 1 kHz / 30 Hz, "
          f"{'shipped (hard)' if args.shipped_contact else 'smoothed'} contact, {args.seconds:g} s, medians of {args.repeats}; load average at start "
          f"{os.getloadavg()[0]:.2f}")
    for d in args.directions:
        report(profile(args.seconds, d, args.repeats, args.kernels, not args.shipped_contact))
    print(f"\nload average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
